"""Calibrations of a running service (cellcal serve): list them (newest first, filtered by run,
state or setup), show one with its result, start one over a run's stations ('start --wait'
follows it until it is done), make one the cell's active calibration, show the active one with
its history, and export one for OpenCV, ROS, a URDF or a UR program. The service is --url
(CELLCAL_URL), its key --api-key (CELLCAL_API_KEY).
"""

# ``cellcal calibrations``: the REST calls of ``service.api.calibrations`` and
# ``service.api.active`` from the command line (``service.cli.client``).

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from service.cli import client
from service.cli.exit_codes import EXIT_FAILED
from service.exports import FORMATS

_COLUMNS = ["id", "run_id", "state", "verdict", "rms_px", "active", "method", "created_at"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``calibrations`` actions and their arguments."""
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    listing = client.add_list_and_show(actions, "calibrations",
                                "one calibration with its result, as JSON", "cal_id")
    listing.add_argument("--run", dest="run_id", metavar="RUN_ID", help="only this run's")
    listing.add_argument("--state", choices=["running", "done", "failed"])
    listing.add_argument("--setup", choices=["eye_in_hand", "eye_to_hand"])
    start = actions.add_parser(
        "start", help="calibrate a run's captured stations; prints the calibration's id",
        description="Start a calibration over a run's captured stations and print its id. "
                    "With --wait, follow it until it ends and print its verdict; exit 0 if "
                    "it is done, 1 if it failed.")
    start.add_argument("run_id", metavar="RUN_ID")
    start.add_argument("--method", help="solver (default joint)")
    start.add_argument("--kappa", choices=["auto", "estimate", "fixed"],
                       help="board scale: auto (default), estimate, or fixed at 1")
    start.add_argument("--wait", action="store_true", help="follow it until it ends")
    activate = actions.add_parser("activate", help="make it the cell's current calibration")
    activate.add_argument("cal_id", metavar="CAL_ID")
    active = actions.add_parser("active", help="the current calibration and what was active "
                                               "when, as JSON")
    active.add_argument("--cell", help="default: the service's cell")
    active.add_argument("--setup", choices=["eye_in_hand", "eye_to_hand"],
                        help="default: the service's setup")
    active.add_argument("--history", type=int, metavar="N",
                        help="periods of what was active when, newest first (default 10)")
    export = actions.add_parser("export", help="the result as a file for OpenCV, ROS, a URDF "
                                               "or a UR program")
    export.add_argument("cal_id", metavar="CAL_ID")
    export.add_argument("--format", required=True, choices=FORMATS, dest="fmt")
    export.add_argument("--out", type=Path, help="output file (default: stdout)")
    export.add_argument("--camera-name", help="ROS camera_name, joint and node prefix")
    export.add_argument("--parent-frame", help="frame the camera is fixed to")
    export.add_argument("--child-frame", help="the camera's frame")
    for sub in actions.choices.values():
        client.add_connection_arguments(sub)


def run(args: argparse.Namespace) -> int:
    """Do ``args.action`` against the service; the exit status."""
    service = client.Service.from_args(args)
    return _ACTIONS[args.action](service, args) or 0


def _list(service: client.Service, args: argparse.Namespace) -> None:
    page = service.fetch("/calibrations", run_id=args.run_id, state=args.state,
                       setup=args.setup, limit=args.limit)
    client.print_table(page["items"], _COLUMNS)


def _activate(service: client.Service, args: argparse.Namespace) -> None:
    active = service.post(f"/calibrations/{args.cal_id}/activate")
    print(f"calibration {active['calibration']['id']} is the active {active['setup']} "
          f"calibration of cell {active['cell']} (robot {active['robot']})")


def _start(service: client.Service, args: argparse.Namespace) -> int:
    options = {k: v for k, v in (("method", args.method), ("kappa", args.kappa))
               if v is not None}
    cal_id = service.post(f"/runs/{args.run_id}/calibrations", {"options": options})["id"]
    print(cal_id)
    if not args.wait:
        return 0
    final = client.follow(service, f"/calibrations/{cal_id}/events", total=None, unit="station",
                   progress=_detected)
    if final.state != "done":
        print(f"calibration {cal_id}: {final.state}: {final.error}", file=sys.stderr)
        return EXIT_FAILED
    from calib import Result

    result = Result.model_validate(service.fetch(f"/calibrations/{cal_id}")["result"])
    verdict = None if result.quality is None else result.quality.verdict
    rms = None if result.camera is None else result.camera.rms_px
    print(f"calibration {cal_id}: done, verdict {verdict}, rms "
          f"{'-' if rms is None else f'{rms:.3f}'} px", file=sys.stderr)
    return 0


def _detected(event: client.Event) -> tuple[int, int | None] | None:
    """Stations detected of all, from a ``progress`` event that counts them."""
    if event.type != "progress" or "of" not in event.data:
        return None
    return int(event.data["step"]), int(event.data["of"])


def _export(service: client.Service, args: argparse.Namespace) -> None:
    """The export as a file, or on stdout."""
    params = {"format": args.fmt, "camera_name": args.camera_name,
              "parent_frame": args.parent_frame, "child_frame": args.child_frame}
    r = service.call("GET", f"/calibrations/{args.cal_id}/export",
                     params={k: v for k, v in params.items() if v is not None})
    if args.out is None:
        sys.stdout.write(r.text)
    else:
        args.out.write_text(r.text)
        print(f"wrote {args.out}", file=sys.stderr)


#: Each action's handler: (service, args) -> exit status (None: 0).
_ACTIONS: dict[str, Callable[[client.Service, argparse.Namespace], int | None]] = {
    "list": _list,
    "show": lambda service, args: client.print_json(
        service.fetch(f"/calibrations/{args.cal_id}")),
    "start": _start,
    "activate": _activate,
    "active": lambda service, args: client.print_json(
        service.fetch("/calibrations/active", cell=args.cell, setup=args.setup,
                      history=args.history)),
    "export": _export,
}
