"""The one board interface: what the calibration needs to know about a printed target."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from calib.boards.detection import Detection


@runtime_checkable
class Board(Protocol):
    """A printed calibration target.

    ``point_ids`` numbers the board's points; ``points(ids)`` gives their positions in the
    target frame with the print's scale κ and aspect ν (true point (κν x, κ y, 0), Strobl &
    Hirzinger eq. 4); ``detect`` finds the points in an image, with their ids; ``outline``
    is the printed edge, for planning views. Implementations: :class:`Checkerboard`,
    :class:`Charuco`.
    """

    kind: str
    square_size: float

    @property
    def point_ids(self) -> np.ndarray:
        """All point ids, shape (N,), int64."""
        ...

    def points(self, ids: np.ndarray | None = None, *, kappa: float = 1.0,
               nu: float = 1.0) -> np.ndarray:
        """Points ``ids`` (all when None) in the target frame, shape (N, 3), metres."""
        ...

    def detect(self, image: np.ndarray) -> Detection:
        """The board's points in one image, with ids, or the reason it is unusable."""
        ...

    def outline(self, per_side: int = 8) -> np.ndarray:
        """Points along the printed board's outer edge, shape (4 * per_side, 3)."""
        ...
