"""OpenCVCamera through cv2.VideoCapture on real files, and on a simulated V4L2 device queue."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.base import Camera
from drivers.errors import CameraError, CameraStalledError, CameraTimeoutError
from drivers.opencv_camera import OpenCVCamera
from drivers.stall import STALL_AFTER
from tests.support.helpers import wait_for

W, H = 160, 120
LEVELS = [0, 60, 120, 180, 240]


def _frame(level: int) -> np.ndarray:
    return np.full((H, W), level, np.uint8)


@pytest.fixture(autouse=True)
def _quiet_opencv() -> None:
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


@pytest.fixture
def video(tmp_path: Path) -> Path:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened()
    for level in LEVELS:
        writer.write(cv2.cvtColor(_frame(level), cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def _levels(camera: OpenCVCamera, n: int) -> list[int]:
    return [round(float(camera.grab(timeout=2.0).mean())) for _ in range(n)]


@pytest.mark.timeout(20)
def test_video_file_frames_in_order_then_end_of_stream(video: Path) -> None:
    with OpenCVCamera(f"file://{video}") as cam:
        assert isinstance(cam, Camera)
        assert cam.resolution == (W, H)
        assert cam.grab().shape == (H, W, 3)
        assert _levels(cam, 4) == pytest.approx(LEVELS[1:], abs=3)
        with pytest.raises(CameraError, match="end of the recording after 5 frames") as err:
            cam.grab()
        assert err.value.code == "end_of_stream"


@pytest.mark.timeout(20)
def test_printf_image_sequence(tmp_path: Path) -> None:
    for k, level in enumerate(LEVELS[:3]):
        assert cv2.imwrite(str(tmp_path / f"frame_{k:04d}.png"), _frame(level))
    with OpenCVCamera(f"file://{tmp_path}/frame_%04d.png") as cam:
        assert cam.resolution == (W, H)
        assert _levels(cam, 3) == LEVELS[:3]
        with pytest.raises(CameraError, match="end of the recording"):
            cam.grab()


@pytest.mark.timeout(20)
def test_image_directory_in_sorted_name_order(tmp_path: Path) -> None:
    for name, level in [("002.png", 120), ("000.png", 0), ("001.png", 60)]:
        assert cv2.imwrite(str(tmp_path / name), _frame(level))
    (tmp_path / "notes.txt").write_text("not an image")
    with OpenCVCamera(f"file://{tmp_path}") as cam:
        assert cam.resolution == (W, H)
        assert _levels(cam, 3) == [0, 60, 120]
        with pytest.raises(CameraError, match="end of the recording after 3 frames"):
            cam.grab()


@pytest.mark.timeout(20)
def test_recording_configuration(video: Path) -> None:
    with OpenCVCamera(f"file://{video}") as cam:
        cam.configure(resolution=(W, H))  # its own resolution is fine
        with pytest.raises(CameraError, match="does not support 640x480") as err:
            cam.configure(resolution=(640, 480))
        assert err.value.code == "camera_unsupported"
        with pytest.raises(CameraError, match="exposure cannot be set"):
            cam.configure(exposure=0.01)
        with pytest.raises(ValueError, match="positive time"):
            cam.configure(exposure=-1.0)


@pytest.mark.timeout(20)
@pytest.mark.parametrize(("url", "message"), [
    ("v4l2:///dev/video987", "No camera at /dev/video987"),
    ("file:///no/such/clip.avi", "no such file or directory"),
    ("file:///no/such/dir/frame_%04d.png", "no directory /no/such/dir"),
])
def test_missing_device_or_file(url: str, message: str) -> None:
    with pytest.raises(CameraError, match=message) as err:
        OpenCVCamera(url).open()
    assert err.value.code == "camera_not_found"


@pytest.mark.timeout(20)
def test_unreadable_sources(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(CameraError, match="holds no images"):
        OpenCVCamera(f"file://{tmp_path}/empty").open()
    (tmp_path / "clip.avi").write_text("this is not a video")
    with pytest.raises(CameraError, match="not a video file OpenCV can decode"):
        OpenCVCamera(f"file://{tmp_path}/clip.avi").open()
    with pytest.raises(CameraError, match="no image matches the pattern"):
        OpenCVCamera(f"file://{tmp_path}/empty/f_%03d.png").open()


@pytest.mark.parametrize("url", ["v4l2://dev/video0", "file://clip.avi", "ftp://cam/0",
                                 "file:///a.avi?loop=1"])
def test_malformed_urls(url: str) -> None:
    with pytest.raises(ValueError):
        OpenCVCamera(url)


def test_grab_before_open_and_close_twice(video: Path) -> None:
    cam = OpenCVCamera(f"file://{video}")
    with pytest.raises(CameraError, match="not open"):
        cam.grab()
    cam.open()
    cam.close()
    cam.close()
    with pytest.raises(CameraError, match="not open"):
        cam.grab()


@pytest.mark.timeout(20)
@pytest.mark.parametrize("name", ["frame_%04d.png", ""])
def test_recording_unplugged_then_replugged(tmp_path: Path, name: str) -> None:
    """A recording on a removable disk: its directory vanishes mid-stream, then comes back."""
    disk, away = tmp_path / "disk", tmp_path / "away"
    disk.mkdir()
    for k, level in enumerate(LEVELS):
        assert cv2.imwrite(str(disk / f"frame_{k:04d}.png"), _frame(level))
    cam = OpenCVCamera(f"file://{disk}/{name}".rstrip("/"))
    cam.open()
    assert cam.opened
    assert _levels(cam, 2) == LEVELS[:2]
    disk.rename(away)  # unplugged
    with pytest.raises(CameraError, match="was disconnected") as err:
        cam.grab()
    assert err.value.code == "camera_disconnected"
    assert not cam.opened
    with pytest.raises(CameraError, match="not open") as err:
        cam.grab()
    assert err.value.code == "camera_not_open"
    with pytest.raises(CameraError) as err:
        cam.open()  # still unplugged
    assert err.value.code == "camera_not_found" and not cam.opened
    away.rename(disk)  # plugged back in
    cam.open()
    assert cam.opened
    assert _levels(cam, 3) == LEVELS[:3]  # the recording starts again
    cam.close()
    assert not cam.opened


# ---- live devices: a stand-in for cv2.VideoCapture with a V4L2-like buffer queue -------------


class FakeV4L2:
    """Frames arrive every ``period`` s into a queue of ``buffers``; when it is full, new
    frames are dropped (the driver has no free buffer), so queued frames grow old, as on V4L2.
    ``retrieve`` returns a frame whose value is its arrival index (no wrap-around: uint32).

    ``streaming = False`` stops delivery (grab fails at once, as V4L2 does without a frame);
    ``stuck.clear()`` makes grab block inside the backend until ``stuck.set()``.
    """

    def __init__(self, period: float = 0.01, buffers: int = 4) -> None:
        self.period, self.buffers = period, buffers
        self.t0 = time.monotonic()
        self.seen = 0  # arrivals already considered
        self.queue: list[int] = []
        self.queued_at: dict[int, float] = {}  # arrival index -> when the sensor queued it
        self.current: int | None = None
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
                      cv2.CAP_PROP_BUFFERSIZE: float(buffers), cv2.CAP_PROP_EXPOSURE: 100.0}
        self.streaming = True
        self.stuck = threading.Event()
        self.stuck.set()
        self.blocked = threading.Event()  # a grab is waiting on ``stuck``
        self.supported_exposure = True
        self.releases = 0
        self.let_go = threading.Event()  # cleared: a device that does not let go until set
        self.let_go.set()

    def arrival(self, k: int) -> float:
        return self.t0 + (k + 1) * self.period

    def _sensor(self) -> None:
        while self.arrival(self.seen) <= time.monotonic():
            if len(self.queue) < self.buffers:
                self.queue.append(self.seen)
            self.seen += 1

    def isOpened(self) -> bool:  # noqa: N802
        return True

    def grab(self) -> bool:
        if not self.stuck.is_set():
            self.blocked.set()
            self.stuck.wait()
            self.blocked.clear()
        if not self.streaming:
            return False
        self._sensor()
        if not self.queue:
            time.sleep(max(self.arrival(self.seen) - time.monotonic(), 0.0))
            self._sensor()
        self.current = self.queue.pop(0)
        return True

    def retrieve(self) -> tuple[bool, np.ndarray]:
        return True, np.full((4, 4), self.current, np.uint32)

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def set(self, prop: int, value: float) -> bool:
        if prop == cv2.CAP_PROP_EXPOSURE and not self.supported_exposure:
            return False
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT) and value > 1000:
            return False  # like a camera that keeps its mode for sizes it lacks
        self.props[prop] = float(value)
        return True

    def release(self) -> None:
        self.let_go.wait()
        self.releases += 1


@pytest.fixture
def live(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[FakeV4L2, Path]]:
    """A fake V4L2 device node; each open gets a new FakeV4L2 (the last one is ``fakes[-1]``)."""
    device = tmp_path / "video0"
    device.write_text("")
    fakes = [FakeV4L2()]

    def capture(source: object, api: int) -> FakeV4L2:
        assert source == str(device) and api == cv2.CAP_V4L2
        if fakes[-1].releases:
            fakes.append(FakeV4L2())
        return fakes[-1]

    monkeypatch.setattr(cv2, "VideoCapture", capture)
    yield fakes[0], device
    for fake in fakes:
        fake.stuck.set()  # let a capture thread left blocked in the backend finish
        fake.let_go.set()


@pytest.mark.timeout(20)
def test_live_grab_drops_stale_buffered_frames(live: tuple[FakeV4L2, Path]) -> None:
    fake, device = live
    with OpenCVCamera(f"v4l2://{device}") as cam:
        for _ in range(3):
            time.sleep(0.1)  # the robot moves: the queue fills with frames from the motion
            fake._sensor()
            stale = list(fake.queue)
            assert len(stale) == fake.buffers
            called = time.monotonic()
            index = int(cam.grab(timeout=5.0)[0, 0])
            # Not a queued frame, and not one whose exposure (the period before its arrival)
            # began before the call: however late the capture thread ran, and however many
            # frames arrived meanwhile.
            assert index not in stale
            assert fake.arrival(index) - fake.period > called


@pytest.mark.timeout(20)
def test_live_camera_unplugged_then_replugged(live: tuple[FakeV4L2, Path]) -> None:
    fake, device = live
    with OpenCVCamera(f"v4l2://{device}", open_timeout=2.0) as cam:
        fake.streaming = False
        with pytest.raises(CameraTimeoutError, match=r"delivered no frame within 0\.2 s"):
            cam.grab(timeout=0.2)
        assert cam.opened  # one timeout is not a loss
        fake.let_go.clear()  # the lost device is let go late: reopen must wait for it
        device.unlink()  # unplugged
        with pytest.raises(CameraError, match="was disconnected") as err:
            cam.grab(timeout=5.0)
        assert err.value.code == "camera_disconnected"
        assert not cam.opened
        with pytest.raises(CameraError, match=r"not open \(closed after: The camera"):
            cam.grab()
        with pytest.raises(CameraError, match="No camera at") as err:
            cam.open()
        assert err.value.code == "camera_not_found"
        device.write_text("")  # plugged back in
        with pytest.raises(CameraTimeoutError, match="not let go within 2 s"):
            cam.open()  # the old handle still holds the device
        assert not cam.opened and fake.releases == 0
        fake.let_go.set()
        cam.open()
        assert cam.opened and fake.releases == 1
        assert cam.grab(timeout=5.0).shape == (4, 4)


@pytest.mark.timeout(30)
def test_consecutive_timeouts_are_one_stall_then_reopen(live: tuple[FakeV4L2, Path]) -> None:
    fake, device = live
    cam = OpenCVCamera(f"v4l2://{device}", open_timeout=5.0)
    cam.open()
    fake.streaming = False
    for _ in range(2):  # a frame in between ends the streak
        for _ in range(STALL_AFTER - 1):
            with pytest.raises(CameraTimeoutError):
                cam.grab(timeout=0.05)
        fake.streaming = True
        cam.grab(timeout=5.0)
        fake.streaming = False
    for _ in range(STALL_AFTER - 1):
        with pytest.raises(CameraTimeoutError):
            cam.grab(timeout=0.05)
    with pytest.raises(CameraStalledError, match=f"no frame in {STALL_AFTER} grabs in a row") \
            as err:
        cam.grab(timeout=0.05)
    assert err.value.code == "camera_stalled"
    assert not isinstance(err.value, CameraTimeoutError)  # retrying the grab does not help
    assert not cam.opened
    wait_for("the release on the capture thread", lambda: fake.releases == 1, 10)
    with pytest.raises(CameraError, match="not open") as err:
        cam.grab(timeout=0.05)
    assert err.value.code == "camera_not_open"
    cam.open()  # the device streams again after a reopen
    assert cam.opened
    assert cam.grab(timeout=5.0).shape == (4, 4)
    cam.close()


@pytest.mark.timeout(20)
def test_live_grab_stuck_in_the_driver_times_out(live: tuple[FakeV4L2, Path]) -> None:
    fake, device = live
    cam = OpenCVCamera(f"v4l2://{device}", open_timeout=1.0)
    cam.open()
    fake.stuck.clear()  # grab() blocks inside the backend until the test lets it go
    with pytest.raises(CameraTimeoutError, match=r"delivered no frame within 0\.2 s"):
        cam.grab(timeout=0.2)
    # the caller got its error while the backend blocks (or is about to, on a busy machine)
    wait_for("the capture thread to block", fake.blocked.is_set, 10)
    cam.close()  # bounded even though the capture thread is stuck
    assert fake.blocked.is_set() and not cam.opened and fake.releases == 0
    fake.stuck.set()
    wait_for("the queued release, once the thread is free", lambda: fake.releases == 1, 10)


@pytest.mark.timeout(20)
def test_live_configuration_is_verified(live: tuple[FakeV4L2, Path]) -> None:
    fake, device = live
    with OpenCVCamera(f"v4l2://{device}") as cam:
        assert cam.resolution == (640, 480)
        cam.configure(resolution=(800, 600), exposure=0.005)
        assert cam.resolution == (800, 600)
        assert fake.props[cv2.CAP_PROP_EXPOSURE] == pytest.approx(50.0)  # units of 100 µs
        assert fake.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1  # manual
        with pytest.raises(CameraError, match="does not support 1920x1080; it delivers 800x600"):
            cam.configure(resolution=(1920, 1080))
        fake.supported_exposure = False
        with pytest.raises(CameraError, match="manual exposure of 20 ms"):
            cam.configure(exposure=0.02)
