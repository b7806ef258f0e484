"""Write a cellcal/result@1 document (from 'cellcal calibrate' or GET /calibrations/{id}) in
another format. Camera formats (opencv-yaml, ros-camera-info) need a camera model; transform
formats (urdf, ur-pose, ros2-static-tf) need a hand-eye: a result without one says which formats
it has.
"""

# ``cellcal export RESULT.json --format FMT``: a result document as the file a user's stack reads
# (``service.exports``), the same files as ``GET /calibrations/{id}/export``.

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from calib import Result, parse_result
from service.cli.files import read_json
from service.exports import FORMATS, ExportNames, export, formats_help


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``export`` command's arguments."""
    parser.add_argument("result", help="result JSON file")
    parser.add_argument("--format", required=True, choices=FORMATS, dest="fmt",
                        help=formats_help())
    parser.add_argument("--out", help="output file (default: stdout)")
    parser.add_argument("--camera-name", default="camera",
                        help="ROS camera_name, prefix of the URDF joint and the ROS 2 node "
                             "(default camera)")
    parser.add_argument("--parent-frame",
                        help="frame the camera is fixed to (default tool0 eye-in-hand, base "
                             "eye-to-hand)")
    parser.add_argument("--child-frame",
                        help="the camera's frame (default <camera-name>_optical_frame)")


def read_result(path: str) -> Result:
    """A ``cellcal/result@1`` document from a file; ValueError naming what is wrong."""
    doc = read_json(Path(path))
    match doc:
        case {"format": "cellcal/result@1"}:
            return parse_result(doc, path)
        case _:
            raise ValueError(f"{path}: not a cellcal result (expected \"format\": "
                             "\"cellcal/result@1\")")


def run(args: argparse.Namespace) -> int:
    """Write ``args.result`` in ``args.fmt``."""
    names = ExportNames(args.camera_name, parent_frame=args.parent_frame,
                        child_frame=args.child_frame)
    content, _, _ = export(read_result(args.result), args.fmt, names)
    if args.out in (None, "-"):
        sys.stdout.write(content)
    else:
        Path(args.out).write_text(content)
        print(f"wrote {args.out}", file=sys.stderr)
    return 0
