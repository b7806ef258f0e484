"""The two small interfaces every robot and camera backend implements, and the capabilities a
backend may offer besides.

Drivers (real devices) and mocks (simulated ones) satisfy the same Protocols, so service code
never imports a concrete backend: it opens a device from its URL (``drivers.registry``).
All poses are UR pose vectors ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians),
T_base_tcp; joint positions are radians. See ``docs/conventions.md``.

Capabilities are Protocols too, checked with ``isinstance`` / ``issubclass``: a backend that
knows its cell roughly (``DescribesCell``, e.g. a simulator) spares the user the planning
guesses; one that knows the truth (``GroundTruthSource``) lets a validation report its error
against it. Code that uses them never asks which backend it has.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, Self, runtime_checkable

import numpy as np

from calib import BoardTarget


@dataclass(frozen=True)
class RobotStatus:
    """A snapshot of the controller state that matters before and during a motion."""

    connected: bool
    program_running: bool = False
    protective_stop: bool = False
    emergency_stop: bool = False
    mode: str = "unknown"

    @property
    def ready(self) -> bool:
        return self.connected and not (self.protective_stop or self.emergency_stop)


@runtime_checkable
class Robot(Protocol):
    """A robot arm that can report and move its tool centre point."""

    def connect(self) -> None:
        """Open the connection; raises ``RobotConnectionError`` within the driver's timeout."""

    def close(self) -> None:
        """Release the connection. Safe to call twice."""

    def tcp_pose(self) -> np.ndarray:
        """Actual TCP pose, shape (6,), T_base_tcp as a UR pose vector."""

    def joint_positions(self) -> np.ndarray:
        """Actual joint angles, shape (6,), radians."""

    def move_linear(self, pose: np.ndarray, *, speed: float = 0.25,
                    acceleration: float = 1.2) -> None:
        """Move the TCP in a straight line to ``pose`` (shape (6,)); blocks until done.

        ``speed`` m/s, ``acceleration`` m/s^2. Raises ``RobotError`` subclasses on faults.
        """

    def move_joint(self, q: np.ndarray, *, speed: float = 1.05,
                   acceleration: float = 1.4) -> None:
        """Move in joint space to ``q`` (shape (6,), radians); blocks until done."""

    def wait_settled(self, *, timeout: float = 5.0) -> None:
        """Block until the TCP is at rest (speed near zero, then a dwell), or raise."""

    def stop(self) -> None:
        """Decelerate and stop any motion."""

    def status(self) -> RobotStatus:
        """Current controller state."""


@runtime_checkable
class Camera(Protocol):
    """A camera that delivers frames taken after the call (never a stale buffered one)."""

    def open(self) -> None:
        """Open the device, or open it again after a loss; ``CameraError`` if it is missing."""

    def close(self) -> None:
        """Release the device. Safe to call twice."""

    @property
    def opened(self) -> bool:
        """True from ``open()`` until ``close()`` or the loss of the device (unplugged:
        code ``camera_disconnected``; stalled: ``camera_stalled``)."""

    def grab(self, *, timeout: float = 2.0) -> np.ndarray:
        """A fresh frame, shape (H, W) uint8 grey or (H, W, 3) uint8 BGR.

        Raises ``CameraTimeoutError`` if no frame arrives within ``timeout`` seconds, and
        ``CameraStalledError`` (closing the camera) instead for the ``drivers.stall.STALL_AFTER``-th
        timeout in a row.
        """

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    def configure(self, *, resolution: tuple[int, int] | None = None,
                  exposure: float | None = None) -> None:
        """Request a resolution and/or exposure (seconds); unsupported requests raise."""


@dataclass(frozen=True)
class RobotIdentity:
    """Which robot this is, as its controller tells it (None: the controller does not say).
    The report names it so that a signed calibration points at one physical arm."""

    model: str | None = None
    serial: str | None = None
    controller_version: str | None = None


@runtime_checkable
class DescribesRobot(Protocol):
    """Capability of a robot: it can say which robot it is."""

    def identity(self) -> RobotIdentity:
        """Model, serial number and controller version, as far as the controller knows."""


@runtime_checkable
class ReportsFreshness(Protocol):
    """Capability of a camera: it says how its last grabbed frame was made fresh (stale
    buffered or late frames skipped), one line kept with the captured station."""

    freshness: str | None


@dataclass(frozen=True)
class CellHints:
    """What is known roughly about a cell before it is calibrated (None: not known).

    ``hand_eye`` is T_tcp_cam (eye-in-hand) or T_base_cam (eye-to-hand), shape (4, 4); ``K``
    shape (3, 3) and ``dist`` shape (n,) in pixels; ``target`` the board, as the one target
    type of ``calib.boards`` (checkerboard or ChArUco).
    """

    setup: str | None = None
    target: BoardTarget | None = None
    hand_eye: np.ndarray | None = None
    K: np.ndarray | None = None
    dist: np.ndarray | None = None


@runtime_checkable
class DescribesCell(Protocol):
    """Capability of a robot class: it knows its cell roughly before connecting (a simulator
    knows its scene). ``config`` is the device configuration the registry was given."""

    @classmethod
    def describe_cell(cls, config: Any) -> CellHints:
        """The cell's rough description; ``ValueError`` for an unusable ``config``."""


@dataclass(frozen=True)
class BoardTruth:
    """The true board: T_base_target (4, 4), its true square size (m, along the rows) and
    aspect ratio ν; ``source`` names where the truth comes from."""

    T_base_target: np.ndarray
    square_size_m: float
    nu: float
    source: str


@runtime_checkable
class GroundTruthSource(Protocol):
    """Capability of a robot: it knows the cell exactly (a simulated cell does)."""

    def true_tcp_pose(self) -> np.ndarray:
        """The true T_base_tcp, shape (4, 4), without the reading's noise."""

    def true_board(self) -> BoardTruth:
        """The board as it really is."""


class RobotSession:
    """Mixin of robot classes: ``with robot:`` connects on entry and closes on exit.

    The registry builds a robot with ``from_url(url, config=...)`` (each class parses its own
    address; ``config`` is an optional device configuration: a file path or an object).
    """

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class CameraSession:
    """Mixin of camera classes: ``with camera:`` opens on entry and closes on exit.

    The registry builds a camera with ``from_url(url, config=..., robot=...)``. A camera that
    only works with a particular robot (a simulated camera renders what its robot sees) names
    that robot's address in ``companion_robot`` and refuses others in ``check_robot``.
    """

    #: Address of the robot this camera needs opened with it; None for a real camera.
    companion_robot: ClassVar[str | None] = None

    @classmethod
    def check_robot(cls, robot_url: str) -> None:
        """Raise ``ValueError`` if this camera cannot work with the robot at ``robot_url``."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
