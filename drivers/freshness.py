"""Fresh frames from a network stream: skip what was buffered, then wait for a still scene.

A network camera (MJPEG over HTTP, RTSP) gives no exposure time a client can compare with the
robot's settle time: FFmpeg's ``CAP_PROP_POS_MSEC`` counts stream time from the first frame,
not the camera's clock. Two kinds of old frames reach a client that grabs after the robot has
settled:

- *buffered* frames: while nobody reads (during the move) the socket and FFmpeg's demuxer hold
  frames, which a grab then returns without waiting, oldest first; they may even show the
  previous station;
- *late* frames: encoding and the network delay every frame by a few frame periods, so even
  a frame that arrives after the call may have been exposed while the robot was moving.

So a stream frame is taken as fresh when (1) it and the frame before it both had to be waited
for (the grab blocked at least ``WAITED_S``: the buffer was empty, so they are the newest the
camera has sent) and (2) the two agree: the scene did not change between their exposures
(mean absolute difference of their grey thumbnails at most ``STILL_LEVEL``), so the robot
stood still during both. A robot still moving in late frames makes consecutive frames differ,
and the search goes on; a scene that never settles (something moving in view) is refused with
code ``scene_moving`` when the grab's time is up.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from drivers.errors import CameraError

#: A grab that blocks at least this long found no buffered frame (s); a buffered frame is
#: handed out in well under a millisecond, a waited one after up to a frame period.
WAITED_S = 0.004
#: Two thumbnails whose mean absolute difference is at most this (grey levels, 0..255) show a
#: still scene: sensor and JPEG noise average out in the thumbnail, while a board edge that
#: moves by one image pixel changes it by several levels.
STILL_LEVEL = 1.5
#: Width of the thumbnails compared (pixels).
THUMB_WIDTH = 80


def thumbnail(frame: np.ndarray) -> np.ndarray:
    """A small grey float32 copy of ``frame`` ((H, W) or (H, W, 3) uint8), for comparing."""
    grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    h, w = grey.shape[:2]
    scale = min(1.0, THUMB_WIDTH / max(w, 1))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32)


@dataclass(frozen=True)
class Fresh:
    """A frame taken as fresh and how: ``skipped`` frames were discarded before it,
    ``difference`` is the mean grey-level difference to the frame before it."""

    frame: np.ndarray
    skipped: int
    difference: float

    def describe(self) -> str:
        """How freshness was ensured, in one line (stored with the station)."""
        return (f"stream: {self.skipped} frames skipped (buffered or taken while the scene "
                f"moved), then two consecutive frames waited for that agree (mean difference "
                f"{self.difference:.2f} grey levels, at most {STILL_LEVEL:g})")


def still_frame(grab: Callable[[], bool], retrieve: Callable[[], np.ndarray | None], *,
                deadline: float, url: str) -> Fresh:
    """Grab until a frame is fresh (module docstring) and return it.

    ``grab`` is the capture's ``grab`` (False: the stream ended, raises ``camera_disconnected``),
    ``retrieve`` decodes the last grabbed frame. Raises ``CameraError`` (``scene_moving``) if
    no two consecutive fresh frames agree before ``deadline`` (``time.monotonic()``).
    """
    before: tuple[np.ndarray, bool] | None = None  # the previous frame's thumbnail, waited
    skipped, difference = -1, float("inf")
    while True:
        started = time.monotonic()
        if started > deadline:
            raise CameraError(
                f"{url}: no two consecutive frames agreed (last difference {difference:.1f} "
                f"grey levels, at most {STILL_LEVEL:g}) in {skipped + 1} frames: something "
                "moves in view, or the robot had not settled.", code="scene_moving")
        if not grab():
            raise CameraError(f"The camera {url} was disconnected (its stream ended).",
                              code="camera_disconnected")
        waited = time.monotonic() - started >= WAITED_S
        frame = retrieve()
        if frame is None:
            raise CameraError(f"{url}: could not decode the frame.", code="corrupt_frame")
        thumb = thumbnail(frame)
        if before is not None and before[0].shape == thumb.shape:
            difference = float(np.mean(np.abs(thumb - before[0])))
            if waited and before[1] and difference <= STILL_LEVEL:
                return Fresh(frame, skipped, difference)
        before = (thumb, waited)
        skipped += 1
