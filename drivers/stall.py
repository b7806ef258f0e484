"""Telling a stalled camera from a late frame: consecutive grab timeouts.

One grab timeout can be a hiccup (a USB transfer retried, an exposure change); several in a row
mean the camera stopped delivering. Cameras count them with ``StallCounter`` and turn the
``limit``-th consecutive timeout into one ``CameraStalledError`` (code ``camera_stalled``), so a
capture ends with one camera fault instead of timing out station after station.
"""

from __future__ import annotations

from drivers.errors import CameraStalledError, CameraTimeoutError

#: Consecutive grab timeouts that make a camera count as stalled.
STALL_AFTER = 3


class StallCounter:
    """Consecutive grab timeouts of one camera; a delivered frame resets the count."""

    def __init__(self, limit: int = STALL_AFTER) -> None:
        if limit < 1:
            raise ValueError(f"a stall needs at least 1 timeout, got {limit}")
        self.limit = limit
        self.count = 0

    def delivered(self) -> None:
        """A frame arrived: the streak is over."""
        self.count = 0

    def timed_out(self, err: CameraTimeoutError, camera: str) -> CameraTimeoutError | \
            CameraStalledError:
        """The error to raise for this timeout: ``err`` itself, or the stall it completes."""
        self.count += 1
        if self.count < self.limit:
            return err
        self.count = 0
        return CameraStalledError(
            f"{camera} delivered no frame in {self.limit} grabs in a row ({err}); it has "
            "stalled and was closed. Check its cable and that no other program uses it, then "
            "open it again.")
