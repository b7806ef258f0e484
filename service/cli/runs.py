"""Capture runs of a running service (cellcal serve): list them, show one, start one (planned
stations, planned until a tolerance is met, a pose list, or an external run a cell controller
feeds), pause, resume or cancel it. 'start --wait' follows the run's event stream with a
progress bar (and the hand-eye's σ against the tolerance) until it ends. The service
is --url (CELLCAL_URL), its key --api-key (CELLCAL_API_KEY).
"""

# ``cellcal runs``: the REST calls of ``service.api.runs`` from the command line
# (``service.cli.client``); errors are one line on stderr and a non-zero exit.

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from service.cli import client
from service.cli.exit_codes import EXIT_FAILED
from service.cli.files import parse_json, read_json

_COLUMNS = ["id", "state", "mode", "stations_captured", "stations_skipped", "stations_planned",
            "created_at"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``runs`` actions and their arguments."""
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    client.add_list_and_show(actions, "runs", "one run as JSON", "run_id")
    start = actions.add_parser(
        "start", help="start a run; prints its id",
        description="Start a capture run and print its id. With --wait, follow it with a "
                    "progress bar until it ends; exit 0 if it is done, 1 if it failed, was "
                    "cancelled or interrupted.")
    plan = start.add_mutually_exclusive_group(required=True)
    plan.add_argument("--stations", type=int, metavar="N",
                      help="plan N stations automatically")
    plan.add_argument("--poses", type=Path, metavar="POSES_JSON",
                      help="JSON file with a list of TCP poses [x, y, z, rx, ry, rz] (m, rad)")
    plan.add_argument("--external", action="store_true",
                      help="a cell controller posts the stations (POST /runs/{id}/stations)")
    plan.add_argument("--tolerance-mm", type=float, metavar="MM",
                      help="plan stations until the 90 %% bound on the hand-eye translation "
                           "error (1.645x its honest 1-sigma) is within MM (with "
                           "--tolerance-deg)")
    start.add_argument("--tolerance-deg", type=float, metavar="DEG",
                       help="... and its rotation's within DEG degrees")
    start.add_argument("--max-stations", type=int, metavar="N",
                       help="with a tolerance: stop after N stations at the latest (default 40)")
    start.add_argument("--target", metavar="JSON|FILE",
                       help="the board, as in a station set: a JSON object such as "
                            "'{\"type\": \"checkerboard\", \"inner_corners\": [9, 6], "
                            "\"square_size_m\": 0.025}', or a file holding one (default: "
                            "the service's configured board)")
    start.add_argument("--wait", action="store_true",
                       help="follow the run until it ends, with a progress bar")
    for name, what in (("pause", "stop after the station in progress"),
                       ("resume", "continue at the next missing station"),
                       ("cancel", "stop for good; stored stations stay")):
        action = actions.add_parser(name, help=what)
        action.add_argument("run_id", metavar="RUN_ID")
    for sub in actions.choices.values():
        client.add_connection_arguments(sub)


def run(args: argparse.Namespace) -> int:
    """Do ``args.action`` against the service; the exit status."""
    service = client.Service.from_args(args)
    if args.action == "start":
        return _start(service, args)
    if args.action == "list":
        client.print_table(service.fetch("/runs", limit=args.limit), _COLUMNS)
    elif args.action == "show":
        client.print_json(service.fetch(f"/runs/{args.run_id}"))
    else:  # pause, resume, cancel: the run's new state
        print(f"run {args.run_id}: {service.post(f'/runs/{args.run_id}/{args.action}')['state']}")
    return 0


def _start(service: client.Service, args: argparse.Namespace) -> int:
    if (args.tolerance_mm is None) != (args.tolerance_deg is None):
        raise ValueError("give --tolerance-mm and --tolerance-deg together")
    if args.max_stations is not None and args.tolerance_mm is None:
        raise ValueError("--max-stations goes with --tolerance-mm and --tolerance-deg")
    body: dict[str, Any]
    if args.external:
        body = {"mode": "external"}
    elif args.stations is not None:
        body = {"stations": args.stations}
    elif args.tolerance_mm is not None:
        body = {"tolerance_mm": args.tolerance_mm, "tolerance_deg": args.tolerance_deg}
        if args.max_stations is not None:
            body["max_stations"] = args.max_stations
    else:
        body = {"poses": _read_file(args.poses, "--poses")}
    if args.target is not None:
        body["target"] = _read_target(args.target)
    run_id = service.post("/runs", body)["id"]
    print(run_id)
    if not args.wait:
        return 0
    planned = service.fetch(f"/runs/{run_id}")["stations_planned"]
    final = client.follow(service, f"/runs/{run_id}/events", total=planned, unit="station",
                          progress=StationCount())
    print(f"run {run_id}: {final.state}, {final.stations_captured} captured, "
          f"{final.stations_skipped} skipped"
          + (f", stopped: {final.stop_reason}" if final.stop_reason else "")
          + (f": {final.error}" if final.error else ""), file=sys.stderr)
    return 0 if final.state == "done" else EXIT_FAILED


def _read_target(value: str) -> dict[str, Any]:
    """``--target``: a JSON object given inline or in a file (the service checks its fields)."""
    target = (parse_json(value, "--target") if value.lstrip().startswith("{")
              else _read_file(Path(value), "--target"))
    if not isinstance(target, dict):
        raise ValueError("--target: a JSON object is needed, e.g. {\"type\": \"checkerboard\", "
                         "\"inner_corners\": [9, 6], \"square_size_m\": 0.025}")
    return target


class StationCount:
    """Stations captured or skipped so far: a ``state`` event's counts, plus one per
    ``station`` event after it."""

    def __init__(self) -> None:
        self.done = 0

    def __call__(self, event: client.Event) -> tuple[int, int | None] | None:
        if event.type == "state":
            from service.cli.answers import StateEvent

            state = StateEvent.model_validate(event.data)
            self.done = state.stations_captured + state.stations_skipped
        elif event.type == "station":
            self.done += 1
        else:
            return None
        return self.done, None


def _read_file(path: Path, option: str) -> Any:
    """The JSON document in the file an option names; ``ValueError`` with one line if it
    cannot be read, is too large or is not JSON."""
    try:
        return read_json(path)
    except OSError as exc:
        raise ValueError(f"{option} {path}: cannot read ({exc.strerror or exc})") from None
