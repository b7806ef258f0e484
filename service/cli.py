"""``cellcal`` command line: thin commands over the library.

Every error prints one line on stderr and exits non-zero; no traceback reaches a user
(set ``CELLCAL_DEBUG=1`` to see one).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from calib.handeye import METHODS, calibrate_hand_eye
from drivers.errors import DeviceError

EXIT_USAGE = 2
EXIT_FAILED = 1


def _calibrate(args: argparse.Namespace) -> int:
    from service.results import hand_eye_result_json
    from service.stationset import load_station_set

    stations = load_station_set(args.station_dir)
    if not stations.pose_only:
        raise ValueError(
            f"{args.station_dir}: stations with images need the image pipeline, which this "
            "version does not have yet; give each station a 'target_pose' (cam_T_target)")
    P, C = stations.pose_arrays()
    options = {"estimate_kappa": args.estimate_kappa}
    result = calibrate_hand_eye(P, C, setup=stations.setup, method=args.method, **options)
    doc = hand_eye_result_json(result, [s.id for s in stations.stations], options=options,
                               command=" ".join(["cellcal", *sys.argv[1:]]))
    text = json.dumps(doc, indent=2)
    if args.out in (None, "-"):
        print(text)
    else:
        Path(args.out).write_text(text + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _demo(args: argparse.Namespace) -> int:
    from service.demo import run_demo

    run_demo(seed=args.seed, stations=args.stations)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cellcal",
        description="Camera and hand-eye calibration for robot cells. Units: metres and "
                    "radians in all files; see docs/conventions.md.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    cal = sub.add_parser(
        "calibrate", help="calibrate a station set directory (stations.json)",
        description="Compute the hand-eye transform (and target pose) from a station set. "
                    "Default method 'joint': screw motions (SM), then a weighted least-squares "
                    "refinement over all stations that also reports standard deviations.")
    cal.add_argument("station_dir", help="directory holding stations.json")
    cal.add_argument("--out", help="result JSON path (default: stdout)")
    cal.add_argument("--method", default="joint", choices=METHODS,
                     help="solver (default: joint)")
    cal.add_argument("--estimate-kappa", action="store_true",
                     help="also estimate the board scale kappa (joint only)")
    cal.set_defaults(func=_calibrate)

    demo = sub.add_parser("demo", help="simulate a cell, calibrate it, compare with the truth")
    demo.add_argument("--seed", type=int, default=1)
    demo.add_argument("--stations", type=int, default=15)
    demo.set_defaults(func=_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (ValueError, DeviceError, OSError) as exc:
        if os.environ.get("CELLCAL_DEBUG"):
            raise
        print(f"cellcal: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, ValueError) else EXIT_FAILED
    except KeyboardInterrupt:
        print("cellcal: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # last line of defence: never show a traceback
        if os.environ.get("CELLCAL_DEBUG"):
            raise
        print(f"cellcal: internal error ({type(exc).__name__}: {exc}); "
              "rerun with CELLCAL_DEBUG=1 and report it", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
