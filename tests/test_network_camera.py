"""Network cameras (http/https/rtsp through FFmpeg): a real MJPEG stream from a local server,
and fresh frames from a stream that lags behind a robot that is still moving in its old frames."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from drivers import registry
from drivers.capture import capture_station
from drivers.errors import CameraError, CameraStalledError, CameraTimeoutError
from drivers.opencv_camera import OpenCVCamera
from drivers.stall import STALL_AFTER
from tests.mjpeg_server import MJPEGCamera

W, H = 160, 120


def _scene() -> np.ndarray:
    """A still scene with structure (a gradient and a square), grey."""
    image = np.tile(np.linspace(30, 220, W, dtype=np.uint8), (H, 1))
    image[40:80, 60:100] = 0
    return image


@pytest.fixture
def mjpeg() -> Iterator[MJPEGCamera]:
    server = MJPEGCamera(_scene)
    yield server
    server.stop()


def test_ffmpeg_in_the_installed_opencv() -> None:
    info = cv2.getBuildInformation()
    assert "FFMPEG:" in info and info.split("FFMPEG:")[1].split()[0] == "YES"


@pytest.mark.parametrize("url", ["http://cam/video.mjpg", "https://user:pw@cam:8443/v?x=1",
                                 "rtsp://10.0.0.9:554/stream1"])
def test_network_urls_are_cameras(url: str) -> None:
    registry.check_camera_url(url)
    assert registry.camera_class(url) is OpenCVCamera
    assert OpenCVCamera(url).live


def test_password_stays_out_of_messages() -> None:
    cam = OpenCVCamera("rtsp://admin:secret@127.0.0.1:9/none")
    assert "secret" not in cam.url and "admin:***@" in cam.url
    with pytest.raises(ValueError, match="names its host"):
        OpenCVCamera("http:///video.mjpg")


@pytest.mark.timeout(60)
def test_mjpeg_stream_grab_loss_and_reconnect(mjpeg: MJPEGCamera) -> None:
    cam = OpenCVCamera(mjpeg.url, open_timeout=3.0)
    cam.open()
    assert cam.resolution == (W, H)
    frame = cam.grab(timeout=5.0)
    assert frame.shape[:2] == (H, W)
    assert np.abs(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY).astype(int) - _scene()).mean() < 3
    assert cam.freshness is not None and cam.freshness.startswith("stream:")
    with pytest.raises(CameraError, match="exposure in the camera's own settings"):
        cam.configure(exposure=0.01)
    # between grabs the capture thread drains the stream; a call on it gets the thread back
    with pytest.raises(CameraError) as unsupported:
        cam.configure(resolution=(2 * W, 2 * H))
    assert unsupported.value.code == "camera_unsupported"

    mjpeg.stop()  # the camera goes away: frames still buffered may come first
    with pytest.raises(CameraError, match="was disconnected") as err:
        for _ in range(50):
            cam.grab(timeout=5.0)
    assert err.value.code == "camera_disconnected"  # the code a V4L2 camera's loss has
    assert not cam.opened
    with pytest.raises(CameraError, match="not open") as err:
        cam.grab()
    assert err.value.code == "camera_not_open"
    with pytest.raises(CameraError, match="No camera stream at") as err:
        cam.open()  # still away
    assert err.value.code == "camera_open_failed" and not cam.opened

    mjpeg.start()  # back on the same address: opening again reconnects
    cam.open()
    assert cam.grab(timeout=5.0).shape[:2] == (H, W)
    cam.close()
    assert not cam.opened


@pytest.mark.timeout(60)
def test_silent_stream_times_out_then_stalls(mjpeg: MJPEGCamera) -> None:
    cam = OpenCVCamera(mjpeg.url, open_timeout=2.0)
    cam.open()
    cam.grab(timeout=5.0)
    silent = threading.Event()
    mjpeg.frame = lambda: (silent.wait(), _scene())[1]  # connected, but no more frames
    silent_since = time.monotonic()
    for _ in range(STALL_AFTER - 1):
        with pytest.raises(CameraTimeoutError):
            for _ in range(50):  # frames sent before the silence may still be buffered
                cam.grab(timeout=0.3)
    assert cam.opened
    with pytest.raises(CameraStalledError) as err:
        cam.grab(timeout=0.3)
    assert err.value.code == "camera_stalled" and not cam.opened
    silent.set()
    assert time.monotonic() > silent_since
    cam.open()  # the stream is back
    assert cam.grab(timeout=5.0).shape[:2] == (H, W)
    cam.close()


# ---- fresh frames: a stream that lags behind a robot that is still moving -------------------

PERIOD = 0.02  # s between frames
LAG = 6  # frames between exposure and arrival (encoder and network)
BUFFER = 10  # frames the socket holds while nobody reads
MOVE_S = 0.4  # the robot's motion
LEVELS = (40, 200)  # what the image shows at the even and the odd stations


class MovingRobot:
    """A robot whose motion takes ``MOVE_S``, between stations whose images differ: the
    image shows how far it got (``level``)."""

    def __init__(self) -> None:
        self.moved_at = -1e9
        self.moves = 0
        self.pose = np.array([0.3, 0.0, 0.4, 0.0, 3.1, 0.0])

    @property
    def settled_level(self) -> int:
        return LEVELS[self.moves % 2]

    def level(self, t: float) -> int:
        progress = min(max((t - self.moved_at) / MOVE_S, 0.0), 1.0)
        start = LEVELS[(self.moves + 1) % 2]
        return round(start + (self.settled_level - start) * progress)

    def move_linear(self, pose: np.ndarray, **_: float) -> None:
        self.moved_at = time.monotonic()
        self.moves += 1
        self.pose = np.asarray(pose, dtype=float)

    def wait_settled(self, *, timeout: float = 5.0) -> None:
        time.sleep(max(self.moved_at + MOVE_S - time.monotonic(), 0.0))

    def tcp_pose(self) -> np.ndarray:
        return self.pose.copy()


class LaggingStream:
    """A ``cv2.VideoCapture`` stand-in for a network stream: frame k is exposed at
    ``t0 + k PERIOD`` (showing the robot then) and arrives ``LAG`` frames later. While nobody
    reads, arrived frames fill a socket buffer of ``BUFFER`` frames and the server then drops
    the rest, so after a pause the client first gets the oldest ones, instantly."""

    def __init__(self, robot: MovingRobot) -> None:
        self.robot = robot
        self.t0 = time.monotonic()
        self.exposed: list[int] = []  # level of every frame exposed so far
        self.delivered = 0  # frames handed out (the next one to hand out)
        self.queued_until = 0  # frames before this index entered the socket
        self.refused_until = 0  # frames before this index that did not fit were dropped
        self.current: int | None = None

    def _expose(self) -> None:
        while self.t0 + len(self.exposed) * PERIOD <= time.monotonic():
            self.exposed.append(self.robot.level(self.t0 + len(self.exposed) * PERIOD))

    def _arrival(self, k: int) -> float:
        return self.t0 + (k + LAG) * PERIOD

    def isOpened(self) -> bool:  # noqa: N802 - the cv2 name
        return True

    def grab(self) -> bool:
        now = time.monotonic()
        arrived = max(int((now - self.t0) / PERIOD) - LAG + 1, 0)  # frames arrived by now
        if self.delivered >= self.queued_until:  # the socket was empty at the last read
            self.delivered = max(self.delivered, self.refused_until)
            self.queued_until = min(arrived, self.delivered + BUFFER)
            self.refused_until = arrived  # arrived while the socket was full: dropped
        if self.delivered < self.queued_until:  # buffered: handed out at once
            k = self.delivered
        else:  # the next frame to arrive (those the full socket refused are gone)
            k = max(arrived, self.delivered)
            time.sleep(max(self._arrival(k) - now, 0.0))
            self.queued_until = k + 1
        self._expose()
        self.current, self.delivered = self.exposed[k], k + 1
        return True

    def retrieve(self) -> tuple[bool, np.ndarray]:
        return True, np.full((H, W, 3), self.current, np.uint8)

    def get(self, prop: int) -> float:
        return {cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H}.get(prop, 0.0)

    def set(self, prop: int, value: float) -> bool:
        return False

    def release(self) -> None:
        pass


@pytest.fixture
def lagging(monkeypatch: pytest.MonkeyPatch) -> tuple[MovingRobot, LaggingStream]:
    robot = MovingRobot()
    stream = LaggingStream(robot)
    monkeypatch.setattr(cv2, "VideoCapture", lambda *args: stream)
    return robot, stream


STEP = np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.0])  # between stations (m, rad)


def _move(robot: MovingRobot) -> None:
    robot.move_linear(robot.pose + STEP)
    robot.wait_settled()


@pytest.mark.timeout(60)
def test_lagging_stream_gives_the_settled_pose(lagging: tuple[MovingRobot,
                                                               LaggingStream]) -> None:
    robot, _ = lagging
    with OpenCVCamera("http://192.0.2.1/video.mjpg") as cam:
        for _ in range(3):
            time.sleep(0.3)  # the robot stands still between stations, nobody reads
            captured = capture_station(robot, cam, robot.pose + STEP)
            # the settled pose: not the move, nor the previous station still buffered
            assert int(captured.image[0, 0, 0]) == robot.settled_level
            station = captured.station("000")
            assert station.freshness == cam.freshness
            assert station.freshness is not None and "frames skipped" in station.freshness


@pytest.mark.timeout(60)
def test_lagging_stream_shows_the_move_to_a_naive_grab(lagging: tuple[MovingRobot,
                                                                      LaggingStream]) -> None:
    """The stand-in is stale: right after settling, the next frames show the previous station,
    then the robot moving."""
    robot, stream = lagging
    time.sleep(0.3)
    _move(robot)
    levels = []
    for _ in range(BUFFER + LAG):
        stream.grab()
        levels.append(int(stream.retrieve()[1][0, 0, 0]))
    assert levels[0] == LEVELS[(robot.moves + 1) % 2]  # the previous station
    assert any(min(LEVELS) < level < max(LEVELS) for level in levels)  # the move
