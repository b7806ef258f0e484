"""Start the REST service with mock devices on a free loopback port, plan and capture 15
stations, calibrate, run the dot-hit validation, export the result, and compare everything with
the simulated cell's truth. The service and its data are removed at the end.
"""

# ``cellcal demo``: the service flow on a simulated cell.
#
# The demo belongs to the simulator (``mocks/demo.py``): it starts ``cellcal serve --mock`` and
# checks the results against the mock scene's truth. The service never imports the mocks, so the
# command names its implementation by an import string, as ``drivers.registry`` names the mock
# devices.

from __future__ import annotations

import argparse
from pathlib import Path

from drivers.registry import resolve

#: The demos, as import strings.
DEMO = "mocks.demo:run_demo"
POSE_DEMO = "mocks.demo:run_pose_demo"




def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``demo`` command's arguments."""
    parser.add_argument("--scene", type=Path, metavar="SCENE_JSON",
                        help="mock scene file (default: the built-in eye-in-hand cell)")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="where to write the result JSON and its exports (default: a new "
                             "temporary directory, kept)")
    parser.add_argument("--poses-only", action="store_true",
                        help="instead: compare every hand-eye method on simulated poses")
    parser.add_argument("--seed", type=int, default=1, help="--poses-only: simulation seed")
    parser.add_argument("--stations", type=int, default=15, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    """Run the simulator's demo (or the pose-only comparison)."""
    if args.poses_only:
        return resolve(POSE_DEMO)(seed=args.seed, stations=args.stations)
    return resolve(DEMO)(stations=args.stations, scene=args.scene, out=args.out)


