"""The UR dashboard server (port 29999): one short text exchange per call.

The dashboard answers one line per command after a banner line. cellcal uses it for what the
RTDE interfaces do not offer: stopping a blocking move from another thread, and the robot's
identity (model, serial number, PolyScope version) for the report.
"""

from __future__ import annotations

import re
import socket

DASHBOARD_PORT = 29999

#: How a dashboard that does not know a command answers (older controllers lack some).
_UNKNOWN = "could not understand"


def dashboard_exchange(host: str, commands: list[str], timeout: float) -> list[str]:
    """Send each command on one dashboard connection; return the reply lines in order.
    Raises ``OSError`` (``TimeoutError``, ``ConnectionResetError``) when the controller does
    not answer."""
    replies = []
    with socket.create_connection((host, DASHBOARD_PORT), timeout) as s:
        s.settimeout(timeout)
        reader = s.makefile("r", encoding="ascii", errors="replace", newline="\n")
        if not reader.readline():  # the banner
            raise ConnectionResetError("the dashboard closed the connection")
        for command in commands:
            s.sendall(command.encode("ascii") + b"\n")
            line = reader.readline()
            if not line:
                raise ConnectionResetError("the dashboard closed the connection")
            replies.append(line.strip())
    return replies


def parse_identity(model: str, serial: str, polyscope: str) -> dict[str, str | None]:
    """The robot's identity from the replies to ``get robot model``, ``get serial number``
    and ``PolyscopeVersion``; a reply the controller could not give is None."""
    def known(reply: str) -> str | None:
        return None if not reply or _UNKNOWN in reply.lower() else reply

    version = re.search(r"\d+\.\d+\.\d+(?:\.\d+)?", polyscope)
    return {"model": known(model), "serial": known(serial) if serial.isdigit() else None,
            "controller_version": version.group(0) if version else None}
