"""ChArUco target: a checkerboard with ArUco markers in its white squares.

Layout: OpenCV's ``CharucoBoard`` (``squares = (cols, rows)``, square (0, 0) at the top-left
of the printed board, markers in the white squares, ``legacy_pattern`` for boards made by
OpenCV before 4.6). Point id k is OpenCV's ChArUco corner id: the inner corners row-major,
``k = j * (cols - 1) + i``. The target frame has its origin at corner 0, x along ``cols``
(towards corner 1) and y along ``rows`` (towards corner ``cols - 1``), both in the board's
print as OpenCV draws it (x right, y down); z = x × y points into the board, away from a
camera that sees its front, as for the checkerboard (``docs/conventions.md``). So corner
(i, j) is at (κν i s, κ j s, 0) (Strobl & Hirzinger, eq. 4), exactly like a checkerboard with
``(cols - 1, rows - 1)`` inner corners, and the markers make every corner's id certain:
partial views are read, and the origin is never ambiguous.

Detection: ``cv2.aruco.CharucoDetector`` finds the markers and places each corner between
two of them; every corner is then refined on the image itself
(:func:`~calib.boards.detection.refine_corners`), the same sub-pixel step the checkerboard
uses. An image is usable with at least :data:`MIN_CHARUCO_CORNERS` corners not all on one
line (a homography, hence a pose, needs four in general position; two spare).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Annotated, ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from calib.boards import detection as imaging
from calib.boards.base import BoardTarget, TargetLength
from calib.boards.charuco_grid import FEW_MARKERS, Markers, whole_grid
from calib.boards.checkerboard import board_points, rectangle_outline
from calib.boards.detection import MIN_CONTRAST, MIN_SHARPNESS, Detection
from calib.boards.markers import (
    dictionary,
    find_markers,
    guess_charuco_layout,
    markers_seen_reason,
)

#: Fewest corners, not all on one line, that make a view usable.
MIN_CHARUCO_CORNERS = 6
#: Sharpness and contrast from every 8th row of the board region: within 0.15 % of every row
#: on 1920x1200 and 1280x1024 views (blur 0.7-4 px), and keeps detection within 1.2x of
#: ``CharucoDetector.detectBoard`` alone (``benchmarks/charuco.py``).
_QUALITY_ROW_STEP = 8


@dataclass(frozen=True)
class Charuco:
    """A ChArUco board as printed: ``squares`` (cols, rows), nominal ``square_size`` and
    ``marker_size`` (m), OpenCV ``dictionary`` name, ``legacy_pattern``.

    One of the :class:`calib.boards.Board` implementations; partial views allowed.
    """

    squares: tuple[int, int]
    square_size: float
    marker_size: float
    dictionary: str
    legacy_pattern: bool = False
    kind: ClassVar[str] = "charuco"

    def __post_init__(self) -> None:
        cols, rows = (int(n) for n in self.squares)
        if min(cols, rows) < 3 or (cols, rows) != tuple(self.squares):
            raise ValueError(f"squares must be two integers >= 3 (cols, rows), got "
                             f"{self.squares!r}")
        if not 0.0 < self.marker_size < self.square_size:
            raise ValueError(f"marker_size must be positive and smaller than square_size "
                             f"({self.marker_size} >= {self.square_size})")
        words = len(dictionary(self.dictionary).bytesList)
        if (cols * rows) // 2 > words:
            raise ValueError(f"a {cols}x{rows}-square ChArUco board needs "
                             f"{(cols * rows) // 2} markers; {self.dictionary} has {words}")

    @property
    def inner_corners(self) -> tuple[int, int]:
        """(cols - 1, rows - 1): the grid of ChArUco corners."""
        return self.squares[0] - 1, self.squares[1] - 1

    @property
    def point_ids(self) -> np.ndarray:
        """All corner ids, shape ((cols - 1) * (rows - 1),), int64."""
        cols, rows = self.inner_corners
        return np.arange(cols * rows, dtype=np.int64)

    def points(self, ids: np.ndarray | None = None, *, kappa: float = 1.0,
               nu: float = 1.0) -> np.ndarray:
        """Corners ``ids`` (all when None) in the target frame, shape (N, 3)."""
        pts = board_points(self.inner_corners, self.square_size, kappa=kappa, nu=nu)
        return pts if ids is None else pts[np.asarray(ids, dtype=np.int64)]

    def detect(self, image: np.ndarray) -> Detection:
        """:func:`detect_charuco` on this board."""
        return detect_charuco(image, self)

    def outline(self, per_side: int = 8) -> np.ndarray:
        """Points along the printed board's outer edge, shape (4 * per_side, 3)."""
        cols, rows = self.inner_corners
        s = self.square_size
        return rectangle_outline((-s, -s), (cols * s, rows * s), per_side)

    def opencv_board(self) -> cv2.aruco.CharucoBoard:
        """The same board as OpenCV's object (its own units: metres)."""
        board = cv2.aruco.CharucoBoard(tuple(self.squares), self.square_size,
                                       self.marker_size, dictionary(self.dictionary))
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def black_squares(self) -> np.ndarray:
        """Mask (rows, cols) of the squares printed black (those without a marker)."""
        cols, rows = self.squares
        centres = np.asarray(self.opencv_board().getObjPoints())[:, :, :2].mean(axis=1)
        a, b = np.floor(centres / self.square_size).astype(int).T
        black = np.ones((rows, cols), bool)
        black[b, a] = False
        return black

    def target(self) -> CharucoTarget:
        """This board's configuration."""
        return CharucoTarget(type="charuco", squares=self.squares,
                             square_size_m=self.square_size, marker_size_m=self.marker_size,
                             dictionary=self.dictionary, legacy_pattern=self.legacy_pattern)


class CharucoTarget(BoardTarget):
    """A ChArUco board's configuration in OpenCV's layout: ``squares`` [cols, rows], nominal
    square and marker sizes, the ArUco ``dictionary`` by OpenCV's name, ``legacy_pattern``
    for boards made by OpenCV before 4.6."""

    type: Literal["charuco"]
    squares: tuple[Annotated[int, Field(ge=3, le=100)], Annotated[int, Field(ge=3, le=100)]] = (
        Field(description="[cols, rows] of squares; x runs along cols"))
    square_size_m: TargetLength = Field(description="nominal square size in metres")
    marker_size_m: TargetLength = Field(description="nominal marker size in metres")
    dictionary: str = Field(description="OpenCV's ArUco dictionary name, e.g. DICT_5X5_100")
    legacy_pattern: bool = Field(False, description="OpenCV's pre-4.6 ChArUco pattern")

    @model_validator(mode="after")
    def _fits(self) -> CharucoTarget:
        if self.marker_size_m >= self.square_size_m:
            raise ValueError("marker_size_m must be smaller than square_size_m")
        self.board()  # the board's own checks: a known dictionary with enough markers
        return self

    def board(self) -> Charuco:
        return Charuco(self.squares, self.square_size_m, self.marker_size_m, self.dictionary,
                       self.legacy_pattern)


def detect_charuco(image: np.ndarray, board: Charuco, *, min_sharpness: float = MIN_SHARPNESS,
                   min_contrast: float = MIN_CONTRAST) -> Detection:
    """Find the ChArUco corners of ``board`` in a grey or BGR uint8 image, with their ids.

    Corners come from ``CharucoDetector.detectBoard`` (each between two markers seen), are
    refined on the image (:func:`refine_corners`), dropped when their refinement window
    leaves the image, and returned in increasing id order. Bad input never raises: the
    :class:`Detection` says why an image is unusable (no markers, another dictionary's
    markers, too few corners, blur, blank).
    """
    grey, reason = imaging.as_grey(image)
    if grey is None:
        return Detection(ok=False, reason=reason)
    corners, ids, markers = _detect_board(grey, board)
    unplaced = None
    if not _usable(ids, board) and len(markers.ids):
        corners, ids, unplaced = _with_whole_grid(grey, board, markers, corners, ids)
    half = _window(_grid(corners, ids, board))
    inside = _inside(corners, grey.shape, half)
    corners, ids = corners[inside], ids[inside]
    if not _usable(ids, board):
        lo, hi = imaging.grey_range(grey)
        if hi - lo < min_contrast:
            return Detection(ok=False, sharpness=0.0, reason=imaging.blank_reason(lo, hi))
        sharp = imaging.sharpness(grey)
        if sharp < min_sharpness:
            reason = f"image too blurred (sharpness {sharp:.3f} < {min_sharpness:.3f})"
        else:
            reason = unplaced or _missing_reason(grey, board, markers.ids, len(ids))
        return Detection(ok=False, reason=reason, sharpness=sharp)
    corners = imaging.refine_corners(grey, corners, half / 0.3)
    box = imaging.corner_box(grey, corners)
    span = imaging.grey_range(box[::_QUALITY_ROW_STEP])
    sharp = imaging.sharpness(box, _QUALITY_ROW_STEP, span)
    metrics = {"sharpness": sharp, "coverage": imaging.hull_coverage(corners, grey.shape),
               "mean_contrast": _contrast(grey, _grid(corners, ids, board), board, span)}
    if sharp < min_sharpness:
        return Detection(ok=False, **metrics, reason=imaging.blurred_reason(sharp, min_sharpness))
    return Detection(ok=True, corners=corners, ids=ids, **metrics)


def _detect_board(grey: np.ndarray, board: Charuco
                  ) -> tuple[np.ndarray, np.ndarray, Markers]:
    """OpenCV's detector: corners (N, 2) and ids (N,) sorted by id, the decoded markers."""
    detector = cv2.aruco.CharucoDetector(board.opencv_board())
    corners, ids, marker_corners, marker_ids = detector.detectBoard(grey)
    decoded = np.zeros(0, int) if marker_ids is None else marker_ids.ravel()
    markers = Markers(ids=decoded, centres=np.array(
        [np.asarray(c).reshape(4, 2).mean(axis=0) for c in marker_corners]).reshape(-1, 2)
        if len(decoded) else np.zeros((0, 2)))
    if ids is None or len(ids) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64), markers
    ids = ids.ravel().astype(np.int64)
    order = np.argsort(ids)
    return corners.reshape(-1, 2).astype(float)[order], ids[order], markers


def _with_whole_grid(grey: np.ndarray, board: Charuco, markers: Markers, corners: np.ndarray,
                     ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Too few corners between decoded markers: every corner of the grid when the checkerboard
    detector reads it and the markers place it (:func:`whole_grid`), in id order; else the
    corners as they were, with the reason when the grid was read but not placed."""
    whole = whole_grid(grey, board.opencv_board(), markers)
    if whole is None or isinstance(whole, str):
        return corners, ids, whole
    order = np.argsort(whole[1])
    return whole[0][order], whole[1][order], None


def _grid(corners: np.ndarray, ids: np.ndarray, board: Charuco) -> np.ndarray:
    """Corners (N, 2) at their places in the board's corner grid, shape (rows - 1, cols - 1,
    2), NaN where no corner was read."""
    cols, rows = board.inner_corners
    grid = np.full((rows, cols, 2), np.nan)
    grid[ids // cols, ids % cols] = corners
    return grid


def _window(grid: np.ndarray) -> float:
    """Half window (px) of the refinement: 0.3 of the smallest distance between detected
    grid neighbours (:func:`_grid`; as for the checkerboard), between 2 and 5 px."""
    gaps = np.concatenate([np.linalg.norm(np.diff(grid, axis=a), axis=2).ravel()
                           for a in (0, 1)])
    gaps = gaps[np.isfinite(gaps)]
    spacing = gaps.min() if len(gaps) else 2.0 / 0.3
    return float(np.clip(0.3 * spacing, 2, 5))


def _inside(corners: np.ndarray, shape: tuple[int, ...], half: float) -> np.ndarray:
    """Corners whose refinement window (plus the gradient's pixel) lies inside the image."""
    margin = np.floor(half) + 1
    h, w = shape[:2]
    return ((corners >= margin) & (corners <= np.array([w, h]) - 1 - margin)).all(axis=1)


def _usable(ids: np.ndarray, board: Charuco) -> bool:
    """At least :data:`MIN_CHARUCO_CORNERS` corners, not all on one line of the board."""
    if len(ids) < MIN_CHARUCO_CORNERS:
        return False
    cols = board.inner_corners[0]
    d = np.column_stack([ids % cols, ids // cols]) - [ids[0] % cols, ids[0] // cols]
    return bool((d[:, 0] * d[1, 1] - d[:, 1] * d[1, 0]).any())  # a point off line 0-1


def _missing_reason(grey: np.ndarray, board: Charuco, marker_ids: np.ndarray,
                    n_corners: int) -> str:
    """Why the board was not read: no markers (another dictionary's, or none), markers of
    another board, or too few corners."""
    cols, rows = board.squares
    if len(marker_ids) == 0:
        wanted = f"{cols}x{rows}-square ChArUco board with {board.dictionary} markers"
        return markers_seen_reason(grey, wanted) or (
            f"ChArUco board not found: no {board.dictionary} markers in view "
            f"({cols}x{rows} squares expected)")
    n_markers = len(board.opencv_board().getIds())
    foreign = marker_ids[marker_ids >= n_markers]
    if len(foreign) > len(marker_ids) // 2:
        return (f"{len(marker_ids)} {board.dictionary} markers seen, but ids such as "
                f"{int(foreign.max())} are not on a {cols}x{rows}-square board (ids "
                f"0..{n_markers - 1}): check squares")
    layout = (_layout_in_view(grey, board) if len(marker_ids) >= FEW_MARKERS * n_markers
              else None)  # a few markers suggest layouts by chance
    if layout is not None and layout != (cols, rows, board.legacy_pattern):
        return (f"{len(marker_ids)} {board.dictionary} markers seen but only {n_corners} "
                f"ChArUco corners readable: the markers sit as on a board with squares "
                f"[{layout[0]}, {layout[1]}] (rows at least), legacy_pattern "
                f"{str(layout[2]).lower()}: check squares and legacy_pattern")
    return (f"only {n_corners} ChArUco corners readable ({len(marker_ids)} markers seen); at "
            f"least {MIN_CHARUCO_CORNERS} not on one line are needed: bring more of the board "
            "into view, or check for glare and blur")


@lru_cache(maxsize=16)
def _inner_black_squares(board: Charuco) -> np.ndarray:
    """:meth:`Charuco.black_squares` without the outer ring (the squares framed by four
    corners), shape (rows - 2, cols - 2); cached, the board being immutable."""
    return board.black_squares()[1:-1, 1:-1]


def _layout_in_view(grey: np.ndarray, board: Charuco) -> tuple[int, int, bool] | None:
    """The ChArUco layout the board's dictionary's markers in view suggest, if any."""
    seen = find_markers(grey, board.dictionary)
    return None if seen is None else guess_charuco_layout(seen)


def _contrast(grey: np.ndarray, grid: np.ndarray, board: Charuco,
              span: tuple[float, float]) -> float:
    """White minus black grey level: the 99th percentile grey over the corners' bounding box
    (``span``: its 1 % and 99 % levels, every 8th row; the white squares' margins) minus the
    mean at the centres of the black squares whose four corners were all seen in ``grid``
    (:func:`_grid`), or, when none is, the box's 1 % level."""
    lo, white = span
    centres = (grid[:-1, :-1] + grid[:-1, 1:] + grid[1:, :-1] + grid[1:, 1:]) / 4
    dark = centres[_inner_black_squares(board)]
    dark = dark[np.isfinite(dark).all(axis=1)].astype(np.float32)
    if len(dark) == 0:
        return white - lo
    vals = cv2.remap(grey, dark[:, :1], dark[:, 1:], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    return float(white - vals.astype(float).mean())
