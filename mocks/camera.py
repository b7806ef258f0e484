"""Simulated camera for a mock scene: the ``Camera`` Protocol, rendering what the mock robot
sees (``mocks.devices.MockRobot``) with the scene's image noise."""

from __future__ import annotations

import threading
import time
from typing import Any, ClassVar
from urllib.parse import urlsplit

import numpy as np

from drivers.base import CameraSession, Robot
from drivers.errors import CameraError, CameraStalledError, CameraTimeoutError
from drivers.stall import StallCounter
from mocks.devices import MockRobot, check_mock_url, parse_fault
from mocks.render import RenderParams, render_board
from mocks.scene import MockScene, camera_pose_for_tcp, read_scene

#: Camera faults, see ``MockCamera.inject_fault``.
CAMERA_FAULTS = ("timeout", "corrupt", "disconnect", "unplug", "stall", "freeze")


class MockCamera(CameraSession):
    """A simulated camera implementing ``drivers.base.Camera``: renders what the robot sees.

    Each grab renders the scene's true board (``mocks.render.render_board``) from the robot's
    *true* pose at the time of the call (``camera_pose_for_tcp``), with fresh image noise from
    a generator seeded by ``seed`` (default: the scene's seed). ``instant=False`` waits one to
    two frame periods of ``fps``, like a live camera delivering the next full frame. Grab
    timeouts count towards a stall as on a real camera (``drivers.stall``; ``stall.limit``).
    """

    def __init__(self, scene: MockScene, robot: MockRobot, *, instant: bool = True,
                 fps: float = 30.0, seed: int | None = None) -> None:
        if fps <= 0.0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.scene = scene
        self.robot = robot
        self.instant = instant
        self.fps = fps
        self._params = RenderParams.from_scene(scene)
        self._rng = np.random.default_rng([scene.seed if seed is None else seed, 2])
        self._opened = False
        self._faults: dict[str, int] = {}
        self._lock = threading.Lock()
        self.stall = StallCounter()
        self._T_mount_cam = np.eye(4)  # how far the camera moved on its mount (shift_mount)
        #: How the last frame was made fresh (``drivers.base.ReportsFreshness``).
        self.freshness: str | None = None
        self._last: np.ndarray | None = None  # the last frame delivered (``freeze``)

    companion_robot: ClassVar[str | None] = "mock://"

    @classmethod
    def from_url(cls, url: str, *, config: Any = None, robot: Robot | None = None) -> MockCamera:
        """The camera of ``mock://``, riding on the mock ``robot`` and sharing its scene
        (``config``, if given, must be that scene)."""
        check_mock_url(url, "camera")
        if not isinstance(robot, MockRobot):
            raise ValueError("a mock:// camera renders what the mock robot sees: open the "
                             "robot as mock:// too and pass it to open_camera")
        if config is not None and read_scene(config) != robot.scene:
            raise ValueError("the mock camera and the mock robot must share one scene")
        return cls(robot.scene, robot)

    @classmethod
    def check_robot(cls, robot_url: str) -> None:
        if urlsplit(robot_url).scheme.lower() != "mock":
            raise ValueError("a mock:// camera renders what the mock robot sees: set the robot "
                             "to mock:// too")

    def inject_fault(self, name: str, count: int = 1) -> None:
        """Make grabs fail (``count``: how many, for ``timeout`` and ``corrupt``).

        ``timeout``: no frame arrives (``CameraTimeoutError`` after the grab's timeout).
        ``corrupt``: the frame is torn, as after a truncated USB transfer: from a random row
        down it is black. ``disconnect``: the connection drops; grabs raise ``CameraError``
        (``camera_not_open``) until :meth:`open`. ``unplug``: the camera is pulled out: the
        next grab raises ``camera_disconnected`` and closes it, and :meth:`open` fails
        (``camera_not_found``) until :meth:`replug`. ``stall``: no grab gets a frame until
        :meth:`clear_faults`; the ``stall.limit``-th timeout in a row raises
        ``CameraStalledError`` and closes the camera. ``freeze``: every grab returns the last
        frame delivered again (a hung stream or driver) until :meth:`clear_faults`.
        """
        parse_fault(name, CAMERA_FAULTS)
        if count < 1:
            raise ValueError(f"count must be at least 1, got {count}")
        with self._lock:
            self._faults[name] = count

    def shift_mount(self, T_mount_cam: np.ndarray) -> None:
        """Move the camera on its mount (a bumped bracket): from now on the camera frame is at
        ``T_tcp_cam @ T_mount_cam`` (eye-in-hand; ``T_base_cam @ T_mount_cam`` eye-to-hand),
        shape (4, 4), while the scene's hand-eye stays what a calibration found."""
        with self._lock:
            self._T_mount_cam = np.asarray(T_mount_cam, dtype=float).copy()

    def replug(self) -> None:
        """Plug the camera back in after an ``unplug`` fault (it still needs :meth:`open`)."""
        with self._lock:
            self._faults.pop("unplug", None)

    def clear_faults(self) -> None:
        """Remove pending faults (an unplugged camera is plugged back in)."""
        with self._lock:
            self._faults.clear()

    @property
    def opened(self) -> bool:
        """True from :meth:`open` until :meth:`close`, a ``disconnect``, unplug or stall."""
        with self._lock:
            return self._opened and "disconnect" not in self._faults

    def open(self) -> None:
        """Open the camera, or open it again after a fault; ``camera_not_found`` if unplugged."""
        with self._lock:
            if "unplug" in self._faults:
                self._opened = False
                raise CameraError("No mock camera is plugged in: plug it back in, then open "
                                  "it.", code="camera_not_found")
            self._opened = True
            self._faults.pop("disconnect", None)
            self.stall.delivered()

    def close(self) -> None:
        """Close the camera. Safe to call twice."""
        with self._lock:
            self._opened = False

    def grab(self, *, timeout: float = 2.0) -> np.ndarray:
        """A frame rendered now, shape (H, W) uint8 grey."""
        fault = self._take_fault()
        if fault in ("timeout", "stall"):
            time.sleep(max(timeout, 0.0))
            error = self.stall.timed_out(CameraTimeoutError(
                f"The mock camera delivered no frame within {timeout:g} s."), "The mock camera")
            if isinstance(error, CameraStalledError):
                self.close()
            raise error
        self.stall.delivered()
        if not self.instant:
            period = 1.0 / self.fps  # the rest of the current frame, then one full frame
            time.sleep(min(2.0 * period - time.monotonic() % period, timeout))
        T_cam_target = camera_pose_for_tcp(self.scene, self.robot.true_pose)
        self.freshness = "mock: rendered at the grab from the robot's pose then"
        with self._lock:
            if fault == "freeze" and self._last is not None:
                return self._last.copy()
            T_cam_target = np.linalg.inv(self._T_mount_cam) @ T_cam_target
            image = render_board(self._params, T_cam_target, rng=self._rng)
            if fault == "corrupt":
                image[int(self._rng.integers(image.shape[0] // 4, image.shape[0])):] = 0
            self._last = image.copy()
        return image

    def _take_fault(self) -> str | None:
        """The fault this grab suffers (``timeout``, ``stall``, ``corrupt``, ``freeze``) or
        None; raises for a closed, disconnected or unplugged camera."""
        with self._lock:
            if "unplug" in self._faults and self._opened:
                self._opened = False
                raise CameraError("The mock camera was disconnected (unplugged).",
                                  code="camera_disconnected")
            if not self._opened or "disconnect" in self._faults:
                self._opened = False
                raise CameraError("The mock camera is not open (unplugged?). Open it first.",
                                  code="camera_not_open")
            fault = next((f for f in ("stall", "timeout", "corrupt", "freeze")
                          if f in self._faults), None)
            if fault in ("timeout", "corrupt"):
                self._faults[fault] -= 1
                if not self._faults[fault]:
                    del self._faults[fault]
        return fault

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the scene's camera."""
        w, h = self.scene.camera.image_size
        return int(w), int(h)

    def configure(self, *, resolution: tuple[int, int] | None = None,
                  exposure: float | None = None) -> None:
        """Accept the scene's resolution only; accept (and ignore) any positive exposure."""
        if resolution is not None and tuple(resolution) != self.resolution:
            w, h = self.resolution
            raise CameraError(f"The mock camera only delivers {w}x{h}, the scene's image size; "
                              f"{resolution[0]}x{resolution[1]} is not supported.",
                              code="camera_unsupported")
        if exposure is not None and (not np.isfinite(exposure) or exposure <= 0.0):
            raise ValueError(f"exposure must be a positive time in seconds, got {exposure}")
