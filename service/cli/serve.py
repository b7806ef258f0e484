"""Serve the calibration REST API (OpenAPI at /docs). Every call but /health needs
'Authorization: Bearer <CELLCAL_API_KEY>'. Settings come from CELLCAL_* environment variables
(CELLCAL_DATA_DIR, CELLCAL_ROBOT, CELLCAL_CAMERA, CELLCAL_WORKSPACE_MIN/MAX, ...); options
override them.
"""

# ``cellcal serve``: run the REST service (FastAPI on uvicorn) for the configured cell.
#
# Configuration comes from ``CELLCAL_*`` environment variables (``service.settings``); the options
# here override them. Without ``CELLCAL_API_KEY`` the service makes up a key for this session and
# prints it, and it refuses to listen beyond loopback at all.

from __future__ import annotations

import argparse
import secrets
import socket
import sys
from typing import Any

from pydantic import ValidationError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``serve`` command's arguments."""
    parser.add_argument("--mock", action="store_true",
                        help="simulate the cell: mock:// robot and camera")
    parser.add_argument("--scene", metavar="SCENE_JSON",
                        help="mock scene file (default: the built-in demo cell)")
    parser.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (default 8000)")
    parser.add_argument("--fd", type=int, metavar="FD",
                        help="serve on the listening TCP socket inherited as file descriptor FD "
                             "instead of binding --host/--port (socket activation: the parent "
                             "holds the port, so no other process can take it meanwhile)")
    parser.add_argument("--log-format", choices=("text", "json"), default="text",
                        help="the log on stderr: text lines, or one JSON object per line "
                             "(access lines and the lifecycle of runs, calibrations and "
                             "re-checks, with their ids, states and error codes as keys)")
    parser.add_argument("--graceful-timeout", type=_seconds, default=None, metavar="S",
                        help="on SIGTERM or SIGINT the robot stops at once; then the running "
                             "jobs, event streams and connections get S seconds in all to end "
                             "(default 10); a second signal exits at once")


def run(args: argparse.Namespace) -> int:
    """Run the service until it is stopped (Ctrl-C)."""
    import uvicorn

    from service.app import create_app
    from service.serving.connections import (
        ACCEPT_BURST,
        ConnectionLimits,
        connection_cap,
        guarded_protocol,
        limit_connection_logs,
        raise_fd_limit,
    )
    from service.serving.logs import configure_logging
    from service.serving.server import GRACEFUL_TIMEOUT_S, CellServer
    from service.settings import Settings, is_loopback

    overrides: dict[str, Any] = {k: v for k, v in (("host", args.host), ("port", args.port),
                                                   ("scene", args.scene)) if v is not None}
    sock = None if args.fd is None else _inherited_socket(args)
    if sock is not None:
        overrides.update(host=sock.getsockname()[0], port=sock.getsockname()[1])
    if args.mock:
        overrides.update(robot="mock://", camera="mock://")
    try:
        settings = Settings(**overrides)
        if settings.api_key is None and is_loopback(settings.host):
            key = secrets.token_urlsafe(24)
            settings = Settings(**overrides, api_key=key)
            print(f"cellcal: no CELLCAL_API_KEY set; this session's API key is {key}",
                  file=sys.stderr)
    except ValidationError as exc:
        raise ValueError(f"configuration: {_describe(exc)}") from None
    _check_database(settings)
    app = create_app(settings)
    limits = ConnectionLimits(cap=settings.max_connections,
                              header_timeout_s=settings.header_timeout_s,
                              send_timeout_s=settings.send_timeout_s)
    # asyncio's loop even where uvloop is installed: the accept errors limit_connection_logs
    # rate-limits are asyncio's, and uvloop used more CPU per GET here (3.4 against 3.0 ms)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level="info",
                            http=guarded_protocol(limits), loop="asyncio", backlog=ACCEPT_BURST,
                            timeout_keep_alive=settings.keep_alive_s)  # type: ignore[arg-type]
    limit_connection_logs()  # uvicorn's logging is configured now
    configure_logging(args.log_format)
    limits.cap = connection_cap(raise_fd_limit(), settings.max_connections)
    grace = GRACEFUL_TIMEOUT_S if args.graceful_timeout is None else args.graceful_timeout
    CellServer(config, app, graceful_timeout=grace).run(
        sockets=None if sock is None else [sock])
    return 0


def _seconds(text: str) -> float:
    """A finite, non-negative number of seconds (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.0 <= value <= 3600.0:
        raise argparse.ArgumentTypeError(f"{text!r}: give 0 to 3600 seconds")
    return value


def _check_database(settings: Any) -> None:
    """Open the database once before serving: one line and a non-zero exit for one that does
    not answer or needs ``cellcal db upgrade``, instead of a failed start-up in uvicorn."""
    from sqlalchemy.exc import SQLAlchemyError

    from service.store.db import Database

    settings.data_dir.mkdir(parents=True, exist_ok=True)
    try:
        Database(settings.database, busy_timeout_s=settings.database_busy_timeout_s).close()
    except SQLAlchemyError as exc:
        why = str(getattr(exc, "orig", None) or exc).splitlines()[0]
        raise ValueError(f"database: {why}") from None


def _inherited_socket(args: argparse.Namespace) -> socket.socket:
    """The listening TCP socket ``--fd`` names (its address becomes the service's host/port)."""
    if args.host is not None or args.port is not None:
        raise ValueError("--fd replaces --host and --port: give one or the other.")
    try:
        sock = socket.socket(fileno=args.fd)
    except OSError as exc:
        raise ValueError(f"--fd {args.fd}: not an open socket ({exc.strerror}).") from None
    if sock.family not in (socket.AF_INET, socket.AF_INET6) or \
            sock.type != socket.SOCK_STREAM or not sock.getsockopt(socket.SOL_SOCKET,
                                                                 socket.SO_ACCEPTCONN):
        raise ValueError(f"--fd {args.fd}: not a listening TCP socket.")
    return sock


def _describe(exc: ValidationError) -> str:
    """The first settings error as ``CELLCAL_NAME: what`` (or just what, for cross-checks)."""
    err = exc.errors()[0]
    msg = err["msg"].removeprefix("Value error, ")
    more = f" (and {exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
    name = f"CELLCAL_{str(err['loc'][0]).upper()}: " if err["loc"] else ""
    return f"{name}{msg}{more}"
