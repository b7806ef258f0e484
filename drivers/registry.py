"""Open a robot or a camera from its URL: the only way service code and the CLI get devices.

=========================  ======================================================
``ur://HOST``              a Universal Robots arm through ur-rtde (``drivers.ur``)
``mock://`` (robot)        ``mocks.devices.MockRobot`` over a mock scene
``v4l2:///dev/videoN``     a V4L2 camera (``drivers.opencv_camera``)
``file:///path``           a video file, image pattern or image directory
``mock://`` (camera)       ``mocks.devices.MockCamera`` riding on the mock robot
=========================  ======================================================

Both functions return the device connected / opened; the caller closes it. Concrete drivers
are imported only when their scheme is used, so a mock run never loads ur-rtde.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from drivers.base import Camera, Robot
from mocks.scene import MockScene, default_scene

ROBOT_URLS = "ur://HOST or mock://"
CAMERA_URLS = "v4l2:///dev/videoN, file:///path or mock://"


def open_robot(url: str, *, scene: MockScene | None = None) -> Robot:
    """Connect to the robot at ``url``; ``scene`` (default: the default scene) for ``mock://``.

    Raises ``ValueError`` for a malformed URL and ``RobotError`` subclasses if connecting fails.
    """
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    robot: Robot
    if scheme == "ur":
        if not parts.hostname or parts.port is not None or parts.path.strip("/") \
                or parts.query or parts.username:
            raise ValueError(f"{url!r}: a UR address is ur://HOST (an IP address or host name; "
                             "the controller's ports are fixed)")
        from drivers.ur import URRobot

        robot = URRobot(parts.hostname)
    elif scheme == "mock":
        _check_mock(url, "robot")
        from mocks.devices import MockRobot

        robot = MockRobot(scene if scene is not None else default_scene())
    else:
        raise ValueError(f"unknown robot address {url!r}; use {ROBOT_URLS}")
    robot.connect()
    return robot


def open_camera(url: str, *, robot: Robot | None = None,
                scene: MockScene | None = None) -> Camera:
    """Open the camera at ``url``. A ``mock://`` camera needs the ``MockRobot`` it sees from.

    ``scene`` defaults to the mock robot's scene and, if given, must be the same scene.
    Raises ``ValueError`` for a malformed URL and ``CameraError`` if opening fails.
    """
    scheme = urlsplit(url).scheme.lower()
    camera: Camera
    if scheme in ("v4l2", "file"):
        from drivers.opencv_camera import OpenCVCamera

        camera = OpenCVCamera(url)
    elif scheme == "mock":
        _check_mock(url, "camera")
        from mocks.devices import MockCamera, MockRobot

        if not isinstance(robot, MockRobot):
            raise ValueError("a mock:// camera renders what the mock robot sees: open the "
                             "robot as mock:// too and pass it to open_camera")
        if scene is not None and scene != robot.scene:
            raise ValueError("the mock camera and the mock robot must share one scene")
        camera = MockCamera(robot.scene, robot)
    else:
        raise ValueError(f"unknown camera address {url!r}; use {CAMERA_URLS}")
    camera.open()
    return camera


def _check_mock(url: str, device: str) -> None:
    if url.lower() != "mock://":
        raise ValueError(f"{url!r}: a mock {device} is addressed as just mock:// "
                         "(choose its cell with a scene file)")
