"""Universal Robots arms through the ``ur-rtde`` client (``rtde_control`` / ``rtde_receive``).

``URRobot`` implements ``drivers.base.Robot``. Poses are UR pose vectors, T_base_tcp, metres and
radians (``docs/conventions.md``). Every failure reaches the caller as a ``drivers.errors``
subclass whose message a shop-floor person can act on; no ``RuntimeError`` from ur-rtde escapes.

Why connecting starts with our own probe: the ur-rtde constructors hold the GIL while they
block, so a worker thread with a deadline cannot interrupt them (the waiting thread never gets to
run). Before constructing them we therefore check (``drivers.ur_probe``), with plain sockets
and real timeouts, that the controller is reachable, answers RTDE requests, streams data and
serves the dashboard, and that it answers fast enough for the ~40 request/reply round trips the
constructors make to fit in ``connect_timeout``. After a successful probe the constructors
return in well under a second; the one slow path left is a control program that never starts,
which ur-rtde itself gives up on after about 5 s.

The interfaces live in a child process (``drivers.ur_rtde_process``): ur-rtde can crash with
SIGSEGV after a short network drop, and that must end a connection, not the service. A crash of
the child is reported like any lost connection, naming the signal.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from calib import check_joint_positions, check_ur_pose
from drivers import rtde_wire
from drivers.base import RobotIdentity, RobotSession, RobotStatus
from drivers.errors import (
    EmergencyStopError,
    ProtectiveStopError,
    RobotConnectionError,
    RobotError,
)
from drivers.ur_dashboard import dashboard_exchange, parse_identity
from drivers.ur_probe import probe_controller
from drivers.ur_rtde_process import RtdeClientGoneError, RtdeInterface, RtdeProcess

#: Longest wait for the control program's start inside the RTDEControlInterface constructor, s.
PROGRAM_START_S = 6.0
#: Bound of one status call into the ur-rtde process (a stuck process is killed), seconds.
READ_TIMEOUT_S = 10.0

_PROTECTIVE_STOP_MSG = (
    "The robot made a protective stop (usually a collision or a safety limit). Check that "
    "nothing is in the way, unlock the protective stop on the teach pendant, then retry.")
_EMERGENCY_STOP_MSG = (
    "The robot is emergency-stopped. Release the emergency stop button, reset the robot on "
    "the teach pendant, then retry.")


class URRobot(RobotSession):
    """A UR arm driven through ur-rtde; see the module docstring for the connection strategy.

    ``connect_timeout`` bounds each stage of ``connect()`` (seconds: the probe, then the wait
    for the program on the status stream; ur-rtde's own program start takes up to 5 s). A move
    is considered settled once the TCP speed stays below ``settle_speed`` (m/s for the linear
    part, rad/s for the angular part) for ``settle_dwell`` seconds. Moves block until the robot
    is at the target and settled.
    """

    def __init__(self, host: str, *, connect_timeout: float = 5.0, settle_speed: float = 1e-3,
                 settle_dwell: float = 0.2, motion_timeout: float = 120.0) -> None:
        self.host = host
        self.connect_timeout = connect_timeout
        self.settle_speed = settle_speed
        self.settle_dwell = settle_dwell
        self.motion_timeout = motion_timeout
        self._process: RtdeProcess | None = None  # holds the two ur-rtde interfaces
        self._control: RtdeInterface | None = None  # rtde_control.RTDEControlInterface
        self._receive: RtdeInterface | None = None  # rtde_receive.RTDEReceiveInterface
        self._lock = threading.RLock()  # one command at a time: ur-rtde is not thread-safe
        self._moving = False
        self._stop_requested = False
        self._lost = False  # a connection was abandoned; cleared by connect() / close()
        self._identity: RobotIdentity | None = None  # asked once, see identity()

    @classmethod
    def from_url(cls, url: str, *, config: Any = None) -> URRobot:
        """The arm at ``ur://HOST`` (the controller's ports are fixed; ``config`` is unused)."""
        parts = urlsplit(url)
        if not parts.hostname or parts.port is not None or parts.path.strip("/") \
                or parts.query or parts.username:
            raise ValueError(f"{url!r}: a UR address is ur://HOST (an IP address or host name; "
                             "the controller's ports are fixed)")
        return cls(parts.hostname)

    # ---- connection -------------------------------------------------------------------------

    def connect(self) -> None:
        """Connect (again): probe the controller, start ur-rtde and its control program.

        Returns once ``status()`` shows the program running (``RobotError`` code
        ``program_not_started`` otherwise); after a dropped connection this is how to
        reconnect.
        """
        with self._lock:
            self.close()
            probe_controller(self.host, self.connect_timeout)
            self._process = process = RtdeProcess()
            ctor_timeout = self.connect_timeout + PROGRAM_START_S
            try:
                self._receive = RtdeInterface(process, "receive", READ_TIMEOUT_S)
                self._receive.call("__init__", self.host, timeout=ctor_timeout)
                self._control = RtdeInterface(process, "control", None)
                self._control.call("__init__", self.host, timeout=ctor_timeout)
            except RuntimeError as err:
                self._process = self._control = self._receive = None
                process.kill()
                raise self._connect_error(err) from err
            self._wait_program_running()

    def close(self) -> None:
        """Disconnect both interfaces. Safe to call twice and after a lost connection."""
        with self._lock:
            process, self._process = self._process, None
            self._control = self._receive = None
            self._lost = False
            if process is not None:
                process.close()  # the ur-rtde destructors disconnect (about 0.5 s each)

    def _wait_program_running(self) -> None:
        """Block until the receive interface shows the control program running, or raise.

        The receive interface is a second RTDE connection with its own stream, started before
        the control interface (re)starts the program; right after the constructors return its
        latest package may still predate the program (or show the stop of the previous one on
        a reconnect). ``connect()`` returns only once this stream, which ``status()`` reads,
        shows it running.
        """
        deadline = time.monotonic() + self.connect_timeout
        while True:
            try:
                streaming = self._receive.getTimestamp() > 0.0
                status = int(self._receive.getRobotStatus())
                running = bool(status & rtde_wire.STATUS_PROGRAM_RUNNING)
            except RuntimeError:
                streaming = running = False
            if streaming and running:
                return
            if time.monotonic() > deadline:
                break
            time.sleep(0.005)
        self.close()
        if not streaming:
            raise RobotConnectionError(f"The robot controller at {self.host} sends no data.")
        raise RobotError(
            f"The robot at {self.host} did not report the remote-control program running "
            f"within {self.connect_timeout:g} s after starting it. Check the teach pendant for "
            "a message, then connect again.", code="program_not_started")

    def _connect_error(self, err: RuntimeError) -> RobotError:
        """Translate a ur-rtde constructor failure into a typed error."""
        text = str(err).lower()
        if "remote control" in text:
            return RobotError(
                f"The robot at {self.host} is in local mode. Switch it to Remote Control on the "
                "teach pendant (top right corner), then connect again.",
                code="not_in_remote_control")
        if "control script" in text or "script" in text:
            return RobotError(
                f"The robot at {self.host} did not start the remote-control program. Make sure "
                "the arm is powered on with brakes released, no protective or emergency stop is "
                "active and no other program is running, then connect again.",
                code="program_not_started")
        return RobotConnectionError(
            f"Could not connect to the robot controller at {self.host} ({err}). Check the "
            "network connection and that the controller is switched on.")

    # ---- state ------------------------------------------------------------------------------

    def _interfaces(self) -> tuple[RtdeInterface, RtdeInterface]:
        """(control, receive) if both are connected, else RobotConnectionError."""
        control, receive = self._control, self._receive
        if (self._lost or control is None or receive is None
                or not self._link_alive(control, receive)):
            raise self._link_error()
        return control, receive

    def _link_error(self) -> RobotConnectionError:
        """Why the interfaces cannot be used: never connected (or closed), or lost."""
        if self._process is None and not self._lost:
            return RobotConnectionError(
                f"Not connected to the robot at {self.host}. Connect first.",
                code="robot_not_connected")
        return self._lost_connection()

    def _lost_connection(self, during: str = "", then: str = "") -> RobotConnectionError:
        """The error for a lost connection, which is given up here: its ur-rtde process is
        killed (left alone, its interfaces would reconnect by themselves beside the next)."""
        crash = self._abandon()
        return RobotConnectionError(
            f"Lost the connection to the robot controller at {self.host}{during}{crash}. Check "
            f"the network cable and that the controller is on, then reconnect{then}.")

    @staticmethod
    def _link_alive(control: object, receive: object) -> bool:
        try:
            return bool(receive.isConnected() and control.isConnected())
        except RuntimeError:
            return False

    def _receive_values(self, *getters: str) -> list[Any] | None:
        """Readings of the receive interface with the link check (both interfaces connected)
        in one call into the ur-rtde process; None if not connected. ur-rtde's RuntimeError
        (or RtdeClientGoneError) is raised as it is."""
        process = self._process
        if process is None or self._lost:
            return None
        calls = [("receive", "isConnected", ()), ("control", "isConnected", ()),
                 *(("receive", getter, ()) for getter in getters)]
        receive_up, control_up, *values = process.call_all(calls, timeout=READ_TIMEOUT_S)
        return values if receive_up and control_up else None

    def _read(self, getter: str) -> object:
        try:
            values = self._receive_values(getter)
        except RuntimeError as err:
            raise self._runtime_error(err) from err
        if values is None:
            raise self._link_error()
        return values[0]

    def tcp_pose(self) -> np.ndarray:
        """Actual TCP pose, shape (6,), T_base_tcp as a UR pose vector."""
        return np.asarray(self._read("getActualTCPPose"), dtype=float)

    def joint_positions(self) -> np.ndarray:
        """Actual joint angles, shape (6,), radians."""
        return np.asarray(self._read("getActualQ"), dtype=float)

    def identity(self) -> RobotIdentity:
        """Model, serial number and PolyScope version from the dashboard, asked once (serial
        numbers are answered from PolyScope 5.6 on; older controllers leave it None)."""
        if self._identity is None:
            try:
                replies = dashboard_exchange(
                    self.host, ["get robot model", "get serial number", "PolyscopeVersion"],
                    self.connect_timeout)
            except OSError as err:
                raise RobotConnectionError(
                    f"The robot controller at {self.host} did not tell its identity on the "
                    f"dashboard ({err.strerror or err}).") from None
            self._identity = RobotIdentity(**parse_identity(*replies))
        return self._identity

    def status(self) -> RobotStatus:
        """Current controller state; ``connected=False`` rather than an error when offline."""
        try:
            values = self._receive_values("getSafetyStatusBits", "getRobotStatus",
                                          "getRobotMode")
        except RuntimeError:
            values = None
        if values is None:
            return RobotStatus(connected=False)
        safety, robot_status, mode = (int(v) for v in values)
        return RobotStatus(
            connected=True,
            program_running=bool(robot_status & rtde_wire.STATUS_PROGRAM_RUNNING),
            protective_stop=bool(safety & rtde_wire.SAFETY_PROTECTIVE_STOP),
            emergency_stop=bool(safety & rtde_wire.SAFETY_EMERGENCY_STOPS),
            mode=rtde_wire.ROBOT_MODES.get(mode, "unknown"))

    def _raise_if_stopped(self) -> None:
        """ProtectiveStopError / EmergencyStopError if the robot is safety-stopped."""
        st = self.status()
        if not st.connected:
            self._interfaces()  # raises the connection error
        if st.emergency_stop:
            raise EmergencyStopError(_EMERGENCY_STOP_MSG)
        if st.protective_stop:
            raise ProtectiveStopError(_PROTECTIVE_STOP_MSG)

    # ---- motion -----------------------------------------------------------------------------

    def move_linear(self, pose: np.ndarray, *, speed: float = 0.25,
                    acceleration: float = 1.2) -> None:
        """Move the TCP in a straight line to ``pose`` (shape (6,)); returns once settled."""
        check_ur_pose(pose, "pose")  # shape, finite, metres
        self._move("moveL", np.asarray(pose, dtype=float), speed, acceleration)

    def move_joint(self, q: np.ndarray, *, speed: float = 1.05,
                   acceleration: float = 1.4) -> None:
        """Move in joint space to ``q`` (shape (6,), radians); returns once settled."""
        self._move("moveJ", check_joint_positions(q), speed, acceleration)

    def _move(self, method: str, target: np.ndarray, speed: float, acceleration: float) -> None:
        if speed <= 0.0 or acceleration <= 0.0:
            raise ValueError("speed and acceleration must be positive")
        with self._lock:
            control, _ = self._interfaces()
            self._raise_if_stopped()
            self._ensure_program(control)
            self._moving, self._stop_requested = True, False
            try:
                ok = self._guarded(getattr(control, method), target.tolist(), speed,
                                   acceleration, timeout=self.motion_timeout)
            finally:
                self._moving = False
            if not ok:
                raise self._move_failure()
        self.wait_settled(timeout=self.motion_timeout)

    def _guarded(self, fn: Callable[..., bool], *args: object, timeout: float) -> bool:
        """Run a blocking ur-rtde call in a worker thread while watching the link.

        ur-rtde calls release the GIL, so this thread can watch: if the receive interface loses
        the connection (the client's own recovery can then wait for minutes) or ``timeout``
        passes, the connection is abandoned and a typed error raised at once. A RuntimeError
        from the call becomes a typed error too.
        """
        outcome: dict[str, object] = {}

        def work() -> None:
            try:
                outcome["value"] = fn(*args)
            except RuntimeError as err:
                outcome["error"] = err

        worker = threading.Thread(target=work, name="ur-rtde-call", daemon=True)
        worker.start()
        deadline = time.monotonic() + timeout
        while worker.is_alive():
            worker.join(0.02)
            if not worker.is_alive():
                break
            receive = self._receive
            try:
                alive = receive is not None and receive.isConnected()
            except RuntimeError:
                alive = False
            if not alive:
                raise self._lost_connection(
                    " during a move", "; the robot may have stopped anywhere along the path")
            if time.monotonic() > deadline:
                self._abandon()
                raise RobotError(
                    f"The robot did not finish within {timeout:g} s; the connection was "
                    "closed. Check the teach pendant, then reconnect.", code="robot_timeout")
        if "error" in outcome:
            raise self._runtime_error(outcome["error"])
        return bool(outcome.get("value"))

    def _abandon(self) -> str:
        """Forget a broken connection whose control call may be stuck in a worker thread.

        The ur-rtde process is killed (its interfaces would otherwise reconnect by themselves
        beside the next connection); the stuck call then ends with RtdeClientGoneError. Returns
        ``" (the ur-rtde client crashed: SIGSEGV)"`` if the process had died by itself, else "".
        """
        process, self._process = self._process, None
        self._receive = self._control = None
        self._lost = True
        if process is None:
            return ""
        crash = process.crash()
        process.kill()
        return f" (the ur-rtde client crashed: {crash})" if crash else ""

    def _ensure_program(self, control: object) -> None:
        """Restart the control program if it stopped (e.g. after an unlocked protective stop)."""
        try:
            running = control.isProgramRunning()
        except RuntimeError as err:
            raise self._runtime_error(err) from err
        if running:
            return
        self._guarded(control.reuploadScript, timeout=self.connect_timeout + 6.0)
        deadline = time.monotonic() + self.connect_timeout
        # The control interface has its own state stream; its view must show the program.
        while not self._guarded(control.isProgramRunning, timeout=self.connect_timeout):
            if time.monotonic() > deadline:
                raise RobotError(
                    f"The robot at {self.host} did not restart the remote-control program. "
                    "Check the teach pendant for a message, then reconnect.",
                    code="program_not_started")
            time.sleep(0.01)

    def _move_failure(self) -> RobotError:
        """Why ur-rtde reported a failed move, as a typed error (waits briefly for the cause)."""
        deadline = time.monotonic() + 0.5
        while True:
            st = self.status()
            if not st.connected:
                return self._lost_connection(" during a move")
            if st.emergency_stop:
                return EmergencyStopError(_EMERGENCY_STOP_MSG)
            if st.protective_stop:
                return ProtectiveStopError(_PROTECTIVE_STOP_MSG)
            if self._stop_requested:
                return RobotError("The move was stopped on request.", code="motion_stopped")
            if time.monotonic() > deadline:
                break
            time.sleep(0.01)
        if not st.program_running:
            return RobotError(
                "The robot's remote-control program stopped during the move. Check the teach "
                "pendant for a message, then retry.", code="program_stopped")
        return RobotError(
            "The robot did not complete the move: the target may be out of reach or outside "
            "the safety limits.", code="motion_failed")

    def _runtime_error(self, err: RuntimeError) -> RobotError:
        """Any other ur-rtde RuntimeError: a connection problem if the link is gone."""
        text = str(err).lower()
        lost = ("connect", "refused", "timed out", "broken pipe", "eof", "reset by peer")
        if (isinstance(err, RtdeClientGoneError) or any(w in text for w in lost)
                or not self.status().connected):
            return self._lost_connection()
        return RobotError(f"The robot controller reported an error: {err}.")

    def wait_settled(self, *, timeout: float = 5.0) -> None:
        """Block until the TCP speed stays below ``settle_speed`` for ``settle_dwell`` seconds."""
        deadline = time.monotonic() + timeout
        quiet_since: float | None = None
        while True:
            speed = np.asarray(self._read("getActualTCPSpeed"), dtype=float)
            now = time.monotonic()
            if (np.linalg.norm(speed[:3]) < self.settle_speed
                    and np.linalg.norm(speed[3:]) < self.settle_speed):
                quiet_since = now if quiet_since is None else quiet_since
                if now - quiet_since >= self.settle_dwell:
                    return
            else:
                quiet_since = None
                self._raise_if_stopped()
            if now > deadline:
                self._raise_if_stopped()
                raise RobotError(
                    f"The robot did not come to rest within {timeout:g} s.", code="not_settled")
            time.sleep(0.004)

    def stop(self) -> None:
        """Stop any motion: stopL when idle; during a blocking move, the dashboard ``stop``."""
        if self._moving:
            self._stop_requested = True
            try:
                dashboard_exchange(self.host, ["stop"], self.connect_timeout)
            except OSError:
                raise RobotConnectionError(
                    f"Could not reach the robot at {self.host} to stop it. Use the emergency "
                    "stop if the robot is still moving.") from None
            return
        with self._lock:
            control, _ = self._interfaces()
            self._guarded(control.stopL, 2.0, timeout=self.connect_timeout)
