"""Open a robot or a camera from its URL: the only way service code and the CLI get devices.

The tables below map a URL scheme to the class that serves it, as an import string, and to the
address form shown in help and error messages. A class is imported only when its scheme is
used, so a mock run never loads ur-rtde, and nothing here imports a backend (or the mocks).

Each class parses its own address: robot classes offer ``from_url(url, *, config)``, camera classes
``from_url(url, *, config, robot)`` (``drivers.base.RobotSession`` / ``CameraSession``).
``config`` is an optional device configuration handed through unread (the mock cell's scene
file, for instance); ``robot`` is the opened robot, for a camera that needs it.

Adding a backend: its module, and one line in ``ROBOTS`` or ``CAMERAS``.
"""

from __future__ import annotations

import importlib
from typing import Any
from urllib.parse import urlsplit

from drivers.base import Camera, CellHints, DescribesCell, Robot

#: scheme -> (import string ``module:Class``, address form for people)
ROBOTS: dict[str, tuple[str, str]] = {
    "ur": ("drivers.ur:URRobot", "ur://HOST"),
    "mock": ("mocks.devices:MockRobot", "mock://"),
}
CAMERAS: dict[str, tuple[str, str]] = {
    "v4l2": ("drivers.opencv_camera:OpenCVCamera", "v4l2:///dev/videoN"),
    "http": ("drivers.opencv_camera:OpenCVCamera", "http://HOST/PATH"),
    "https": ("drivers.opencv_camera:OpenCVCamera", "https://HOST/PATH"),
    "rtsp": ("drivers.opencv_camera:OpenCVCamera", "rtsp://HOST/PATH"),
    "file": ("drivers.opencv_camera:OpenCVCamera", "file:///path"),
    "mock": ("mocks.camera:MockCamera", "mock://"),
}


def _forms(table: dict[str, tuple[str, str]]) -> str:
    forms = [form for _, form in table.values()]
    return ", ".join(forms[:-1]) + " or " + forms[-1]


ROBOT_URLS = _forms(ROBOTS)
CAMERA_URLS = _forms(CAMERAS)


def resolve(target: str) -> Any:
    """The object named by an import string ``package.module:attribute``."""
    module, _, attribute = target.partition(":")
    return getattr(importlib.import_module(module), attribute)


def _entry(table: dict[str, tuple[str, str]], url: str, kind: str, forms: str) -> str:
    scheme = urlsplit(url).scheme.lower()
    if scheme not in table:
        raise ValueError(f"unknown {kind} address {url!r}; use {forms}")
    return table[scheme][0]


def check_robot_url(url: str) -> None:
    """``ValueError`` for a robot URL whose scheme no backend serves (imports nothing)."""
    _entry(ROBOTS, url, "robot", ROBOT_URLS)


def check_camera_url(url: str) -> None:
    """``ValueError`` for a camera URL whose scheme no backend serves (imports nothing)."""
    _entry(CAMERAS, url, "camera", CAMERA_URLS)


def robot_class(url: str) -> Any:
    """The class serving robot ``url`` (imported now)."""
    return resolve(_entry(ROBOTS, url, "robot", ROBOT_URLS))


def camera_class(url: str) -> Any:
    """The class serving camera ``url`` (imported now)."""
    return resolve(_entry(CAMERAS, url, "camera", CAMERA_URLS))


def describe_cell(robot_url: str, config: Any = None) -> CellHints:
    """What the robot's backend knows about its cell before connecting (``DescribesCell``);
    empty hints for a backend that knows nothing. ``ValueError`` for an unusable config."""
    cls = robot_class(robot_url)
    return cls.describe_cell(config) if issubclass(cls, DescribesCell) else CellHints()


def check_pair(robot_url: str, camera_url: str) -> None:
    """``ValueError`` if the camera cannot work with that robot (a simulated camera)."""
    camera_class(camera_url).check_robot(robot_url)


def companion_robot(camera_url: str) -> str | None:
    """The robot address a camera needs opened with it, or None."""
    return camera_class(camera_url).companion_robot


def open_robot(url: str, *, config: Any = None) -> Robot:
    """Connect to the robot at ``url``; ``config`` goes to its backend (the mock's scene).

    Raises ``ValueError`` for a malformed URL and ``RobotError`` subclasses if connecting fails.
    """
    robot: Robot = robot_class(url).from_url(url, config=config)
    robot.connect()
    return robot


def open_camera(url: str, *, robot: Robot | None = None, config: Any = None) -> Camera:
    """Open the camera at ``url``; ``robot`` is the opened robot for a camera that needs one.

    Raises ``ValueError`` for a malformed URL and ``CameraError`` if opening fails.
    """
    camera: Camera = camera_class(url).from_url(url, config=config, robot=robot)
    camera.open()
    return camera
