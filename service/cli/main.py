"""``cellcal`` command line: the parser and the error policy; each command is a module.

A command module offers a docstring (its description in ``cellcal COMMAND --help``),
``add_arguments(parser)`` and ``run(args)`` (the exit status); ``devices`` adds its command
groups (``robot``, ``camera``, ``devices``) itself. Only the module of the command given is
imported, when it is given (``COMMANDS``): ``cellcal --version`` and ``--help`` start without
numpy, OpenCV or the service, and each command loads what it needs.

Every error prints one line on stderr and exits non-zero; no traceback reaches a user
(set ``CELLCAL_DEBUG=1`` to see one).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from drivers.errors import DeviceError
from service.cli.errors import ServiceCallError
from service.cli.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from service.version import software_version

#: BLAS on one thread in every command, set before numpy loads (a value the user set is
#: kept). cellcal's matrices have tens of columns, and OpenBLAS's threads busy-wait after each
#: call; they are also started again whenever ``calib.pipeline``'s one-thread limit is lifted,
#: and in each forked worker: 0.5 of the 2.5 CPU s of ``cellcal calibrate`` on 18 stations.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

#: Each command: its module and its line in ``cellcal --help``, in the order listed there.
COMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": ("service.cli.calibrate", "calibrate a station set directory (stations.json)"),
    "calibrations": ("service.cli.calibrations",
                     "list, show, start, activate or export calibrations of a running service"),
    "db": ("service.cli.db", "upgrade the service's database or show its schema revision"),
    "demo": ("service.cli.demo", "run the service on a simulated cell: capture, calibrate, "
                                 "validate"),
    "robot": ("service.cli.devices", "read or move the robot"),
    "camera": ("service.cli.devices", "grab camera frames"),
    "devices": ("service.cli.devices", "check the cell's devices"),
    "export": ("service.cli.export", "export a result file for OpenCV, ROS, a URDF or a UR "
                                     "program"),
    "report": ("service.cli.report", "write the HTML report of a calibration result"),
    "runs": ("service.cli.runs",
             "list, show, start, pause, resume or cancel capture runs of a running service"),
    "serve": ("service.cli.serve", "run the REST service"),
}


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``cellcal`` parser with the full arguments of the command named in ``argv``
    (its module imported), and the others by name and help line only."""
    argv = sys.argv[1:] if argv is None else argv
    given = next((a for a in argv if not a.startswith("-")), None)
    parser = argparse.ArgumentParser(
        prog="cellcal",
        description="Camera and hand-eye calibration for robot cells. Units: metres and "
                    "radians in all files; see docs/conventions.md.")
    parser.add_argument("--version", action="version",
                        version=f"cellcal {software_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    wanted = COMMANDS[given][0] if given in COMMANDS else ""
    for name, (module_name, help_line) in COMMANDS.items():
        if module_name != wanted:
            sub.add_parser(name, help=help_line)
        elif module_name == "service.cli.devices":
            if name == "robot":  # the first of its commands: it adds all three
                importlib.import_module(module_name).register(
                    sub, {n: h for n, (m, h) in COMMANDS.items() if m == module_name})
        else:
            command = importlib.import_module(module_name)
            command_parser = sub.add_parser(name, help=help_line, description=command.__doc__)
            command.add_arguments(command_parser)
            command_parser.set_defaults(func=command.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser(argv).parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (ValueError, DeviceError, OSError, ServiceCallError) as exc:
        if os.getenv("CELLCAL_DEBUG"):
            raise
        print(f"cellcal: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, ValueError) else EXIT_FAILED
    except KeyboardInterrupt:
        print("cellcal: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # last line of defence: never show a traceback
        if os.getenv("CELLCAL_DEBUG"):
            raise
        print(f"cellcal: internal error ({type(exc).__name__}: {exc}); "
              "rerun with CELLCAL_DEBUG=1 and report it", file=sys.stderr)
        return EXIT_FAILED


def entry() -> NoReturn:
    """The ``cellcal`` program: :func:`main`, then exit with its status. What a command
    leaves dies with the process, so the interpreter's last garbage collections skip it
    (``gc.freeze``): 0.11 -> 0.03 s of exit after a calibration's imports."""
    status = main()
    gc.freeze()
    sys.exit(status)
