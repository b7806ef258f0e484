"""The two small interfaces every robot and camera backend implements.

Drivers (real devices) and mocks (simulated ones) satisfy the same Protocols, so service code
never imports a concrete backend: it opens a device from its URL (``drivers.open_robot``).
All poses are UR pose vectors ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians),
base_T_tcp; joint positions are radians. See ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

import numpy as np


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
        """Actual TCP pose, shape (6,), base_T_tcp as a UR pose vector."""

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


class RobotSession:
    """Mixin: ``with robot:`` connects on entry and closes on exit."""

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class CameraSession:
    """Mixin: ``with camera:`` opens on entry and closes on exit."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
