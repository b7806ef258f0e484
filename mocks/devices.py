"""Simulated robot for a mock scene: the ``Robot`` Protocol (its camera: ``mocks.camera``).

``MockRobot`` holds the *true* TCP pose and reports it with the scene's robot noise;
``mocks.camera.MockCamera`` renders the scene's board from the robot's true pose with the
scene's image noise and blur. Both are instant by default (ophyd-async
``SimMotor(instant=True)``); realistic timing is on request. Both fail on purpose: faults are
injected with ``inject_fault`` (or the robot's ``faults`` argument) and surface as the same
typed errors the real drivers raise.

Noise model. A real controller reading at rest is stable: it differs from the true pose by the
arm's calibration error for that configuration, not by fresh noise on every read. So the robot
draws one noise transform (``calib.geometry.perturb``: Gaussian angle of sigma
``robot_rot_deg`` about a random axis, Gaussian length of sigma ``robot_trans_mm`` in a random
direction) each time a motion ends, and ``tcp_pose()`` returns ``true @ noise`` until the next
motion ends. A scene with ``kinematics`` (UR5e DH offsets) also gives the arm systematic
errors: the camera sees from the commanded pose moved by the arm's kinematic error there,
while the reading stays the commanded pose with its noise.

Kinematics. The mock is a Cartesian robot: ``move_linear`` accepts any pose inside the
workspace box. Joint space is a UR5e (``mocks.ur_kinematics``, TCP = flange): ``move_joint``
goes through forward kinematics, and ``joint_positions()`` solves inverse kinematics, which
fails (``RobotError`` code ``joints_unknown``) for poses beyond a UR5e's 0.85 m reach — the
default scene's stations reach about 1.2 m from the base.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calib import (
    check_joint_positions,
    check_ur_pose,
    matrix_from_ur_pose,
    perturb,
    ur_pose_from_matrix,
)
from drivers.base import BoardTruth, CellHints, RobotIdentity, RobotSession, RobotStatus
from drivers.errors import (
    ProtectiveStopError,
    RobotConnectionError,
    RobotError,
    WorkspaceError,
)
from mocks import ur_kinematics as kin
from mocks.scene import MockScene, read_scene
from mocks.ur_emulator.controller import trapezoid_fraction

#: Robot faults: each affects the next move only (``slow`` its settling), see ``inject_fault``.
ROBOT_FAULTS = ("protective_stop", "disconnect", "unreachable", "slow")

#: Motion update period (s) of a timed move.
_TICK = 0.01
#: Extra settling time (s) of the ``slow`` fault when no value is given.
_DEFAULT_SLOW_S = 10.0


@dataclass(frozen=True)
class Workspace:
    """An axis-aligned box in the base frame (metres) that TCP targets must lie in.

    The default is a 3 m wide box above the base's z = 0 plane (the table the robot stands on):
    it holds every station of the default scene and refuses targets below the table.
    """

    lo: tuple[float, float, float] = (-1.5, -1.5, 0.0)
    hi: tuple[float, float, float] = (1.5, 1.5, 1.5)

    def check(self, pose: np.ndarray) -> None:
        """Raise ``WorkspaceError`` if the position of UR pose ``pose`` (6,) is outside."""
        p = np.asarray(pose, dtype=float)[:3]
        if np.all(p >= self.lo) and np.all(p <= self.hi):
            return
        mm = ", ".join(f"{v * 1e3:.0f}" for v in p)
        box = " x ".join(f"[{a * 1e3:.0f}, {b * 1e3:.0f}]"
                         for a, b in zip(self.lo, self.hi, strict=True))
        raise WorkspaceError(f"Target position ({mm}) mm is outside the workspace limits "
                             f"{box} mm (base frame); the robot was not moved.")


def check_mock_url(url: str, device: str) -> None:
    """A mock device is addressed as just ``mock://`` (its cell comes from the scene)."""
    if url.lower() != "mock://":
        raise ValueError(f"{url!r}: a mock {device} is addressed as just mock:// "
                         "(choose its cell with a scene file)")


def parse_fault(spec: str, known: tuple[str, ...]) -> tuple[str, float | None]:
    """``NAME`` or ``NAME=VALUE`` -> (name, value or None); ValueError for unknown names."""
    name, _, value = spec.partition("=")
    name = name.strip()
    if name not in known:
        raise ValueError(f"unknown fault {name!r}; known: {', '.join(known)}")
    try:
        return name, float(value) if value else None
    except ValueError:
        raise ValueError(f"fault {name!r}: value {value!r} is not a number") from None


@dataclass(frozen=True)
class MockTiming:
    """How a mock robot moves in time.

    ``instant``: moves take no time and settle at once; otherwise they follow a trapezoidal
    velocity profile (as the UR emulator does) and then ring out for ``settle_time`` s.
    ``speed``: the speed slider, the fraction of the commanded speed and acceleration used.
    """

    instant: bool = True
    speed: float = 1.0
    settle_time: float = 0.2


class MockRobot(RobotSession):
    """A simulated arm implementing ``drivers.base.Robot`` over a ``MockScene``.

    Parameters
    ----------
    scene : the cell; the robot starts at ``scene.start_pose()``.
    timing : instant moves (the default) or timed ones, see ``MockTiming``.
    seed : seed of the robot noise draws (default: the scene's seed).
    workspace : limits every move target must respect.
    faults : fault specs ``NAME[=VALUE]`` injected from the start (see :meth:`inject_fault`).
    """

    def __init__(self, scene: MockScene, *, timing: MockTiming = MockTiming(),
                 seed: int | None = None, workspace: Workspace | None = None,
                 faults: Iterable[str] = ()) -> None:
        if not 0.0 < timing.speed <= 1.0:
            raise ValueError(f"speed slider must be in (0, 1], got {timing.speed}")
        self.scene = scene
        self.instant = timing.instant
        self.speed = timing.speed
        self.settle_time = 0.0 if timing.instant else timing.settle_time
        self.workspace = workspace if workspace is not None else Workspace()
        self._rng = np.random.default_rng([scene.seed if seed is None else seed, 1])
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._T = scene.start_pose()  # where the controller believes the tcp is
        self._kin = np.eye(4)  # T_tcp_truetcp: the arm's kinematic error at rest there
        if scene.kinematics is not None:
            # a start beyond the UR5e's reach: no kinematic error until the first move
            with contextlib.suppress(ValueError):
                self._kin = kin.kinematic_error(self._T, scene.kinematics.offsets())
        self._noise = self._draw_noise()
        self._q: np.ndarray | None = None  # joints, when known from a joint move
        self._q_seed = kin.HOME_Q.copy()
        self._connected = False
        self._protective_stop = False
        self._moving = False
        self._settled_at = 0.0
        self._faults: dict[str, float | None] = {}
        #: Moves refused by the scene's safety box (``MockScene.workspace``), since creation.
        self.refused_moves = 0
        for spec in faults:
            self.inject_fault(*parse_fault(spec, ROBOT_FAULTS))

    # ---- construction from the registry, capabilities ---------------------------------------

    @classmethod
    def from_url(cls, url: str, *, config: Any = None) -> MockRobot:
        """The robot of ``mock://`` over the scene ``config`` (a scene, a file, None: default);
        a :class:`BlindMockRobot` for a blind scene."""
        check_mock_url(url, "robot")
        scene = read_scene(config)
        return BlindMockRobot(scene) if scene.blind else cls(scene)

    @classmethod
    def describe_cell(cls, config: Any) -> CellHints:
        """``drivers.base.DescribesCell``: the scene's setup, board, hand-eye and camera; of a
        blind scene only the setup and board, what a user configures on a real cell."""
        scene = read_scene(config)
        if scene.blind:
            return CellHints(setup=scene.setup, target=scene.nominal_target())
        return CellHints(setup=scene.setup, target=scene.nominal_target(),
                         hand_eye=scene.hand_eye_matrix,
                         K=scene.camera.k_matrix, dist=scene.camera.dist_coeffs)

    def true_tcp_pose(self) -> np.ndarray:
        """``drivers.base.GroundTruthSource``: the true T_base_tcp, shape (4, 4)."""
        return self.true_pose

    def true_board(self) -> BoardTruth:
        """``drivers.base.GroundTruthSource``: the scene's board through its true κ, ν."""
        t = self.scene.target
        return BoardTruth(T_base_target=self.scene.target_pose_matrix,
                          square_size_m=t.square_size_m * t.kappa, nu=t.nu, source="mock scene")

    # ---- simulation controls ----------------------------------------------------------------

    @property
    def true_pose(self) -> np.ndarray:
        """The true (noise-free) T_base_tcp, shape (4, 4): what the camera sees from.

        The commanded pose moved by the scene's kinematic error (``MockScene.kinematics``).
        """
        with self._lock:
            return self._T @ self._kin

    def inject_fault(self, name: str, value: float | None = None) -> None:
        """Make the next move fail or misbehave.

        ``protective_stop``: the move stops half way with a protective stop, which stays until
        :meth:`unlock_protective_stop`. ``disconnect``: the connection drops half way; every
        call raises ``RobotConnectionError`` until :meth:`connect`. ``unreachable``: the move
        is refused (code ``motion_failed``) and the robot stays put. ``slow``: the move takes
        ``value`` s (default 10) longer to settle, so a shorter ``wait_settled`` times out.
        """
        parse_fault(name, ROBOT_FAULTS)
        with self._lock:
            self._faults[name] = value

    def clear_faults(self) -> None:
        """Remove pending faults and unlock a protective stop."""
        with self._lock:
            self._faults.clear()
            self._protective_stop = False

    def unlock_protective_stop(self) -> None:
        """Clear a protective stop, as the teach pendant does."""
        with self._lock:
            self._protective_stop = False

    # ---- Robot Protocol ---------------------------------------------------------------------

    def connect(self) -> None:
        """Connect (again); never fails: a lost connection is restored."""
        with self._lock:
            self._connected = True

    def close(self) -> None:
        """Disconnect. Safe to call twice."""
        with self._lock:
            self._connected = False

    def tcp_pose(self) -> np.ndarray:
        """Reported TCP pose, shape (6,): the true pose with this rest's noise draw."""
        with self._lock:
            self._check_link()
            return ur_pose_from_matrix(self._T @ self._noise)

    def joint_positions(self) -> np.ndarray:
        """Joint angles, shape (6,), of the UR5e model; ``joints_unknown`` beyond its reach."""
        with self._lock:
            self._check_link()
            if self._q is None:
                q = kin.ik(ur_pose_from_matrix(self._T), self._q_seed)
                if q is None:
                    raise RobotError(
                        "The mock robot's TCP pose is beyond the reach of the UR5e model it "
                        "uses for joint positions; joint positions are unknown here.",
                        code="joints_unknown")
                self._q = self._q_seed = q
            return self._q.copy()

    def move_linear(self, pose: np.ndarray, *, speed: float = 0.25,
                    acceleration: float = 1.2) -> None:
        """Move the TCP in a straight line to ``pose`` (shape (6,)); blocks until there."""
        T1 = check_ur_pose(pose, "pose")
        with self._lock:
            T0 = self._T.copy()
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix([T0[:3, :3], T1[:3, :3]]))
        lin = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        ang = float(np.linalg.norm((slerp(1.0) * slerp(0.0).inv()).as_rotvec()))

        def path(s: float) -> tuple[np.ndarray, np.ndarray | None]:
            T = T1.copy() if s >= 1.0 else np.eye(4)
            if s < 1.0:
                T[:3, :3] = slerp(s).as_matrix()
                T[:3, 3] = T0[:3, 3] + s * (T1[:3, 3] - T0[:3, 3])
            return T, None

        self._move(pose, lin if lin > 1e-6 else ang, speed, acceleration, path)

    def move_joint(self, q: np.ndarray, *, speed: float = 1.05,
                   acceleration: float = 1.4) -> None:
        """Move in joint space to ``q`` (shape (6,), radians); the TCP follows UR5e FK."""
        q1 = check_joint_positions(q)
        q0 = self.joint_positions()

        def path(s: float) -> tuple[np.ndarray, np.ndarray | None]:
            qs = q1 if s >= 1.0 else q0 + s * (q1 - q0)
            return kin.fk_matrix(qs), qs

        self._move(kin.fk_pose(q1), float(np.abs(q1 - q0).max()), speed, acceleration, path)

    def wait_settled(self, *, timeout: float = 5.0) -> None:
        """Block until no move is running and the last one has rung out, or raise
        ``RobotError`` (code ``not_settled``) after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                self._check_link()
                rest_at = np.inf if self._moving else self._settled_at
            now = time.monotonic()
            if now >= rest_at:
                return
            if now >= deadline:
                raise RobotError(f"The robot did not come to rest within {timeout:g} s.",
                                 code="not_settled")
            time.sleep(min(rest_at, deadline, now + _TICK) - now)

    def stop(self) -> None:
        """Stop a move in progress where it is (the move raises ``motion_stopped``)."""
        self._stop.set()

    def identity(self) -> RobotIdentity:
        """A simulator: its model says so; it has no serial number or controller version."""
        return RobotIdentity(model="cellcal mock (a simulated arm)")

    def status(self) -> RobotStatus:
        """Current simulated controller state."""
        with self._lock:
            return RobotStatus(connected=self._connected, program_running=self._connected,
                               protective_stop=self._protective_stop,
                               mode="running" if self._connected else "disconnected")

    # ---- internals --------------------------------------------------------------------------

    def _check_link(self) -> None:
        """RobotConnectionError unless connected (call with the lock held)."""
        if not self._connected:
            raise RobotConnectionError("Not connected to the mock robot. Connect first.",
                                       code="robot_not_connected")

    def _take_move_faults(self) -> tuple[str | None, float]:
        """The injected faults a move consumes (call holding the lock): raises for an
        ``unreachable`` target; the fault that breaks the move midway (or None) and the extra
        settling time of a ``slow`` one."""
        if "unreachable" in self._faults:
            del self._faults["unreachable"]
            raise RobotError(
                "The robot did not complete the move: the target may be out of reach or "
                "outside the safety limits.", code="motion_failed")
        fault = next((f for f in ("protective_stop", "disconnect") if f in self._faults), None)
        if fault:
            del self._faults[fault]
        extra_settle = 0.0
        if "slow" in self._faults:
            value = self._faults.pop("slow")
            extra_settle = _DEFAULT_SLOW_S if value is None else max(value, 0.0)
        return fault, extra_settle

    def _kinematic_error(self, pose: np.ndarray) -> np.ndarray:
        """T_tcp_truetcp at rest at UR pose ``pose`` (6,); identity without kinematics."""
        if self.scene.kinematics is None:
            return np.eye(4)
        try:
            return kin.kinematic_error(check_ur_pose(pose, "pose"),
                                       self.scene.kinematics.offsets(), self._q_seed)
        except ValueError:
            raise RobotError("The target is beyond the reach of the simulated UR5e, whose "
                             "kinematic errors the scene defines; the robot was not moved.",
                             code="motion_failed") from None

    def _check_safety_box(self, target: np.ndarray) -> None:
        """Refuse a move ending outside the scene's safety box (the tcp, and eye-in-hand the
        camera) with a protective stop, counted in ``refused_moves`` (call holding the lock)."""
        box = self.scene.workspace
        if box is None:
            return
        T = matrix_from_ur_pose(np.asarray(target, dtype=float))
        points = {"tcp": T[:3, 3]}
        if self.scene.setup == "eye_in_hand":
            points["camera"] = (T @ self.scene.hand_eye_matrix)[:3, 3]
        outside = [name for name, p in points.items() if not box.contains(p)]
        if outside:
            self.refused_moves += 1
            self._protective_stop = True
            raise ProtectiveStopError(
                f"Protective stop: the move would take the {' and '.join(outside)} outside the "
                "cell's safety box; the robot was not moved.")

    def _draw_noise(self) -> np.ndarray:
        """One reading-error transform (4, 4) from the scene's robot noise."""
        n = self.scene.noise
        return perturb(np.eye(4), np.deg2rad(n.robot_rot_deg), n.robot_trans_mm * 1e-3,
                       self._rng)

    def _move(self, target: np.ndarray, distance: float, speed: float, acceleration: float,
              path: Callable[[float], tuple[np.ndarray, np.ndarray | None]]) -> None:
        """Check, then play ``path`` (fraction -> (T_base_tcp, joints or None)) with faults."""
        if speed <= 0.0 or acceleration <= 0.0:
            raise ValueError("speed and acceleration must be positive")
        with self._lock:
            self._check_link()
            if self._moving:
                raise RobotError("The robot is already moving.", code="robot_busy")
            if self._protective_stop:
                raise ProtectiveStopError(
                    "The robot is in a protective stop. Unlock it, then retry.")
            self._check_safety_box(target)
            self.workspace.check(target)
            kin_error = self._kinematic_error(target)
            fault, extra_settle = self._take_move_faults()
            self._moving = True
            self._stop.clear()
        v, a = speed * self.speed, acceleration * self.speed
        start = time.monotonic()
        try:
            while True:
                s = (1.0 if self.instant else
                     trapezoid_fraction(time.monotonic() - start, distance, v, a))
                if fault:
                    s = min(s, 0.5)
                T, q = path(s)
                with self._lock:
                    self._T, self._q, self._kin = T, q, kin_error
                    if q is not None:
                        self._q_seed = q
                if fault and s >= 0.5:
                    self._fail_mid_move(fault)
                if s >= 1.0:
                    return
                if self._stop.is_set():
                    raise RobotError("The move was stopped on request.", code="motion_stopped")
                time.sleep(_TICK)
        finally:
            with self._lock:
                self._moving = False
                self._noise = self._draw_noise()
                self._settled_at = time.monotonic() + self.settle_time + extra_settle

    def _fail_mid_move(self, fault: str) -> None:
        """Raise the error of a mid-move ``protective_stop`` or ``disconnect`` fault."""
        with self._lock:
            if fault == "protective_stop":
                self._protective_stop = True
            else:
                self._connected = False
        if fault == "protective_stop":
            raise ProtectiveStopError(
                "The robot made a protective stop (usually a collision or a safety limit). "
                "Check that nothing is in the way, unlock the protective stop, then retry.")
        raise RobotConnectionError(
            "Lost the connection to the mock robot during a move; the robot may have stopped "
            "anywhere along the path. Reconnect.")


class BlindMockRobot(MockRobot):
    """The robot of a blind scene (``MockScene.blind``): a mock robot that, like a real one,
    offers no ground truth (not a ``drivers.base.GroundTruthSource``)."""

    true_tcp_pose = None  # type: ignore[assignment]
    true_board = None  # type: ignore[assignment]
