"""The UR controller checked with plain sockets and real timeouts before ur-rtde connects
(``drivers.ur``'s module docstring says why): reachable, answering RTDE requests fast enough
for the ur-rtde constructors' round trips, streaming data, serving the dashboard (which stops a
program left running) and the script port."""

from __future__ import annotations

import socket
import struct
import time

from drivers import rtde_wire
from drivers.errors import RobotConnectionError
from drivers.ur_dashboard import dashboard_exchange

RTDE_PORT = 30004
SCRIPT_PORT = 30003
#: Request/reply round trips the two ur-rtde constructors make (RTDE recipes + dashboard).
CONSTRUCTOR_ROUND_TRIPS = 40


def probe_controller(host: str, connect_timeout: float) -> None:
    """Check that the controller at ``host`` is reachable and responsive within
    ``connect_timeout`` (seconds, for the whole probe); RobotConnectionError saying what to
    check when it is not."""
    deadline = time.monotonic() + connect_timeout

    def remaining() -> float:
        return max(deadline - time.monotonic(), 0.01)

    try:
        with socket.create_connection((host, RTDE_PORT), remaining()) as s:
            s.settimeout(remaining())
            t0 = time.monotonic()
            rtde_wire.rtde_request(s, b"V", struct.pack(">H", 2))
            rtde_wire.rtde_request(s, b"v")
            per_request = (time.monotonic() - t0) / 2.0
            if per_request * CONSTRUCTOR_ROUND_TRIPS > remaining():
                raise RobotConnectionError(
                    f"The robot controller at {host} answers too slowly "
                    f"({per_request * 1e3:.0f} ms per request) to connect within "
                    f"{connect_timeout:g} s. Check the network between this computer "
                    "and the robot (a busy or wireless link?).")
            s.settimeout(remaining())
            rtde_wire.rtde_request(s, b"O", struct.pack(">d", 125.0) + b"timestamp")
            rtde_wire.rtde_request(s, b"S")
            rtde_wire.rtde_receive(s, b"U")  # the first streamed data package
        (running,) = dashboard_exchange(host, ["running"], remaining())
        if running.lower().endswith("true"):
            # ur-rtde would stop a running program before its own upload anyway; a control
            # script whose client died mid-move never takes that request (it waits for
            # the dead client's handshake), so the dashboard stops it first.
            dashboard_exchange(host, ["stop"], remaining())
        socket.create_connection((host, SCRIPT_PORT), remaining()).close()
    except TimeoutError:
        raise RobotConnectionError(
            f"The robot controller at {host} did not answer within "
            f"{connect_timeout:g} s. Check that the robot is switched on and fully "
            "booted, then try again.") from None
    except OSError as err:
        raise RobotConnectionError(
            f"Cannot reach the robot controller at {host} ({err.strerror or err}). "
            "Check that the controller is switched on, the network cable is plugged in and "
            "the IP address is right.") from None
