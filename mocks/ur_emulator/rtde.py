"""One RTDE connection: the version handshake, output and input recipes, and the data stream
at the client's frequency."""


from __future__ import annotations

import socket
import struct
import sys
import threading
import time

import numpy as np

from mocks.ur_emulator.controller import Controller
from mocks.ur_emulator.wire import (
    CONTROLLER_VERSION,
    MIN_STREAM_PERIOD,
    RTDE_CONTROLLER_VERSION,
    RTDE_DATA,
    RTDE_PAUSE,
    RTDE_SETUP_INPUTS,
    RTDE_SETUP_OUTPUTS,
    RTDE_START,
    RTDE_VERSION,
    TYPE_FORMATS,
    field_type,
)


class RtdeSession:
    """One RTDE client connection: recipes, requests and the output stream."""

    def __init__(self, sock: socket.socket, ctrl: Controller) -> None:
        self.sock = sock
        self.ctrl = ctrl
        self.send_lock = threading.Lock()
        self.output: tuple[int, list[str], list[str], float] | None = None
        self.inputs: dict[int, tuple[list[str], list[str]]] = {}
        self.next_input_id = 1
        self.next_output_id = 1
        self.streaming = threading.Event()
        self.closed = threading.Event()

    def _send(self, msg_type: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.sock.sendall(struct.pack(">HB", len(payload) + 3, msg_type) + payload)

    def _recv_exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("client closed")
            buf += chunk
        return buf

    def serve(self) -> None:
        """Answer requests until the client leaves or the connection is dropped."""
        threading.Thread(target=self._stream, daemon=True).start()
        try:
            while True:
                size, msg_type = struct.unpack(">HB", self._recv_exact(3))
                payload = self._recv_exact(size - 3) if size > 3 else b""
                self._handle(msg_type, payload)
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            self.closed.set()
            self.streaming.clear()

    def _handle(self, msg_type: int, payload: bytes) -> None:
        if msg_type == RTDE_DATA:
            self._accept_data(payload)
            return
        delay = self.ctrl.faults.slow_replies
        if delay > 0.0:
            time.sleep(delay)
        if msg_type == RTDE_VERSION:
            self._send(RTDE_VERSION, b"\x01")
        elif msg_type == RTDE_CONTROLLER_VERSION:
            self._send(RTDE_CONTROLLER_VERSION, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif msg_type == RTDE_SETUP_OUTPUTS:
            (frequency,) = struct.unpack(">d", payload[:8])
            names = [n for n in payload[8:].decode().split(",") if n]
            types = self._types(names)
            rid = self.next_output_id
            self.next_output_id += 1
            self.output = (rid, names, types, frequency)
            self._send(RTDE_SETUP_OUTPUTS, bytes([rid]) + ",".join(types).encode())
        elif msg_type == RTDE_SETUP_INPUTS:
            names = [n for n in payload.decode().split(",") if n]
            types = self._types(names)
            rid = self.next_input_id
            self.next_input_id += 1
            self.inputs[rid] = (names, types)
            self._send(RTDE_SETUP_INPUTS, bytes([rid]) + ",".join(types).encode())
        elif msg_type == RTDE_START:
            self._send(RTDE_START, b"\x01")
            self.streaming.set()
        elif msg_type == RTDE_PAUSE:
            self.streaming.clear()
            self._send(RTDE_PAUSE, b"\x01")
        # Unknown requests get no reply: never an unsolicited M message.

    @staticmethod
    def _types(names: list[str]) -> list[str]:
        """RTDE types for a recipe; unknown names become NOT_FOUND (logged, the client throws)."""
        types = [field_type(n) or "NOT_FOUND" for n in names]
        for name, rtype in zip(names, types, strict=True):
            if rtype == "NOT_FOUND":
                print(f"ur_emulator: unknown RTDE field {name!r}", file=sys.stderr, flush=True)
        return types

    def _accept_data(self, payload: bytes) -> None:
        """A data package from the client: write its values into the controller's inputs."""
        recipe = self.inputs.get(payload[0]) if payload else None
        if recipe is None:
            return
        names, types = recipe
        if "NOT_FOUND" in types:
            return
        fmt = ">" + "".join(TYPE_FORMATS[t] for t in types)
        try:
            values = struct.unpack(fmt, payload[1:1 + struct.calcsize(fmt)])
        except struct.error:
            return
        i = 0
        for name, rtype in zip(names, types, strict=True):
            width = int(TYPE_FORMATS[rtype][0]) if TYPE_FORMATS[rtype][0].isdigit() else 1
            value = values[i] if width == 1 else list(values[i:i + width])
            i += width
            self.ctrl.set_input(name, value)

    def _stream(self) -> None:
        """Send U packages for the output recipe while started, at most 125 Hz."""
        while not self.closed.is_set():
            if not self.streaming.wait(0.05) or self.output is None:
                continue
            rid, names, types, frequency = self.output
            period = max(1.0 / max(frequency, 1.0), MIN_STREAM_PERIOD)
            packed = bytearray([rid])
            with self.ctrl.lock:
                for name, rtype in zip(names, types, strict=True):
                    packed += _pack(rtype, self.ctrl.value(name))
            try:
                self._send(RTDE_DATA, bytes(packed))
            except OSError:
                return
            time.sleep(period)


def bind_port(host: str, port: int) -> socket.socket:
    """A listening TCP socket on (host, port)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
        s.listen(16)
    except OSError:
        s.close()
        raise
    return s


def _pack(rtype: str, value: object) -> bytes:
    """Big-endian bytes of ``value`` as RTDE type ``rtype``; None packs as zeros."""
    fmt = TYPE_FORMATS.get(rtype)
    if fmt is None:
        return b""
    count = int(fmt[0]) if fmt[0].isdigit() else 1
    values = [0] * count if value is None else list(np.ravel(value))
    convert = {"d": float, "?": bool}.get(fmt[-1], int)
    return struct.pack(">" + fmt, *[convert(v) for v in values])


