"""``cellcal`` command line: the parser and the error policy; each command is a module.

A command module offers ``HELP`` (its line in ``cellcal --help``), a docstring (its description
in ``cellcal COMMAND --help``), ``add_arguments(parser)`` and ``run(args)`` (the exit status);
``devices`` adds its command groups (``robot``, ``camera``, ``devices``) itself.

Every error prints one line on stderr and exits non-zero; no traceback reaches a user
(set ``CELLCAL_DEBUG=1`` to see one).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from types import ModuleType

from drivers.errors import DeviceError
from service.cli import calibrate, calibrations, db, demo, devices, export, report, runs, serve
from service.cli.client import ServiceCallError
from service.cli.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from service.results import software_version


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cellcal",
        description="Camera and hand-eye calibration for robot cells. Units: metres and "
                    "radians in all files; see docs/conventions.md.")
    parser.add_argument("--version", action="version",
                        version=f"cellcal {software_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_command(sub, "calibrate", calibrate)
    _add_command(sub, "calibrations", calibrations)
    _add_command(sub, "db", db)
    _add_command(sub, "demo", demo)
    devices.register(sub)
    _add_command(sub, "export", export)
    _add_command(sub, "report", report)
    _add_command(sub, "runs", runs)
    _add_command(sub, "serve", serve)
    return parser


def _add_command(sub: argparse._SubParsersAction, name: str, command: ModuleType) -> None:
    parser = sub.add_parser(name, help=command.HELP, description=command.__doc__)
    command.add_arguments(parser)
    parser.set_defaults(func=command.run)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (ValueError, DeviceError, OSError, ServiceCallError) as exc:
        if os.environ.get("CELLCAL_DEBUG"):
            raise
        print(f"cellcal: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, ValueError) else EXIT_FAILED
    except KeyboardInterrupt:
        print("cellcal: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # last line of defence: never show a traceback
        if os.environ.get("CELLCAL_DEBUG"):
            raise
        print(f"cellcal: internal error ({type(exc).__name__}: {exc}); "
              "rerun with CELLCAL_DEBUG=1 and report it", file=sys.stderr)
        return EXIT_FAILED
