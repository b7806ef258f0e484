"""The RTDE wire protocol's framing (a 2-byte size and a 1-byte type ahead of each payload),
enough for the UR driver's probe to talk to a controller with plain sockets and real timeouts
before it hands the connection to ur-rtde (``drivers.ur_probe``), and the codes of the status
outputs the driver reads. :func:`recv_exact` also reads the driver's own channel to its ur-rtde
process (``drivers.ur_rtde_process``)."""

from __future__ import annotations

import socket
import struct

#: Codes of the RTDE outputs ``safety_status_bits``, ``robot_status_bits`` and ``robot_mode``.
SAFETY_PROTECTIVE_STOP = 1 << 2
SAFETY_EMERGENCY_STOPS = (1 << 5) | (1 << 6) | (1 << 7)  # system, robot, any e-stop
STATUS_PROGRAM_RUNNING = 1 << 1
ROBOT_MODES = {-1: "no_controller", 0: "disconnected", 1: "confirm_safety", 2: "booting",
               3: "power_off", 4: "power_on", 5: "idle", 6: "backdrive", 7: "running",
               8: "updating_firmware"}


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``sock``; ConnectionError when it closes first."""
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("connection closed by the controller")
        buf += chunk
    return buf


def rtde_receive(sock: socket.socket, msg_type: bytes) -> bytes:
    """Payload of the next RTDE message of type ``msg_type`` (others are skipped)."""
    while True:
        size, reply_type = struct.unpack(">HB", recv_exact(sock, 3))
        body = recv_exact(sock, size - 3)
        if reply_type == msg_type[0]:
            return body


def rtde_request(sock: socket.socket, msg_type: bytes, payload: bytes = b"") -> bytes:
    """Send one RTDE request and return the payload of its reply."""
    sock.sendall(struct.pack(">HB", len(payload) + 3, msg_type[0]) + payload)
    return rtde_receive(sock, msg_type)
