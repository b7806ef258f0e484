"""Cameras and recordings through ``cv2.VideoCapture``: ``v4l2://``, network and ``file://`` URLs.

``OpenCVCamera`` implements ``drivers.base.Camera``. Sources, by URL:

- ``v4l2:///dev/videoN`` (or any V4L2 device path, e.g. ``/dev/v4l/by-id/...``): a live camera
  through OpenCV's V4L2 backend.
- ``http://``, ``https://`` or ``rtsp://`` URLs: a network camera's stream (MJPEG over HTTP,
  RTSP) through OpenCV's FFmpeg backend, the URL handed over as it is (query and credentials
  included; error messages leave the password out).
- ``file:///path/video.avi``: a video file, one frame per grab.
- ``file:///path/frame_%04d.png``: an image sequence named by a printf pattern (OpenCV's
  ``CAP_IMAGES``; numbering starts at 0 or 1), one image per grab.
- ``file:///path/dir``: every image in a directory (``.png .jpg .jpeg .bmp .tif .tiff .pgm``)
  in sorted file-name order, one per grab. Use zero-padded names so sorting keeps the order.

A recording replays what was captured, so a grab returns its *next* frame; at the end it raises
``CameraError`` (code ``end_of_stream``) rather than looping, so a capture can never pair a
robot pose with an old frame.

Fresh frames from a live camera. V4L2 keeps up to ``CAP_PROP_BUFFERSIZE`` (B, usually 4) frames
queued; after the robot has been standing still for a while they are all old (exposed during
the move). At the time of a grab at most B frames are ready, so after discarding B frames the
next one arrived after the call. Its exposure may still have begun just before the call, so it
is discarded too, and frame B + 2 is returned. This needs no timing heuristics; its cost is
about one frame period when the queue was full (the usual case after a move) and up to B + 2
periods when it was empty. A network stream's buffer has no known length and its frames arrive
late, so its frames are grabbed until two consecutive ones that had to be waited for agree
(``drivers.freshness``). Between grabs the capture thread keeps reading a stream and drops what
it reads, so that frames sent while the robot moved do not pile up in the socket: otherwise a
backlog of large frames, each read a little slowly on a busy machine, passes for frames waited
for, and old frames of a robot at rest at the previous station agree with each other.
``freshness`` says, after each grab, how the frame was made fresh; the capture stores it with
the station.

Timeouts. A ``grab`` on a device that stopped streaming can block inside OpenCV for many
seconds, so every ``cv2.VideoCapture`` call runs on one worker thread (OpenCV releases the GIL)
and the caller waits at most its timeout. A call stuck on the worker delays the next ones, which
then time out too, until the device answers again or the camera is closed and reopened.

Losing the device. The camera closes itself when its device is unplugged (``camera_disconnected``:
the V4L2 device node, or the directory of a recording, is gone) or stalls (``drivers.stall``:
``camera_stalled`` for the ``stall_after``-th grab timeout in a row); a network stream is lost
(``camera_disconnected``) when its stream ends: the server closed it or went away. FFmpeg's own
open and read timeouts are set to ``open_timeout`` so that a silent server frees the capture
thread too. ``opened`` is then False,
grabs raise ``camera_not_open``, and ``open()`` opens the device again once it is back (a
recording then restarts from its first frame).
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import urlsplit

import cv2
import numpy as np

from drivers.base import CameraSession, Robot
from drivers.errors import CameraError, CameraTimeoutError
from drivers.freshness import still_frame
from drivers.stall import STALL_AFTER, StallCounter

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")
#: V4L2 buffer queue length assumed when the backend does not report one.
DEFAULT_V4L2_BUFFERS = 4
#: OpenCV's V4L2 backend passes exposure in the driver's unit: 100 µs.
_V4L2_EXPOSURE_UNIT_S = 1e-4
_V4L2_EXPOSURE_MANUAL = 1
#: URL schemes of network cameras, opened through FFmpeg.
STREAM_SCHEMES = ("http", "https", "rtsp")
#: ``freshness`` of a recording's frame: a replay, nothing to wait for.
RECORDING_FRESHNESS = "recording: its next frame, as recorded"

_T = TypeVar("_T")


class _ImageDirectory:
    """The part of the ``cv2.VideoCapture`` interface this module uses, over a directory."""

    def __init__(self, directory: Path) -> None:
        self._files = sorted(p for p in directory.iterdir()
                             if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        self._next = 0
        self._frame: np.ndarray | None = None

    def isOpened(self) -> bool:  # noqa: N802 - the cv2.VideoCapture name
        return bool(self._files)

    def grab(self) -> bool:
        if self._next >= len(self._files):
            return False
        path = self._files[self._next]
        if not path.is_file():  # removed with its directory (unplugged) or on its own
            return False
        self._next += 1
        self._frame = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if self._frame is None:
            raise CameraError(f"{path}: not a readable image.", code="corrupt_frame")
        return True

    def retrieve(self) -> tuple[bool, np.ndarray | None]:
        return self._frame is not None, self._frame

    def get(self, prop: int) -> float:
        if self._files and prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            shape = self._frame.shape if self._frame is not None else cv2.imread(
                str(self._files[0]), cv2.IMREAD_UNCHANGED).shape
            return float(shape[1] if prop == cv2.CAP_PROP_FRAME_WIDTH else shape[0])
        return 0.0

    def set(self, prop: int, value: float) -> bool:
        return False

    def release(self) -> None:
        self._files = []


class OpenCVCamera(CameraSession):
    """A ``v4l2://`` or network camera, or a ``file://`` recording; see the module docstring.

    ``open_timeout`` bounds ``open()``, ``configure()`` and ``close()`` (seconds);
    ``stall_after`` consecutive grab timeouts close the camera as stalled. Use as a context
    manager, or call ``open()`` and ``close()``.
    """

    def __init__(self, url: str, *, open_timeout: float = 5.0,
                 stall_after: int = STALL_AFTER) -> None:
        self._kind, self._path = _parse_url(url)
        self.url = _without_password(url) if self._kind == "stream" else url
        self.open_timeout = open_timeout
        #: How the last grabbed frame was made fresh (stored with a captured station).
        self.freshness: str | None = None
        self._cap: Any = None
        self._worker: ThreadPoolExecutor | None = None
        self._size = (0, 0)
        self._frames_read = 0
        self._stall = StallCounter(stall_after)
        self._lost: CameraError | None = None  # why the device was closed behind our back
        self._releasing: Future | None = None  # a release queued by a loss, not yet awaited
        self._draining = threading.Event()  # a stream is read and dropped until the next grab

    @property
    def live(self) -> bool:
        """True for a V4L2 device or a network stream, False for a recording."""
        return self._kind in ("v4l2", "stream")

    @property
    def opened(self) -> bool:
        """True from ``open()`` until ``close()`` or the loss of the device."""
        return self._cap is not None

    @classmethod
    def from_url(cls, url: str, *, config: Any = None,
                 robot: Robot | None = None) -> OpenCVCamera:
        """The camera or recording at ``url`` (``config`` and ``robot`` are unused)."""
        return cls(url)

    def open(self) -> None:
        """Open (again) the device or recording; ``CameraError`` saying what is wrong.

        Works after a loss (``camera_disconnected``, ``camera_stalled``) once the device is
        back and its old handle has let go of it (``CameraTimeoutError`` until then); a camera
        that is open is closed and opened anew.
        """
        release = self._release()
        path = Path(self._path)
        if self._kind == "v4l2" and not path.exists():
            raise CameraError(f"No camera at {path}: check that it is plugged in and look for "
                              "its device with `ls /dev/video*`.", code="camera_not_found")
        if self._kind == "pattern" and not path.parent.is_dir():
            raise CameraError(f"{self.url}: no directory {path.parent} for the image sequence.",
                              code="camera_not_found")
        if self._kind in ("file", "directory") and not path.exists():
            raise CameraError(f"{self.url}: no such file or directory.", code="camera_not_found")
        if self._kind == "file" and path.is_dir():
            self._kind = "directory"
        self._await_release(release, reopening=True)
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="opencv-camera")
        self._cap = self._call(self._open_capture, self.open_timeout, "opening the camera")
        if not self._cap.isOpened():
            self.close()
            raise CameraError(self._open_failure(), code="camera_open_failed")
        self._size = self._call(self._read_size, self.open_timeout, "reading its resolution")
        self._frames_read = 0
        self.freshness = None
        self._stall.delivered()
        self._lost = None

    def close(self) -> None:
        """Release the device. Safe to call twice; never blocks longer than ``open_timeout``."""
        self._await_release(self._release(), reopening=False)

    def _await_release(self, release: Future | None, *, reopening: bool) -> None:
        """Wait up to ``open_timeout`` for ``release`` (from ``_release``) to let go of the device.

        A V4L2 device cannot be opened again before it is let go, so when ``reopening`` a release
        still running raises ``CameraTimeoutError`` and is waited for again by the next ``open``;
        ``close`` gives up waiting without an error.
        """
        if release is not None:
            try:
                release.result(self.open_timeout)
            except FutureTimeout:
                if reopening:
                    raise CameraTimeoutError(
                        f"{self.url}: the device was not let go within {self.open_timeout:g} s "
                        "of being closed, so it cannot be opened yet; try again.") from None
            except cv2.error:
                pass  # a release that fails has let go too
        self._releasing = self._lost = None

    def _release(self) -> Future | None:
        """Forget the capture at once; its release, queued on the capture thread, runs when a
        call stuck there returns. Returns that release (None if nothing was open), or the one a
        loss queued earlier, so that ``open()`` after a loss waits for the device to be let go
        before opening it again, as a real V4L2 device requires."""
        self._draining.clear()
        worker, cap = self._worker, self._cap
        self._worker = self._cap = None
        if worker is None:
            return self._releasing
        release = worker.submit(cap.release) if cap is not None else None
        worker.shutdown(wait=False)  # queued calls still run
        self._releasing = release
        return release

    def grab(self, *, timeout: float = 2.0) -> np.ndarray:
        """A frame exposed after this call (live) or the next frame (recording).

        Shape (H, W, 3) uint8 BGR, or (H, W) for grey recordings. Raises
        ``CameraTimeoutError`` if none arrives within ``timeout`` seconds and ``CameraError``
        at the end of a recording or when a live device disappears.
        """
        deadline = time.monotonic() + timeout
        no_frame = (f"{self.url} delivered no frame within {timeout:g} s: is the camera still "
                    "connected and streaming?")
        try:
            frame = self._call(lambda: self._read(deadline, no_frame), timeout, no_frame)
        except CameraTimeoutError as err:
            error = self._stall.timed_out(err, self.url)
            if error is not err:
                self._lose(error)
            raise error from None
        except CameraError as err:
            if err.code == "camera_disconnected":
                self._lose(err)
            raise
        self._stall.delivered()
        if self._kind == "stream" and self._worker is not None:
            self._draining.set()
            self._worker.submit(self._drain, self._cap)
        return frame

    def _drain(self, cap: Any) -> None:
        """Read and drop a stream's frames until the next grab (or close) asks for the
        capture thread (module docstring); stops at the end of the stream."""
        while self._draining.is_set() and cap.grab():
            pass

    def _lose(self, reason: CameraError) -> None:
        """The device is gone or stalled: close it without waiting (``opened`` is False)."""
        self._release()
        self._lost = reason

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels, as the device reports it."""
        self._check_open()
        return self._size

    def configure(self, *, resolution: tuple[int, int] | None = None,
                  exposure: float | None = None) -> None:
        """Set the resolution and/or a manual exposure (seconds); verified by reading back.

        A request the device ignores or rounds raises ``CameraError`` (code
        ``camera_unsupported``) naming what it delivers instead. Recordings only accept their
        own resolution and have no exposure control.
        """
        self._check_open()
        if exposure is not None and (not np.isfinite(exposure) or exposure <= 0.0):
            raise ValueError(f"exposure must be a positive time in seconds, got {exposure}")
        if resolution is not None and tuple(resolution) != self._size:
            w, h = (int(v) for v in resolution)
            got = self._call(lambda: self._set_resolution(w, h), self.open_timeout,
                             "setting the resolution")
            if got != (w, h):
                raise CameraError(
                    f"{self.url} does not support {w}x{h}; it delivers {got[0]}x{got[1]}.",
                    code="camera_unsupported")
        if exposure is not None:
            if self._kind != "v4l2":
                what = "a network stream: set its exposure in the camera's own settings" \
                    if self.live else "a recording: its exposure cannot be set"
                raise CameraError(f"{self.url} is {what}.", code="camera_unsupported")
            got_s = self._call(lambda: self._set_exposure(exposure), self.open_timeout,
                               "setting the exposure")
            if abs(got_s - exposure) > _V4L2_EXPOSURE_UNIT_S:
                raise CameraError(
                    f"{self.url} does not support a manual exposure of {exposure * 1e3:g} ms "
                    f"(it reports {got_s * 1e3:g} ms).", code="camera_unsupported")

    # ---- worker-thread side -----------------------------------------------------------------

    def _call(self, fn: Callable[[], _T], timeout: float, what: str) -> _T:
        """Run ``fn`` on the capture thread; ``CameraTimeoutError`` after ``timeout`` s.

        ``what`` is the timeout message, or the activity it names (``opening the camera``).
        """
        worker = self._worker
        if worker is None:
            self._check_open()
        self._draining.clear()  # a stream's drain gives the thread back after its next frame
        try:
            return worker.submit(fn).result(timeout=max(timeout, 0.0))
        except FutureTimeout:
            raise CameraTimeoutError(what if what.startswith(self.url) else
                                     f"{self.url} did not answer within {timeout:g} s while "
                                     f"{what}.") from None
        except cv2.error as err:
            raise CameraError(f"{self.url}: OpenCV error: {err.msg}") from None

    def _open_capture(self) -> Any:
        if self._kind == "directory":
            return _ImageDirectory(Path(self._path))
        if self._kind == "stream":
            timeout_ms = round(self.open_timeout * 1000)
            return cv2.VideoCapture(self._path, cv2.CAP_FFMPEG,
                                    [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms,
                                     cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms])
        if self._kind == "v4l2":
            m = re.fullmatch(r"/dev/video(\d+)", self._path)
            return cv2.VideoCapture(int(m.group(1)) if m else self._path, cv2.CAP_V4L2)
        return cv2.VideoCapture(self._path, cv2.CAP_IMAGES if self._kind == "pattern"
                                else cv2.CAP_ANY)

    def _open_failure(self) -> str:
        if self._kind == "stream":
            return (f"No camera stream at {self.url}: the server refused or did not answer "
                    f"within {self.open_timeout:g} s, or sent no video OpenCV can decode. Check "
                    "the address in a browser or with ffprobe.")
        if self._kind == "v4l2":
            return (f"{self._path} exists but cannot be opened as a V4L2 camera: is another "
                    "program using it, or does this user lack access (the 'video' group)?")
        if self._kind == "directory":
            return (f"{self.url}: the directory holds no images "
                    f"({' '.join(IMAGE_SUFFIXES)}).")
        if self._kind == "pattern":
            return f"{self.url}: no image matches the pattern (numbering must start at 0 or 1)."
        return f"{self.url}: not a video file OpenCV can decode."

    def _read_size(self) -> tuple[int, int]:
        return (int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))

    def _read(self, deadline: float, no_frame: str) -> np.ndarray:
        """Discard stale frames (live), grab the frame to return and decode it."""
        cap = self._cap
        if self._kind == "stream":
            fresh = still_frame(cap.grab, lambda: cap.retrieve()[1], deadline=deadline,
                                url=self.url)
            self.freshness = fresh.describe()
            self._frames_read += 1
            return fresh.frame
        if self.live:
            buffers = int(cap.get(cv2.CAP_PROP_BUFFERSIZE))
            queue = buffers if buffers > 0 else DEFAULT_V4L2_BUFFERS
            to_grab = queue + 2
            self.freshness = (f"v4l2: the queue of {queue} buffers and the frame exposed at the "
                              f"call discarded ({queue + 1} frames), the next one returned")
        else:
            to_grab = 1
            self.freshness = RECORDING_FRESHNESS
        while to_grab:
            if time.monotonic() > deadline:
                raise CameraTimeoutError(no_frame)
            if cap.grab():
                to_grab -= 1
                continue
            if not self._source().exists():
                raise CameraError(f"The camera {self._source()} was disconnected.",
                                  code="camera_disconnected")
            if not self.live:
                raise CameraError(
                    f"{self.url}: end of the recording after {self._frames_read} frames; "
                    "there are no more frames to grab.", code="end_of_stream")
            time.sleep(0.005)  # the device is not streaming (yet): retry until the deadline
        ok, frame = cap.retrieve()
        if not ok or frame is None:
            raise CameraError(f"{self.url}: could not decode the frame.", code="corrupt_frame")
        self._frames_read += 1
        return frame

    def _set_resolution(self, w: int, h: int) -> tuple[int, int]:
        self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
        self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
        self._size = self._read_size()
        return self._size

    def _set_exposure(self, exposure: float) -> float:
        self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _V4L2_EXPOSURE_MANUAL)
        self._cap.set(cv2.CAP_PROP_EXPOSURE, exposure / _V4L2_EXPOSURE_UNIT_S)
        return float(self._cap.get(cv2.CAP_PROP_EXPOSURE)) * _V4L2_EXPOSURE_UNIT_S

    def _source(self) -> Path:
        """What must exist while the camera is plugged in: the device node, the video file or
        the directory of the images."""
        path = Path(self._path)
        return path.parent if self._kind == "pattern" else path

    def _check_open(self) -> None:
        if self._cap is None:
            after = f" (closed after: {self._lost})" if self._lost is not None else ""
            raise CameraError(f"{self.url} is not open{after}. Open it first.",
                              code="camera_not_open")


def _parse_url(url: str) -> tuple[str, str]:
    """(kind, path) of a ``v4l2://``, network or ``file://`` URL, else ValueError.

    ``kind`` is ``v4l2``, ``stream`` (path: the whole URL), ``pattern`` (a printf pattern) or
    ``file`` (a video, or a directory once ``open`` has seen it is one). The path is taken
    literally: no percent-decoding, so ``%04d`` stays a pattern.
    """
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme in STREAM_SCHEMES:
        if not parts.hostname:
            raise ValueError(f"{url!r}: a network camera URL names its host, e.g. "
                             f"{scheme}://192.168.0.90/video.mjpg")
        return "stream", url
    if scheme not in ("v4l2", "file"):
        raise ValueError(f"not a camera URL: {url!r}; use v4l2:///dev/videoN, "
                         "http(s)://HOST/PATH, rtsp://HOST/PATH or file:///path")
    if parts.netloc not in ("", "localhost") or not parts.path.startswith("/"):
        raise ValueError(f"{url!r}: write an absolute path after three slashes, e.g. "
                         f"{scheme}:///{(parts.netloc + parts.path).lstrip('/')}")
    if parts.query or parts.fragment:
        raise ValueError(f"{url!r}: camera URLs take no '?' or '#' part")
    if scheme == "v4l2":
        return "v4l2", parts.path
    return ("pattern" if "%" in Path(parts.path).name else "file"), parts.path


def _without_password(url: str) -> str:
    """``url`` with the password of its credentials replaced by ``***`` (for messages)."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return parts._replace(netloc=netloc).geturl()
