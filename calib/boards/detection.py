"""What every board's detector returns, and the image helpers they share.

:class:`Detection` holds the corners a board found in one image with their point ids (the
board's own numbering, :attr:`Board.point_ids`), a reason when the image is unusable, and the
quality figures the service shows (sharpness, coverage, contrast). The helpers turn any
camera image into grey, measure its grey range and edge sharpness, and refine corners to
sub-pixel on the image itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import cv2
import numpy as np

#: Default lower bound on :attr:`Detection.sharpness` (a Gaussian edge blur sigma of 4 px).
MIN_SHARPNESS = 0.1
#: Default lower bound on the image's robust grey range (1st to 99th percentile).
MIN_CONTRAST = 20.0
#: Gaussian sigma (px) of the smoothing applied before the sub-pixel refinement.
_REFINE_SIGMA = 1.2
#: Largest half window (px) of the sub-pixel refinement.
_REFINE_HALF_WINDOW = 5


@dataclass(frozen=True)
class Detection:
    """Result of a board's ``detect`` for one image.

    Attributes
    ----------
    ok : bool
        True when ``corners`` holds enough usable points and the image passed the checks.
    corners : ndarray, shape (N, 2), float64, or None
        Pixel positions of the points ``ids``, in that order; None unless ``ok``.
    ids : ndarray, shape (N,), int64, or None
        Board point ids of ``corners`` (all of them, in order, for a full checkerboard);
        defaults to ``0 .. N-1`` when ``corners`` is given without ids.
    reason : str or None
        Why the image was rejected, in words a person can act on; None when ``ok``.
    sharpness : float or None
        Edge steepness over the board region (whole image if no board): mean of the top 1 %
        gradient magnitudes divided by the grey range, per pixel. About 0.4 for a crisp
        image, ``1 / (sigma sqrt(2 pi))`` for an edge blurred by a Gaussian of ``sigma`` px.
        None for unreadable images.
    coverage : float
        Fraction of the image area inside the convex hull of the corners (0 if none).
    mean_contrast : float or None
        Mean grey level of white minus black squares; None without corners.
    ambiguous : bool
        True for boards symmetric under 180° (cols + rows even): the origin is at one of the
        symmetric ends and must be resolved by a later stage.
    """

    ok: bool
    corners: np.ndarray | None = None
    reason: str | None = None
    sharpness: float | None = None
    coverage: float = 0.0
    mean_contrast: float | None = None
    ambiguous: bool = False
    ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.corners is None:
            return
        corners = np.asarray(self.corners, dtype=float).reshape(-1, 2)
        ids = (np.arange(len(corners), dtype=np.int64) if self.ids is None
               else np.asarray(self.ids, dtype=np.int64).reshape(-1))
        if len(ids) != len(corners):
            raise ValueError(f"{len(ids)} ids for {len(corners)} corners")
        object.__setattr__(self, "corners", corners)
        object.__setattr__(self, "ids", ids)


def as_grey(image: object) -> tuple[np.ndarray | None, str | None]:
    """The image as contiguous 2-D uint8, or None and the reason it is unusable."""
    if not isinstance(image, np.ndarray):
        return None, f"image is empty/corrupt: expected an array, got {type(image).__name__}"
    if image.size == 0:
        return None, f"image is empty/corrupt: no pixels (shape {image.shape})"
    if image.dtype != np.uint8:
        return None, f"image is empty/corrupt: expected 8-bit pixels (uint8), got {image.dtype}"
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    elif image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        return None, f"image is empty/corrupt: expected grey or BGR, got shape {image.shape}"
    return np.ascontiguousarray(image), None


#: How OpenCV says an allocation failed (under a worker's address-space limit): its allocator's
#: message, or the assertion ``u != 0`` in ``UMat::create`` when the allocator returned
#: nothing; which one depends on where the work ran out.
OPENCV_OUT_OF_MEMORY = ("Insufficient memory", "Failed to allocate", "u != 0")


def opencv_out_of_memory(exc: cv2.error) -> bool:
    """Whether an OpenCV error is a failed allocation."""
    return any(sign in str(exc) for sign in OPENCV_OUT_OF_MEMORY)


@overload
def find_board_sb(grey: np.ndarray, inner_corners: tuple[int, int], flags: int = 0, *,
                  with_meta: Literal[False] = False) -> tuple[bool, np.ndarray | None]: ...


@overload
def find_board_sb(grey: np.ndarray, inner_corners: tuple[int, int], flags: int = 0, *,
                  with_meta: Literal[True]
                  ) -> tuple[bool, np.ndarray | None, np.ndarray | None]: ...


def find_board_sb(grey: np.ndarray, inner_corners: tuple[int, int], flags: int = 0, *,
                  with_meta: bool = False) -> tuple:
    """OpenCV's sector-based board search on ``grey`` (H, W) uint8 for ``inner_corners``
    (cols, rows): ``(found, corners)``, corners (N, 1, 2) float32 px, N = cols * rows, or
    with ``with_meta`` ``(found, corners, meta)`` (``findChessboardCornersSBWithMeta``; meta
    (rows, cols) of the grid found, which ``CALIB_CB_LARGER`` lets be larger, N its size). An
    assertion that fails inside the search is a board not found, so that detection never
    raises on an image: its neighbour index fails on some regular grids (``result.full()`` in
    ``getNeighbors``, on a 500x500 image of 32-pixel checkers). A failed allocation
    (:func:`opencv_out_of_memory`) still raises.

    Every board search of ``calib`` goes through here. Benchmarks and tests call
    ``cv2.findChessboardCornersSB`` directly on purpose: they compare with what an OpenCV
    user's own call gets.
    """
    try:
        if with_meta:
            return cv2.findChessboardCornersSBWithMeta(grey, inner_corners, flags)
        return cv2.findChessboardCornersSB(grey, inner_corners, flags=flags)
    except cv2.error as exc:
        if opencv_out_of_memory(exc):
            raise
        return (False, None, None) if with_meta else (False, None)


def grey_range(grey: np.ndarray) -> tuple[float, float]:
    """1st and 99th percentile grey levels of a uint8 image, from its 256-bin histogram
    (exact for integer levels, and many times faster than ``np.percentile``)."""
    cdf = np.cumsum(cv2.calcHist([grey], [0], None, [256], [0, 256]).ravel())
    lo, hi = np.searchsorted(cdf, [0.01 * cdf[-1], 0.99 * cdf[-1]])
    return float(lo), float(hi)


def blank_reason(lo: float, hi: float) -> str:
    """The one wording for an image without contrast."""
    return (f"image is blank: grey levels span only {lo:.0f}..{hi:.0f} "
            "(nothing in view, lens cap, lighting or exposure?)")


def sharpness(grey: np.ndarray, row_step: int = 1,
              span: tuple[float, float] | None = None) -> float:
    """Mean of the top 1 % gradient magnitudes over the 1-99 % grey range, per pixel.

    ``row_step`` > 1 takes the gradients and grey levels of every ``row_step``-th row only:
    the same statistic from fewer samples, for detectors that must stay close to OpenCV's
    speed. ``span``: the (1 %, 99 %) grey levels of those rows when the caller has them.
    """
    gx = cv2.Sobel(grey, cv2.CV_16S, 1, 0, ksize=3)[::row_step].astype(np.float32)
    gy = cv2.Sobel(grey, cv2.CV_16S, 0, 1, ksize=3)[::row_step].astype(np.float32)
    mag = cv2.magnitude(gx, gy).ravel() / 8.0
    top = np.partition(mag, int(0.99 * mag.size))[int(0.99 * mag.size):]
    lo, hi = grey_range(grey[::row_step]) if span is None else span
    return float(top.mean() / max(hi - lo, 1.0))


def corner_box(grey: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The image region (a view) spanned by ``corners`` (N, 2): the board's bounding box."""
    x0, y0 = np.floor(corners.min(axis=0)).astype(int)
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int)
    return grey[max(y0, 0):y1 + 1, max(x0, 0):x1 + 1]


def region_sharpness(grey: np.ndarray, corners: np.ndarray, row_step: int = 1) -> float:
    """:func:`sharpness` over the bounding box of ``corners`` (N, 2)."""
    return sharpness(corner_box(grey, corners), row_step)


def hull_coverage(corners: np.ndarray, image_shape: tuple[int, ...]) -> float:
    """Fraction of the image area inside the convex hull of ``corners`` (N, 2)."""
    hull = cv2.convexHull(corners.astype(np.float32))
    return float(cv2.contourArea(hull)) / float(image_shape[0] * image_shape[1])


def blurred_reason(value: float, limit: float) -> str:
    """The one wording for a board found with soft edges."""
    return (f"image too blurred: the board was found but its edges are soft (sharpness "
            f"{value:.3f} < {limit:.3f}), corners would be inaccurate")


def refine_corners(grey: np.ndarray, corners: np.ndarray, spacing: float) -> np.ndarray:
    """Sub-pixel corners, shape (N, 2): ``cornerSubPix`` on a Gaussian-smoothed image.

    On rendered images with known truth this is 2-5x more accurate than the SB detector's own
    ``CALIB_CB_ACCURACY`` (0.02-0.03 px RMS against 0.03-0.16 px) because smoothing removes
    the pixel locking that gradient-based refinement shows on very sharp edges; on the 13
    OpenCV ``left*.jpg`` images it lowers the ``cv2.calibrateCamera`` RMS from 0.234 px
    (``CALIB_CB_ACCURACY``) to 0.182 px. The window shrinks for small squares (``spacing``,
    the smallest corner distance in px); a corner that wanders off its window keeps its
    start. Only a tile around each corner is smoothed (:func:`_corner_mosaic`): the same
    values as smoothing the whole image wherever a window inside the image looks, at a third
    of the cost for a board filling a 1920x1200 image.
    """
    refined, converged = sub_pixel(grey, corners, spacing)
    refined[~converged] = corners[~converged]
    return refined


def sub_pixel(grey: np.ndarray, corners: np.ndarray, spacing: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_corners`'s search: the refined corners (N, 2) and which of them stayed
    within their window (N,) bool; the others are where the search wandered off to."""
    if len(corners) == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    half = int(np.clip(0.3 * spacing, 2, _REFINE_HALF_WINDOW))
    # cornerSubPix keeps a result within one window of its start and reads the window plus
    # one pixel around it; the Gaussian reaches round(8 sigma + 1) // 2 pixels.
    radius = 2 * half + 1 + round(8 * _REFINE_SIGMA + 1) // 2
    mosaic, shift = _corner_mosaic(grey, corners, radius)
    smooth = cv2.GaussianBlur(mosaic.astype(np.float32), (0, 0), _REFINE_SIGMA)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    start = (corners + shift).astype(np.float32).reshape(-1, 1, 2)
    refined = cv2.cornerSubPix(smooth, start, (half, half), (-1, -1), criteria)
    refined = refined.reshape(-1, 2).astype(float) - shift
    return refined, np.linalg.norm(refined - corners, axis=1) <= 0.6 * half


def _corner_mosaic(grey: np.ndarray, corners: np.ndarray, radius: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The (2 r + 1)² pixels around each of the N corners (r = ``radius``), laid out as the
    tiles of a square mosaic (small coordinates keep ``cornerSubPix``'s float32 positions
    precise), and each corner's shift (N, 2) from image to mosaic pixels. Pixels beyond the
    image are mirrored as ``cv2.BORDER_REFLECT_101`` (the smoothing's own border rule) does."""
    h, w = grey.shape
    n, size = len(corners), 2 * radius + 1
    per_row = int(np.ceil(np.sqrt(n)))
    per_col = -(-n // per_row)
    origins = np.rint(corners).astype(int) - radius  # tiles' top-left pixels in the image
    tiles = np.zeros((per_row * per_col, size, size), grey.dtype)
    inside = ((origins >= 0) & (origins <= [w - size, h - size])).all(axis=1)
    if inside.any():
        x0, y0 = origins[inside].T
        tiles[:n][inside] = np.lib.stride_tricks.sliding_window_view(grey, (size, size))[y0, x0]
    steps = np.arange(size)
    xs = _reflect_101(origins[~inside, :1] + steps, w)
    ys = _reflect_101(origins[~inside, 1:] + steps, h)
    tiles[:n][~inside] = grey[ys[:, :, None], xs[:, None, :]]
    mosaic = tiles.reshape(per_col, per_row, size, size).swapaxes(1, 2)
    slot = np.arange(n)
    placed = np.column_stack([slot % per_row, slot // per_row]) * size
    return mosaic.reshape(per_col * size, per_row * size), (placed - origins).astype(float)


def _reflect_101(index: np.ndarray, n: int) -> np.ndarray:
    """Indices mirrored into 0..n-1 without repeating the edge pixel (…2 1 | 0 1 2…)."""
    period = 2 * n - 2
    index = np.abs(index) % period
    return np.where(index >= n, period - index, index)
