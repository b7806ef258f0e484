"""A frozen camera: the frame of an earlier station handed out again after the robot moved.

A camera whose stream or driver hangs on one frame (an IP camera's encoder stuck, a stream
server repeating its last snapshot, a driver re-queueing its last buffer) still answers every
grab at once, so no grab timeout or stall catches it, and a stream's freshness test passes:
two consecutive frames that are the same frame agree (``drivers.freshness``, difference 0).
Every station then pairs a new robot pose with one old image: a 12-station mock run whose
camera froze after its second frame ended ``done``, and its calibration failed with "fewer
than 2 station pairs rotate by more than 2 deg: add stations with the tool tilted", which
points at the poses instead of the camera.

A live sensor's noise changes every frame, so a frame equal bit for bit to the frame taken
at the previous station, although the robot moved between them by more than ``MIN_MOTION``,
was not exposed at this station: the camera is frozen (``CameraFrozenError``, code
``camera_frozen``). A camera without noise (a rendered test scene) still shows a moved robot
differently. A retry at the same pose is no evidence, and a blank frame (one grey level
throughout: a lens cap, darkness) shows nothing that would change; both are left alone (the
board detection reports a blank frame).
"""

from __future__ import annotations

import hashlib
import threading

import numpy as np

from calib import matrix_from_ur_pose, pose_error
from drivers.errors import CameraFrozenError

#: A robot motion (metres, radians) beyond which a bit-identical frame is a frozen camera:
#: 1 mm or 0.1 deg, well above the drift a still robot shows (``CaptureOptions.max_drift``).
MIN_MOTION = (1e-3, np.deg2rad(0.1))


class FrameWatch:
    """The frames of one capture (a run, a re-check), to tell a frozen camera (module doc).

    ``identical`` counts the frames in a row that were bit-identical, the current one
    included (1: the last frame differed from the one before it, or was blank). Safe to share
    between threads (posts to several external runs grab from one camera).
    """

    def __init__(self, min_motion: tuple[float, float] = MIN_MOTION) -> None:
        self.min_motion = min_motion
        self.identical = 1
        self._digest: bytes | None = None
        self._T_base_tcp_first: np.ndarray | None = None  # (4, 4), where the frame first came
        self._lock = threading.Lock()

    def check(self, image: np.ndarray, tcp_pose: np.ndarray) -> None:
        """Take ``image`` (uint8 (H, W) or (H, W, 3)), the frame of the robot at ``tcp_pose``
        (UR pose (6,), read after the grab); ``CameraFrozenError`` if it is bit for bit the
        frame of an earlier grab although the robot has moved since that grab."""
        T_base_tcp = matrix_from_ur_pose(np.asarray(tcp_pose, dtype=float))
        digest = _digest(image)
        with self._lock:
            if digest is None or digest != self._digest:
                self.identical, self._digest, self._T_base_tcp_first = 1, digest, T_base_tcp
                return
            self.identical += 1
            identical, T_first = self.identical, self._T_base_tcp_first
        assert T_first is not None
        angle, dist = pose_error(T_first, T_base_tcp)
        if dist <= self.min_motion[0] and angle <= self.min_motion[1]:
            return  # the same view again: no evidence
        raise CameraFrozenError(
            f"The camera is frozen: {identical} identical frames in a row, the last "
            f"after the robot moved {dist * 1e3:.1f} mm / {np.rad2deg(angle):.2f} deg (a live "
            "camera's frames always differ, so the first of them may be old too). Its stream "
            "or driver keeps handing out one frame: restart the camera (or its stream "
            "server), then resume the run (or post the station again).")


def _digest(image: np.ndarray) -> bytes | None:
    """A fingerprint of ``image``'s pixels and shape, or None for a blank frame."""
    image = np.ascontiguousarray(image)
    if image.size == 0 or image.min() == image.max():
        return None
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((image.shape, image.dtype.str)).encode())
    h.update(memoryview(image).cast("B"))
    return h.digest()
