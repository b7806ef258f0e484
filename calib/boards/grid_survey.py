"""The checkerboard grid in view whatever its size, and what it says about a board that was
not found: off the image, a wrong ``inner_corners``, or a board seen but not read.

Two ways tell a grid larger than the board. :class:`GridSurvey`'s ``grid`` is OpenCV's search
for any grid of at least 3x3 corners (``CALIB_CB_LARGER``): it gives a real board's exact
size, also one only a little larger than asked (a 10x7 board where 9x6 was asked), but on a
checker texture filling the image it stops at a patch of a few corners (3x4 to 5x3 on 8-64 px
checkers at 1 MP) and tells nothing. Its ``lattice`` counts the regular grid corners
without a board search (``calib.boards.lattice``): tens of milliseconds on any texture, but
only a count, so it tells only a grid well beyond the board (``LATTICE_FACTOR`` boards). The
detector skips its fallback searches when either says so (``checkerboard._find_grid``); the
diagnosis names the grid's size where the board search found one.
"""

from __future__ import annotations

import cv2
import numpy as np

from calib.boards.detection import find_board_sb, grey_range
from calib.boards.lattice import LATTICE_FACTOR, regular_corners


class GridSurvey:
    """The checkerboard grid in view, whatever its size (at least 3x3 inner corners, its
    squares really alternating black and white; ``CALIB_CB_LARGER``): found once, on first
    use, for the search and the diagnosis of a missing board.

    ``CALIB_CB_LARGER`` may extend a board by a row of points on its outer edge, where the
    outer squares meet a dark plate, a frame or a white margin: those are no corners, and the
    board no larger grid. Such rows are trimmed (:func:`_without_edge_rows`).
    """

    def __init__(self, grey: np.ndarray) -> None:
        self.grey = grey
        self._grid: np.ndarray | None = None  # (rows, cols, 2) px
        self._done = False
        self._regular: int | None = None  # regular corners in view, counted on first use

    def lattice(self, inner_corners: tuple[int, int]) -> int | None:
        """The regular grid corners in view (:func:`calib.boards.lattice.regular_corners`)
        when they are more than ``LATTICE_FACTOR`` boards of ``inner_corners`` (cols, rows)
        have, else None."""
        if self._regular is None:
            self._regular = regular_corners(self.grey)
        cols, rows = inner_corners
        return self._regular if self._regular > LATTICE_FACTOR * cols * rows else None

    @property
    def grid(self) -> np.ndarray | None:
        """The grid in view, (rows, cols, 2) px, or None when there is none."""
        if not self._done:
            self._done = True
            found, pts, meta = find_board_sb(
                self.grey, (3, 3), cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_LARGER,
                with_meta=True)
            if found and pts is not None:
                grid = pts.reshape(*meta.shape[:2], 2).astype(float)
                lo, hi = grey_range(self.grey)
                if abs(even_square_darkness(self.grey, grid)) >= 0.25 * (hi - lo):
                    self._grid = _without_edge_rows(self.grey, grid, 0.25 * (hi - lo))
        return self._grid

    def larger_than(self, inner_corners: tuple[int, int]) -> bool:
        """True when the grid in view is larger than ``inner_corners`` (either way round)."""
        if self.grid is None:
            return False
        seen, wanted = sorted(self.grid.shape[1::-1]), sorted(inner_corners)
        return seen != wanted and seen[0] >= wanted[0] and seen[1] >= wanted[1]


def _without_edge_rows(grey: np.ndarray, grid: np.ndarray, contrast: float
                       ) -> np.ndarray | None:
    """``grid`` (rows, cols, 2) without its outer rows or columns of points that are no
    corners: a true corner row has alternating squares on both sides, so the ring of squares
    just beyond the outermost row (extrapolated by one spacing) must alternate by at least
    ``contrast`` grey levels too. Beyond a row found on the board's edge lies the plate, the
    frame or the margin: one colour. A ring that leaves the image proves nothing and is kept.
    None when fewer than 3x3 corners remain."""
    trimmed = True
    while trimmed and min(grid.shape[:2]) >= 3:
        trimmed = False
        for turn in range(4):  # each side in turn as row 0
            turned = np.rot90(grid, turn)
            alternation = _ring_alternation(grey, turned)
            if alternation is not None and alternation < contrast:
                grid = np.rot90(turned[1:], -turn)
                trimmed = True
                break
    return grid if min(grid.shape[:2]) >= 3 else None


def _ring_alternation(grey: np.ndarray, grid: np.ndarray) -> float | None:
    """Mean grey of the even minus the odd squares (absolute) in the ring of squares beyond
    row 0 of ``grid`` (rows, cols, 2), each sampled at its centre and halfway to its corners;
    None when a sample falls outside the image."""
    edge, beyond = grid[0], 2 * grid[0] - grid[1]
    samples = _square_samples(edge[:-1], edge[1:], beyond[:-1], beyond[1:])  # (5, cols - 1, 2)
    h, w = grey.shape
    if (samples < 0).any() or (samples[..., 0] > w - 1).any() or (samples[..., 1] > h - 1).any():
        return None
    vals = _mean_grey(grey, samples)
    return float(abs(vals[::2].mean() - vals[1::2].mean()))


def diagnose_missing_board(survey: GridSurvey, inner_corners: tuple[int, int]) -> str:
    """Reason for a failed detection: off-image, wrong size, or simply not found, from the
    grid ``survey`` sees compared with what was asked for."""
    cols, rows = inner_corners
    grid, lattice = survey.grid, survey.lattice(inner_corners)
    if lattice is not None and not survey.larger_than(inner_corners):
        return (f"board not found: a regular grid of about {lattice} corners is in view, more "
                f"than a {cols}x{rows}-corner board has (check inner_corners)")
    if grid is None:
        return f"board not found ({cols}x{rows} inner corners expected)"
    grey = survey.grey
    grid_rows, grid_cols = grid.shape[:2]
    pts = grid.reshape(-1, 2)
    h, w = grey.shape
    spacing = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1))
    near_edge = ((pts < 1.5 * spacing) | (pts > np.array([w, h]) - 1.5 * spacing)).any()
    if near_edge and len(pts) < cols * rows:
        return (f"only part of the board is visible: {grid_cols}x{grid_rows} of {cols}x{rows} "
                "inner corners found, the board runs off the image")
    seen, wanted = sorted((grid_cols, grid_rows)), sorted((cols, rows))
    if seen == wanted:
        return (f"board seen ({grid_cols}x{grid_rows} inner corners) but not read reliably "
                "(glare, shadow or strong perspective?)")
    if seen[0] >= wanted[0] and seen[1] >= wanted[1]:
        return (f"board not found with {cols}x{rows} inner corners; a larger "
                f"{grid_cols}x{grid_rows} grid is visible: check inner_corners")
    if seen[0] <= wanted[0] and seen[1] <= wanted[1] and len(pts) < cols * rows // 2:
        return (f"board not read: only a {grid_cols}x{grid_rows} patch of the {cols}x{rows} "
                "inner corners could be followed (part of the board hidden, in glare or "
                "shadow, or too blurred?)")
    return (f"board not found with {cols}x{rows} inner corners; a {grid_cols}x{grid_rows} "
            "grid is visible: check inner_corners, or whether part of the board is hidden")


def even_square_darkness(grey: np.ndarray, grid: np.ndarray) -> float:
    """Mean grey of inner squares with a + b odd minus those with a + b even.

    Inner square (a, b), 1 <= a < cols, 1 <= b < rows, is bounded by corners (a-1..a,
    b-1..b); it is sampled at its centre and halfway to each of its corners. Positive when
    the even squares (the colour of square (0, 0), ``calib.boards.checkerboard``) are
    the dark ones.
    """
    vals = _mean_grey(grey, _square_samples(grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1],
                                            grid[1:, 1:]))
    b, a = np.mgrid[1:grid.shape[0], 1:grid.shape[1]]
    even = (a + b) % 2 == 0
    return float(vals[~even].mean() - vals[even].mean())


def _square_samples(*corners: np.ndarray) -> np.ndarray:
    """Where squares are sampled, shape (5, ..., 2) px: each square's centre and the points
    halfway to its four corners, from the four arrays (..., 2) px of those corners."""
    centre = sum(corners) / 4
    return np.stack([centre] + [(centre + c) / 2 for c in corners])


def _mean_grey(grey: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Each square's mean grey over its ``samples`` (5, ..., 2) px (:func:`_square_samples`),
    bilinear, a sample off the image taking the nearest edge pixel; shape (...)."""
    m = samples.reshape(-1, 1, 2).astype(np.float32)
    vals = cv2.remap(grey, m[..., 0], m[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(samples.shape[:-1])
    return vals.astype(float).mean(axis=0)
