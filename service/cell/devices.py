"""The cell's robot and camera as the service holds them: opened on first use, reopened after
a connection loss or any device fault of a run, closed at shutdown."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from drivers.base import Camera, Robot
from drivers.errors import CameraError, DeviceError
from drivers.registry import open_camera, open_robot
from service.settings import Settings

log = logging.getLogger("cellcal.service")

DeviceOpener = Callable[[], tuple[Robot, Camera]]


def settings_opener(settings: Settings) -> DeviceOpener:
    """Open the configured robot and camera, both given the configured device file
    (``scene``)."""

    def open_devices() -> tuple[Robot, Camera]:
        robot = open_robot(settings.robot, config=settings.scene)
        try:
            camera = open_camera(settings.camera, robot=robot, config=settings.scene)
        except BaseException:
            robot.close()
            raise
        return robot, camera

    return open_devices


class Devices:
    """The cell's robot and camera, opened on first use and reopened after a connection loss."""

    def __init__(self, opener: DeviceOpener) -> None:
        self._opener = opener
        self._lock = threading.Lock()
        self._devices: tuple[Robot, Camera] | None = None

    def get(self) -> tuple[Robot, Camera]:
        """The open devices; raises ``DeviceError`` (or ``ValueError``) if they cannot open.

        A camera that closed itself (unplugged, stalled: ``opened`` is False) is opened again
        here, so it comes back as soon as it is plugged in or delivers again. Until it is back
        it stays ``camera_disconnected``, the code its loss had: whether a capture finds the
        camera gone at its first grab or at this reopen (the loss seen by a thread that has
        let go of its run, a paused one finishing its station in progress) then says the same.
        """
        with self._lock:
            if self._devices is None:
                self._devices = self._opener()
            elif not self._devices[1].opened:
                _reopen(self._devices[1])
            return self._devices

    def current(self) -> tuple[Robot, Camera] | None:
        """The devices if they are open, without trying to open them."""
        with self._lock:
            return self._devices

    def reset(self) -> None:
        """Close the devices so that the next ``get`` connects again."""
        with self._lock:
            devices, self._devices = self._devices, None
        if devices is not None:
            for device in devices:
                try:
                    device.close()
                except DeviceError as exc:
                    log.warning("closing %s: %s", type(device).__name__, exc)

    close = reset


def _reopen(camera: Camera) -> None:
    """Open ``camera`` again after it closed itself; a device still missing is
    ``camera_disconnected`` (the camera was there and went away), not ``camera_not_found``."""
    try:
        camera.open()
    except CameraError as exc:
        if exc.code != "camera_not_found":
            raise
        raise CameraError(f"The camera was disconnected and is not back: {exc}",
                          code="camera_disconnected") from exc
