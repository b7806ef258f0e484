"""The three servers (dashboard, script, RTDE) on one loopback address, connection tracking,
the drop fault, and the command line."""


from __future__ import annotations

import argparse
import contextlib
import errno
import re
import selectors
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from mocks import ur_kinematics as kin
from mocks.ur_emulator.controller import Controller, Faults
from mocks.ur_emulator.rtde import RtdeSession, bind_port
from mocks.ur_emulator.safety import SafetyBox, parse_floats
from mocks.ur_emulator.wire import (
    AUTO_HOSTS,
    CONTROLLER_VERSION,
    DASHBOARD_PORT,
    FAULT_NAMES,
    RTDE_PORT,
    RUNTIME_PLAYING,
    SAFETY_NORMAL,
    SAFETY_PROTECTIVE_STOP,
    SCRIPT_PORT,
)


class Emulator:
    """The three servers on one address, connection tracking and the drop fault."""

    def __init__(self, host: str, *, instant: bool, settle_time: float, faults: Faults,
                 box: SafetyBox | None = None) -> None:
        self.host = host
        self.ctrl = Controller(instant=instant, settle_time=settle_time, faults=faults,
                               on_drop=self.drop, box=box)
        self._conns: set[socket.socket] = set()
        self._conns_lock = threading.Lock()
        self._refuse_until = 0.0
        self._listeners: dict[int, socket.socket] = {}

    # ---- connections ----------------------------------------------------------------------

    def _listen(self) -> None:
        """Bind the three ports on ``self.host``, or on the first free 127.0.0.N for ``auto``.

        The ports are held until the process exits (a drop resets connections instead of
        releasing them), so no other emulator can take this address while this one lives.
        """
        candidates = ([f"127.0.0.{n}" for n in AUTO_HOSTS] if self.host == "auto"
                      else [self.host])
        for host in candidates:
            try:
                self._listeners = {port: bind_port(host, port)
                                   for port in (DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT)}
            except OSError as err:
                self._unlisten()
                if len(candidates) == 1:
                    raise
                if err.errno not in (errno.EADDRINUSE, errno.EADDRNOTAVAIL):
                    raise
                continue
            self.host = host
            return
        raise OSError(errno.EADDRINUSE, "every address in 127.0.0.2..199 is taken")

    def _unlisten(self) -> None:
        for s in self._listeners.values():
            s.close()
        self._listeners.clear()

    def drop(self, seconds: float) -> None:
        """Close every connection and reset new ones for ``seconds``, like a cable pulled."""
        self._refuse_until = time.monotonic() + seconds
        with self._conns_lock:
            conns, self._conns = list(self._conns), set()
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()

    def serve_forever(self) -> None:
        """Accept on all three ports; each connection gets its own thread.

        The first line on stdout names the address served (``ur_emulator listening on HOST
        ports ...``): with ``--host auto`` that is how the caller learns it.
        """
        handlers = {DASHBOARD_PORT: self._dashboard, SCRIPT_PORT: self._script,
                    RTDE_PORT: self._rtde}
        self._listen()
        print(f"ur_emulator listening on {self.host} ports 29999 30003 30004", flush=True)
        sel = selectors.DefaultSelector()
        for port, s in self._listeners.items():
            sel.register(s, selectors.EVENT_READ, port)
        while True:
            for key, _ in sel.select(timeout=0.05):
                try:
                    conn, _ = key.fileobj.accept()
                except OSError:
                    continue
                if time.monotonic() < self._refuse_until:  # dropped: reset at once
                    conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                    struct.pack("ii", 1, 0))
                    conn.close()
                    continue
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with self._conns_lock:
                    self._conns.add(conn)
                threading.Thread(target=self._run, args=(handlers[key.data], conn),
                                 daemon=True).start()

    def _run(self, handler: Callable[[socket.socket], None], conn: socket.socket) -> None:
        try:
            handler(conn)
        except OSError:
            pass
        finally:
            with self._conns_lock:
                self._conns.discard(conn)
            conn.close()

    def _rtde(self, conn: socket.socket) -> None:
        RtdeSession(conn, self.ctrl).serve()

    def _script(self, conn: socket.socket) -> None:
        """Collect uploaded text; a complete ``def rtde_control(): ... end`` starts the twin."""
        buf = ""
        while True:
            chunk = conn.recv(65536)
            if not chunk:
                return
            buf += chunk.decode(errors="replace")
            start = buf.find("def rtde_control():")
            if start < 0:
                continue
            end = re.search(r"^end[ \t]*$", buf[start:], re.MULTILINE)
            if end is None:
                continue
            program = buf[start:start + end.end()]
            buf = buf[start + end.end():]
            m = re.search(r"global\s+reg_offset_int\s*=\s*(\d+)", program)
            self.ctrl.start_program(int(m.group(1)) if m else 0)

    def _dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        reader = conn.makefile("r", encoding="utf-8", newline="\n")
        for line in reader:
            command = line.strip()
            reply = self._dashboard_reply(command)
            delay = self.ctrl.faults.slow_replies
            if delay > 0.0:
                time.sleep(delay)
            conn.sendall((reply + "\n").encode())
            if command.startswith("emulator drop"):
                parts = command.split()
                self.drop(float(parts[2]) if len(parts) > 2 else 1.0)
                return

    def _dashboard_reply(self, command: str) -> str:
        """The text a UR dashboard server answers to ``command`` (plus emulator controls)."""
        ctrl = self.ctrl
        version = ".".join(str(v) for v in CONTROLLER_VERSION)
        running = ctrl.runtime_state == RUNTIME_PLAYING
        simple = {
            "PolyscopeVersion": f"URSoftware {version} (Jan 01 2023)",
            "get serial number": "20205500001",
            "get robot model": "UR5",
            "is in remote control": "false" if ctrl.faults.local_control else "true",
            "robotmode": f"Robotmode: {'RUNNING'}",
            "safetymode": "Safetymode: " + ("NORMAL" if ctrl.safety_bits == SAFETY_NORMAL else
                                            "PROTECTIVE_STOP"
                                            if ctrl.safety_bits & SAFETY_PROTECTIVE_STOP else
                                            "ROBOT_EMERGENCY_STOP"),
            "safetystatus": "Safetystatus: " + ("NORMAL" if ctrl.safety_bits == SAFETY_NORMAL
                                                else "PROTECTIVE_STOP"),
            "running": f"Program running: {str(running).lower()}",
            "programState": ("PLAYING" if running else "STOPPED") + " <unnamed>",
            "power on": "Powering on", "brake release": "Brake releasing",
            "emulator state": ctrl.state_json(),
        }
        if command in simple:
            return simple[command]
        if command == "stop":
            ctrl.stop_program()
            return "Stopped"
        if command == "play":
            return "Starting program"
        if command == "unlock protective stop":
            return "Protective stop releasing" if ctrl.unlock() else \
                "Failed to unlock protective stop"
        if command == "close safety popup":
            return "closing safety popup"
        if command == "emulator clear":
            ctrl.reset()
            return "emulator: faults cleared"
        if command.startswith("emulator fault "):
            try:
                with ctrl.lock:
                    ctrl.faults.set(command[len("emulator fault "):])
            except ValueError as err:
                return f"emulator: {err}"
            return f"emulator: fault set: {command[len('emulator fault '):]}"
        if command.startswith("emulator drop"):
            return "emulator: dropping all connections"
        return f"could not understand: '{command}'"


def start_joints(pose: str) -> np.ndarray:
    """The joints (6,) of ``--start-pose`` (IK from the home joints); ValueError if none."""
    q = kin.ik(np.array(parse_floats(pose, 6, "--start-pose")), kin.HOME_Q)
    if q is None:
        raise ValueError(f"--start-pose {pose}: beyond the UR5e's reach")
    return q


def main(argv: list[str] | None = None) -> None:
    """Command line entry: parse options, start the servers, serve until killed."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.2",
                        help="loopback address to serve on (not 127.0.0.1, so the client runs its "
                             "remote-control check), or 'auto' for the first free one")
    parser.add_argument("--instant", action="store_true", help="motions take no time")
    parser.add_argument("--settle-time", type=float, default=0.15,
                        help="seconds the reported TCP speed rings out after a timed motion")
    parser.add_argument("--fault", action="append", default=[], metavar="NAME[=VALUE]",
                        help=f"inject a fault at start; one of {', '.join(FAULT_NAMES)}")
    parser.add_argument("--box", metavar="X0,Y0,Z0,X1,Y1,Z1",
                        help="safety box (m, base frame): a move that would take the flange or "
                             "a tool point outside it is refused with a protective stop")
    parser.add_argument("--tool-point", action="append", default=[], metavar="X,Y,Z",
                        help="with --box: a point in the flange frame kept inside it too (m)")
    parser.add_argument("--start-pose", metavar="X,Y,Z,RX,RY,RZ",
                        help="UR pose the arm stands at on start (default: the home joints)")
    args = parser.parse_args(argv)
    try:
        box = None if args.box is None else SafetyBox.parse(args.box, args.tool_point)
        start_q = None if args.start_pose is None else start_joints(args.start_pose)
    except ValueError as err:
        parser.error(str(err))
    faults = Faults()
    for spec in args.fault:
        try:
            faults.set(spec)
        except ValueError as err:
            parser.error(str(err))
    emulator = Emulator(args.host, instant=args.instant, settle_time=args.settle_time,
                        faults=faults, box=box)
    if start_q is not None:
        emulator.ctrl.q, emulator.ctrl.pose = start_q, kin.fk_pose(start_q)
    try:
        emulator.serve_forever()
    except OSError as err:  # typically: the address is taken by another emulator
        sys.exit(f"ur_emulator: cannot serve on {args.host}: {err.strerror or err}")
    except KeyboardInterrupt:
        return


if __name__ == "__main__":
    main()
