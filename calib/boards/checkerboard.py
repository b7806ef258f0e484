"""Checkerboard target: board geometry and corner detection with a canonical origin.

Geometry (``docs/conventions.md``): ``inner_corners = (cols, rows)``; true corner (i, j) is
at (κν i s, κ j s, 0) in the target frame (Strobl & Hirzinger, eq. 4), nominal at κ = ν = 1.
Corner arrays are row-major: point id ``j * cols + i``, x along cols. A checkerboard is read
only when all its corners are in view (``ids`` = all).

Origin convention. The board has (cols + 1) x (rows + 1) squares; square (a, b) is the one
whose far corner is inner corner (a, b), so square (0, 0) lies diagonally outside corner
(0, 0) in the -x -y direction. **Square (0, 0) is black**; squares with a + b even are black.
A camera always sees the board from the front, where z = x × y points away from it, so in
the image (u right, v down) the x → y turn is clockwise: that fixes the handedness of the
order. Then:

- cols + rows odd (e.g. 11x8, 9x6): the two ends of the board have opposite colours, so the
  colour of the squares decides the origin in every image (:func:`order_corners`).
- cols + rows even (e.g. 8x6, 7x7): the pattern is the same after a 180° turn (a square
  board also after 90°), so no single image can tell the ends apart. Detection still returns
  a canonical order (the one whose x axis points most to the image right) and sets
  ``ambiguous=True``; a later stage must pick the physical origin using the robot poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field

from calib.boards.base import BoardTarget, TargetLength
from calib.boards.detection import (
    MIN_CONTRAST,
    MIN_SHARPNESS,
    Detection,
    as_grey,
    blank_reason,
    blurred_reason,
    find_board_sb,
    grey_range,
    hull_coverage,
    region_sharpness,
    sharpness,
    sub_pixel,
)
from calib.boards.grid_check import keep_consistent, stray_corners
from calib.boards.grid_survey import GridSurvey, diagnose_missing_board, even_square_darkness
from calib.boards.markers import markers_seen_reason

#: Images at least this large (smaller side, px) are searched at half size first: SB's cost
#: grows with the pixel count, and a board that fills a 1280x720 or larger image has squares
#: wide enough at half size (all of ``rwhe-kuka_1``'s 28x17 boards at 1928x1208 are read there).
_COARSE_MIN_SIZE = 720
#: ... and at quarter size first from this size on (quarter-size squares of the 1280x1024
#: renders and of ``rwhe-kuka_1`` are read there; of the 1280x720 UR Kinect images some are
#: not). A quarter-size find is kept only when every corner refines on the half-size image,
#: and a coarse find only when no corner strays from its neighbours (``grid_check``).
_QUARTER_MIN_SIZE = 960
#: SB detector flags tried, in order, only when the default call (flags 0, what an OpenCV user
#: writes) fails: with normalisation (low contrast), the exhaustive search with and without it,
#: and last with ``CALIB_CB_ACCURACY``, whose up-sampled search reads some boards the others
#: miss (it is 4x slower, and its corners are replaced by the sub-pixel refinement's anyway).
_FALLBACK_FLAGS = (
    cv2.CALIB_CB_NORMALIZE_IMAGE,
    cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE,
    cv2.CALIB_CB_EXHAUSTIVE,
    cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY,
)
#: Local contrast equalisation for the last attempt (tile size in board-independent px).
_CLAHE = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8))


@dataclass(frozen=True)
class Checkerboard:
    """A checkerboard as printed: ``inner_corners`` (cols, rows), nominal ``square_size`` (m).

    One of the :class:`calib.boards.Board` implementations; point ids run row-major over
    the inner corners, and a detection always holds all of them.
    """

    inner_corners: tuple[int, int]
    square_size: float
    kind: ClassVar[str] = "checkerboard"

    @property
    def point_ids(self) -> np.ndarray:
        """All point ids, shape (cols * rows,), int64."""
        cols, rows = _check_inner_corners(self.inner_corners)
        return np.arange(cols * rows, dtype=np.int64)

    def points(self, ids: np.ndarray | None = None, *, kappa: float = 1.0,
               nu: float = 1.0) -> np.ndarray:
        """Inner corners ``ids`` (all when None) in the target frame, shape (N, 3):
        :func:`board_points`."""
        pts = board_points(self.inner_corners, self.square_size, kappa=kappa, nu=nu)
        return pts if ids is None else pts[np.asarray(ids, dtype=np.int64)]

    def detect(self, image: np.ndarray) -> Detection:
        """:func:`detect_checkerboard` with this board's corner counts."""
        return detect_checkerboard(image, self.inner_corners)

    def mismatch(self, image: np.ndarray) -> str | None:
        """:func:`grid_mismatch` with this board's corner counts
        (``calib.boards.ChecksConfiguration``)."""
        return grid_mismatch(image, self.inner_corners)

    def outline(self, per_side: int = 8) -> np.ndarray:
        """Points along the outer edge of the squares (one square beyond the inner corners),
        shape (4 * per_side, 3), target frame."""
        cols, rows = self.inner_corners
        s = self.square_size
        return rectangle_outline((-s, -s), (cols * s, rows * s), per_side)

    def target(self) -> CheckerboardTarget:
        """This board's configuration."""
        return CheckerboardTarget(inner_corners=self.inner_corners,
                                  square_size_m=self.square_size)


class CheckerboardTarget(BoardTarget):
    """A checkerboard's configuration: ``inner_corners`` [cols, rows], nominal
    ``square_size_m``; ``type`` may be left out (the default board type)."""

    type: Literal["checkerboard"] = "checkerboard"
    inner_corners: tuple[Annotated[int, Field(ge=2, le=100)],
                         Annotated[int, Field(ge=2, le=100)]] = Field(
        description="[cols, rows] of inner corners; x runs along cols")
    square_size_m: TargetLength = Field(description="nominal square size in metres")

    def board(self) -> Checkerboard:
        return Checkerboard(self.inner_corners, self.square_size_m)


def rectangle_outline(lo: tuple[float, float], hi: tuple[float, float],
                      per_side: int) -> np.ndarray:
    """Points along the rectangle ``lo``..``hi`` (x, y) in the target plane, going round
    from ``lo``, shape (4 * per_side, 3)."""
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)
    (x0, y0), (x1, y1) = lo, hi
    xs = np.concatenate([x0 + (x1 - x0) * t, np.full_like(t, x1), x1 - (x1 - x0) * t,
                         np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + (y1 - y0) * t, np.full_like(t, y1),
                         y1 - (y1 - y0) * t])
    return np.stack([xs, ys, np.zeros_like(xs)], axis=1)


def board_points(inner_corners: tuple[int, int], square_size: float, *, kappa: float = 1.0,
                 nu: float = 1.0) -> np.ndarray:
    """Inner corners in the target frame, shape (cols * rows, 3), row-major (x along cols).

    Corner (i, j) is at (κν i s, κ j s, 0) (Strobl & Hirzinger, eq. 4).
    """
    cols, rows = _check_inner_corners(inner_corners)
    if not np.isfinite(square_size) or square_size <= 0:
        raise ValueError(f"square_size must be a positive length in metres, got {square_size}")
    j, i = np.mgrid[0:rows, 0:cols]
    s = square_size * kappa
    return np.stack([i.ravel() * s * nu, j.ravel() * s, np.zeros(i.size)], axis=1)


def detect_checkerboard(image: np.ndarray, inner_corners: tuple[int, int], *,
                        min_sharpness: float = MIN_SHARPNESS,
                        min_contrast: float = MIN_CONTRAST) -> Detection:
    """Find the checkerboard's inner corners in a grey or BGR uint8 image.

    Uses OpenCV's sector-based detector (``findChessboardCornersSB``), puts the corners in the
    canonical order (:func:`order_corners`) and refines them (``sub_pixel``, a refined place
    kept where the neighbours agree with it: ``grid_check.keep_consistent``).
    Bad input never raises: the returned :class:`Detection` says why it was rejected.

    Parameters
    ----------
    image : ndarray, shape (H, W), (H, W, 1) or (H, W, 3) BGR, uint8
    inner_corners : (cols, rows)
    min_sharpness, min_contrast : float
        Quality bounds; see :class:`Detection`.
    """
    cols, rows = _check_inner_corners(inner_corners)
    grey, reason = as_grey(image)
    if grey is None:
        return Detection(ok=False, reason=reason)
    lo, hi = grey_range(grey)
    faint = hi - lo < min_contrast  # a blank frame, or a board in a few grey levels
    survey = GridSurvey(grey)
    found, raw, coarse = ((False, None, False) if hi == lo
                          else _find_grid(grey, (cols, rows), survey, quick=faint))
    if not found:
        if faint:
            return Detection(ok=False, sharpness=0.0, reason=blank_reason(lo, hi))
        sharp = sharpness(grey)
        if sharp < min_sharpness:
            reason = f"image too blurred (sharpness {sharp:.3f} < {min_sharpness:.3f})"
        else:
            reason = ((survey.lattice((cols, rows)) is None  # a dense grid is slow to scan
                       and markers_seen_reason(grey, f"{cols}x{rows}-corner checkerboard"))
                      or diagnose_missing_board(survey, (cols, rows)))
        return Detection(ok=False, reason=reason, sharpness=sharp)

    corners, ambiguous, contrast = order_corners(grey, raw.reshape(-1, 2), (cols, rows))
    spacing = _spacing(corners, (cols, rows))
    refined, converged = sub_pixel(grey, corners, spacing)
    if coarse and not converged.all():
        # a reduced copy's corner the refinement could not reach (on a steep view one 4 px
        # off) starts again from the full-size search's, if that search reads the board
        found, raw = find_board_sb(grey, (cols, rows))
        if found:
            full = order_corners(grey, raw.reshape(-1, 2), (cols, rows))[0]
            again = ~converged & (np.linalg.norm(full - corners, axis=1) < spacing / 2)
            corners[again] = full[again]
            refined[again], converged[again] = sub_pixel(grey, full[again], spacing)
    if min(cols, rows) < 3:  # no neighbourhoods: the window's convergence limit decides
        refined[~converged] = corners[~converged]
    # else every refined place is weighed against its start by the neighbours, also one
    # beyond that limit: on a steep view even the full-size search's corner can be 3 px off
    corners = keep_consistent(corners, refined, (cols, rows), spacing)
    sharp = region_sharpness(grey, corners)
    metrics = {"sharpness": sharp, "coverage": hull_coverage(corners, grey.shape),
               "mean_contrast": contrast, "ambiguous": ambiguous}
    if sharp < min_sharpness:
        return Detection(ok=False, **metrics, reason=blurred_reason(sharp, min_sharpness))
    return Detection(ok=True, corners=corners, **metrics)


def _find_grid(grey: np.ndarray, inner_corners: tuple[int, int], survey: GridSurvey, *,
               quick: bool = False) -> tuple[bool, np.ndarray | None, bool]:
    """OpenCV's SB detector with its default flags, on a half-size copy of a large image first
    (about 4x faster; a quarter-size copy before it, 4x faster again, from
    ``_QUARTER_MIN_SIZE`` on), then on the full image: the common case costs one call.

    Coarse corners are scaled back (a half-size pixel centre x sits at 2x + 0.5) and are
    only a start for the sub-pixel refinement at full resolution; quarter-size ones are first
    refined on the half-size copy, and the find is dropped unless all of them converge there
    (a quarter-size start is up to 2 px off, beyond the full-size window); a coarse find with a
    corner its neighbours do not predict is dropped too (``stray_corners``). Only when the
    default call fails is the full image searched with each of ``_FALLBACK_FLAGS`` in turn,
    and last the exhaustive search on a locally equalised copy (CLAHE) for boards in shadow or
    glare; except when ``survey`` sees a board larger than ``inner_corners``, or more grid
    corners than ``LATTICE_FACTOR`` such boards (``calib.boards.grid_survey``): SB reads a
    board of exactly the size asked for, so the searches could not succeed (a wrong
    ``inner_corners`` is told in a fraction of a second instead of several; a checker
    texture costs no fallback). ``quick`` (faint images, usually blank frames) tries the
    normalised searches alone. Returns whether it found the board, its corners
    (cols * rows, 2) in full-size pixels, and whether a reduced copy's search found them.
    """
    in_view = survey
    if min(grey.shape) >= _COARSE_MIN_SIZE:
        half = cv2.pyrDown(grey)
        if min(grey.shape) >= _QUARTER_MIN_SIZE:
            found, raw = find_board_sb(cv2.pyrDown(half), inner_corners)
            if found:
                start = raw.reshape(-1, 2) * 2.0 + 0.5  # half-size pixels
                corners, converged = sub_pixel(half, start, _spacing(start, inner_corners))
                if converged.all() and not stray_corners(corners, inner_corners).any():
                    return True, corners * 2.0 + 0.5, True
        found, raw = find_board_sb(half, inner_corners)
        if found and not stray_corners(raw.reshape(-1, 2), inner_corners).any():
            return True, raw * 2.0 + 0.5, True
        in_view = GridSurvey(half)  # a grid has the same size at half size, 4x cheaper
    found, raw = find_board_sb(grey, inner_corners)
    if found:
        return True, raw, False
    if (not quick and in_view.larger_than(inner_corners)) or survey.lattice(inner_corners):
        return False, None, False
    for flags in _FALLBACK_FLAGS[:2] if quick else _FALLBACK_FLAGS:
        found, raw = find_board_sb(grey, inner_corners, flags)
        if found:
            return True, raw, False
    if quick:
        return False, None, False
    found, raw = find_board_sb(_CLAHE.apply(grey), inner_corners, _FALLBACK_FLAGS[1])
    return (True, raw, False) if found else (False, None, False)


def _spacing(corners: np.ndarray, inner_corners: tuple[int, int]) -> float:
    """The smallest distance (px) between neighbouring corners of a grid (cols * rows, 2) in
    row-major order."""
    cols, rows = inner_corners
    grid = corners.reshape(rows, cols, 2)
    return float(min(np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
                     np.linalg.norm(np.diff(grid, axis=1), axis=-1).min()))


def order_corners(grey: np.ndarray, corners: np.ndarray,
                  inner_corners: tuple[int, int]) -> tuple[np.ndarray, bool, float]:
    """Put a detected grid in the canonical order of the module docstring.

    Handles any order a detector may return: row- or column-major (transposed), either
    handedness, either end first.

    Parameters
    ----------
    grey : ndarray, shape (H, W), uint8
    corners : ndarray, shape (cols * rows, 2)
    inner_corners : (cols, rows)

    Returns
    -------
    corners : ndarray, shape (cols * rows, 2), float64
    ambiguous : bool
        True when the board's symmetry leaves the origin undecided (cols + rows even).
    contrast : float
        Mean grey level of white minus black inner squares.
    """
    cols, rows = inner_corners
    pts = np.asarray(corners, dtype=float).reshape(-1, 2)
    grid = pts.reshape(rows, cols, 2)
    if cols != rows:
        transposed = pts.reshape(cols, rows, 2).transpose(1, 0, 2)
        if _bending(transposed) < _bending(grid):
            grid = transposed
    if _signed_area(grid) < 0:
        grid = grid[:, ::-1]
    candidates = [grid, grid[::-1, ::-1]]
    if cols == rows:
        candidates += [np.rot90(grid, 1), np.rot90(grid, -1)]
    if (cols + rows) % 2:
        dark = even_square_darkness(grey, grid)
        return (grid if dark > 0 else candidates[1]).reshape(-1, 2), False, abs(dark)
    rightness = [g[:, -1].mean(axis=0)[0] - g[:, 0].mean(axis=0)[0] for g in candidates]
    best = candidates[int(np.argmax(rightness))]
    return best.reshape(-1, 2), True, abs(even_square_darkness(grey, best))


def _check_inner_corners(inner_corners: tuple[int, int]) -> tuple[int, int]:
    try:
        cols, rows = (int(n) for n in inner_corners)
    except (TypeError, ValueError):
        raise ValueError(f"inner_corners must be (cols, rows), got {inner_corners!r}") from None
    if cols < 2 or rows < 2 or (cols, rows) != tuple(inner_corners):
        raise ValueError(f"inner_corners must be two integers >= 2, got {inner_corners!r}")
    return cols, rows


def _bending(grid: np.ndarray) -> float:
    """Mean second difference along both grid axes (px); small for a true grid order."""
    return float(np.linalg.norm(np.diff(grid, 2, axis=0), axis=-1).mean()
                 + np.linalg.norm(np.diff(grid, 2, axis=1), axis=-1).mean())


def _signed_area(grid: np.ndarray) -> float:
    """Shoelace area of the outer corners (0,0), (c,0), (c,r), (0,r); > 0 when x → y is
    clockwise on screen, i.e. the board is seen from its front."""
    q = np.array([grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]])
    return float(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1]))


def grid_mismatch(image: np.ndarray, inner_corners: tuple[int, int]) -> str | None:
    """What ``image`` shows instead of a board of ``inner_corners`` (cols, rows): "found a 9x6
    grid of inner corners, you configured 12x9"; None when it shows that size (either way
    round), no grid, or a grid it cannot vouch for.

    The grid survey (any size, on a half-size copy of a large image) is read again with SB at
    exactly the size it saw. SB reads only a board of exactly the size asked for, so success
    means the whole board in view has that size, not a patch of a larger one hidden in part
    (which the survey also reports). Costs two detector calls, not the full search for a
    board that is not there.
    """
    cols, rows = _check_inner_corners(inner_corners)
    grey, _ = as_grey(image)
    if grey is None:
        return None
    survey = GridSurvey(grey if min(grey.shape) < _COARSE_MIN_SIZE else cv2.pyrDown(grey))
    grid = survey.grid
    if grid is None:
        return None
    seen = sorted(grid.shape[1::-1], reverse=cols >= rows)  # in the configured order
    if seen == sorted((cols, rows), reverse=cols >= rows):
        return None
    found, _ = find_board_sb(survey.grey, tuple(seen))
    if not found:
        return None
    return (f"found {_article(seen[0])} {seen[0]}x{seen[1]} grid of inner corners, you "
            f"configured {cols}x{rows}")


def _article(n: int) -> str:
    """'an' before a number said with a vowel first (8, 11, 18, 80-89, ...), else 'a'."""
    return "an" if str(n).startswith("8") or n in (11, 18) else "a"
