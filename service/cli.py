"""``cellcal`` command line: thin commands over the library.

Every error prints one line on stderr and exits non-zero; no traceback reaches a user
(set ``CELLCAL_DEBUG=1`` to see one).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from calib.handeye import METHODS, calibrate_hand_eye
from drivers.errors import DeviceError
from service import cli_devices, cli_serve
from service.image_files import DEFAULT_MAX_PIXELS, read_station_image
from service.stationset import DEFAULT_MAX_STATIONS

if TYPE_CHECKING:
    from service.stationset import StationSet

EXIT_USAGE = 2
EXIT_FAILED = 1


#: Show a detection progress bar from this many images on.
PROGRESS_MIN_IMAGES = 10


def _calibrate(args: argparse.Namespace) -> int:
    from service.stationset import load_station_set

    stations = load_station_set(args.station_dir, max_stations=args.max_stations)
    command = " ".join(["cellcal", *sys.argv[1:]])
    if stations.pose_only:
        from service.results import hand_eye_result_json

        P, C = stations.pose_arrays()
        options = {"estimate_kappa": args.estimate_kappa}
        result = calibrate_hand_eye(P, C, setup=stations.setup, method=args.method, **options)
        doc = hand_eye_result_json(result, [s.id for s in stations.stations], options=options,
                                   command=command)
    else:
        doc = _calibrate_images(args, stations, command)
    text = json.dumps(doc, indent=2)
    if args.out in (None, "-"):
        print(text)
    else:
        Path(args.out).write_text(text + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _calibrate_images(args: argparse.Namespace, stations: StationSet,
                      command: str) -> dict[str, Any]:
    """Result document of a station set with images (``calib.pipeline``)."""
    from tqdm import tqdm

    from calib.pipeline import calibrate_stations
    from service.results import calibration_result_json

    posed = [s.id for s in stations.stations if s.target_pose is not None]
    if posed:
        raise ValueError(f"{args.station_dir}: station {posed[0]} has a target_pose while others "
                         "have images; a station set is either pose-only or image-based")
    target = stations.target
    directory = Path(args.station_dir)
    images = (read_station_image(directory, s.image, max_pixels=args.max_image_pixels)
              for s in stations.stations)
    n = len(stations.stations)

    def progress(items: Iterable[Any]) -> Iterable[Any]:
        return tqdm(items, total=n, desc="detecting corners", unit="image", file=sys.stderr,
                    disable=n < PROGRESS_MIN_IMAGES, leave=False)

    intrinsics = None if stations.intrinsics is None else (
        stations.intrinsics.K, stations.intrinsics.dist)
    result = calibrate_stations(
        images, [s.tcp_pose for s in stations.stations], inner_corners=target.inner_corners,
        square_size=target.square_size_m, setup=stations.setup,
        station_ids=[s.id for s in stations.stations], intrinsics=intrinsics,
        method=args.method, nu_method=args.nu_method, progress=progress)
    return calibration_result_json(result, command=command)


def _demo(args: argparse.Namespace) -> int:
    from service.demo import run_demo, run_pose_demo

    if args.poses_only:
        return run_pose_demo(seed=args.seed, stations=args.stations)
    return run_demo(stations=args.stations, scene=args.scene, out=args.out)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cellcal",
        description="Camera and hand-eye calibration for robot cells. Units: metres and "
                    "radians in all files; see docs/conventions.md.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    cal = sub.add_parser(
        "calibrate", help="calibrate a station set directory (stations.json)",
        description="Calibrate a station set. With images: corners are detected, then "
                    "intrinsics with the board aspect ratio nu, hand-eye by screw motions (SM), "
                    "the board scale kappa, and by default ('joint') a maximum-likelihood "
                    "estimate over all corners and robot poses with standard deviations; "
                    "images that cannot be used are listed with the reason. Pose-only sets "
                    "(stations with target_pose): SM, then a weighted least-squares "
                    "refinement over all stations.")
    cal.add_argument("station_dir", help="directory holding stations.json")
    cal.add_argument("--out", help="result JSON path (default: stdout)")
    cal.add_argument("--method", default="joint", choices=METHODS,
                     help="solver (default: joint)")
    cal.add_argument("--estimate-kappa", action="store_true",
                     help="pose-only sets: also estimate the board scale kappa (joint only; "
                          "always estimated from images)")
    cal.add_argument("--nu-method", default="images", choices=("images", "extrinsics"),
                     help="images: board aspect ratio nu from the corner residuals (Method #1, "
                          "default); extrinsics: from the hand-eye residuals (Method #2)")
    cal.add_argument("--max-stations", type=int, default=DEFAULT_MAX_STATIONS, metavar="N",
                     help=f"refuse sets of more stations (default {DEFAULT_MAX_STATIONS})")
    cal.add_argument("--max-image-pixels", type=int, default=DEFAULT_MAX_PIXELS, metavar="N",
                     help="reject images larger than this, width x height, read from the file "
                          f"header before decoding (default {DEFAULT_MAX_PIXELS})")
    cal.set_defaults(func=_calibrate)

    demo = sub.add_parser(
        "demo", help="run the service on a simulated cell: capture, calibrate, validate",
        description="Start the REST service with mock devices on a free loopback port, plan "
                    "and capture 15 stations, calibrate, run the dot-hit validation, export "
                    "the result, and compare everything with the simulated cell's truth. The "
                    "service and its data are removed at the end.")
    demo.add_argument("--scene", type=Path, metavar="SCENE_JSON",
                      help="mock scene file (default: the built-in eye-in-hand cell)")
    demo.add_argument("--out", type=Path, metavar="DIR",
                      help="where to write the result JSON and its exports (default: a new "
                           "temporary directory, kept)")
    demo.add_argument("--poses-only", action="store_true",
                      help="instead: compare every hand-eye method on simulated poses")
    demo.add_argument("--seed", type=int, default=1, help="--poses-only: simulation seed")
    demo.add_argument("--stations", type=int, default=15, help=argparse.SUPPRESS)
    demo.set_defaults(func=_demo)
    cli_devices.register(sub)
    cli_serve.register(sub)
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
