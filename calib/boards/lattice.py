"""How many corners of a regular checker grid an image shows, without OpenCV's board search.

A board search (``findChessboardCornersSB``) that fails on an image with a regular checker
grid larger than the board is slow: every grid corner starts a candidate board that grows to
the grid's edge and is dropped there. A 1-megapixel PNG of 32-pixel checkers (2 kB on the
wire) took 12.8 CPU-s of fallback searches, 8-pixel checkers 26.9 (issue 22), where a real
1928x1208 image with its board at 10 % contrast takes 4.5. Where the default searches failed
and the image shows clearly more grid corners than the board has, no search for the board can
succeed, and :func:`regular_corners` says so in tens of milliseconds.

A checker corner (an X-junction of two dark and two light squares) is a saddle of the
smoothed grey image: its Hessian determinant ``I_xx I_yy - I_xy²`` is strongly negative,
where an edge gives about zero and a blob a positive value. The strength
``sqrt(I_xy² - I_xx I_yy) σ² / contrast`` (contrast: the 1st to 99th percentile grey range)
does not depend on the corner's size or contrast: a sharp corner scores about 1.0 with the
kernels here (1.03 measured), real ones 0.3-1.0; a local maximum above a quarter is a
candidate. Sensor noise, text and clutter make candidates too, but scattered ones: a corner
counts only where its four nearest candidates form a grid cell around it (all four at the
same distance within 20 %, in two opposite pairs). On the real sets in ``../shared/data``,
under every degradation ``tests/test_detection_real`` makes, that count is at most 1.13 times
the board's own corners (a 9x6 board in ``opencv-left`` at 10 % contrast; 1.00 on the KUKA
and UR sets); beyond ``LATTICE_FACTOR`` times, the grid in view is no board of the size asked
for.

The count is taken on the image and on each ``cv2.pyrDown`` of it (coarse grids show best at
coarse levels, fine ones at full size), and the largest is kept.
"""

from __future__ import annotations

import cv2
import numpy as np

from calib.boards.detection import grey_range

#: A grid with more regular corners than this many times the board's corners is not the board
#: (the real sets' most: 1.13, a 9x6 board in ``opencv-left`` at 10 % contrast).
LATTICE_FACTOR = 1.5
#: Gaussian smoothing (px) before the Hessian, at every pyramid level.
_SIGMA = 1.5
#: A candidate's strength must reach this (an ideal corner's is about 1.0 with these kernels).
_MIN_STRENGTH = 0.25
#: Neighbour distances and opposite pairs agree within this fraction of the spacing.
_TOLERANCE = 0.2
#: Levels smaller than this (px, smaller side) are not searched.
_MIN_SIDE = 60


def regular_corners(grey: np.ndarray) -> int:
    """The largest number of regular grid corners (see the module doc) at any pyramid level of
    ``grey`` (H, W) uint8."""
    best, level = 0, grey
    while min(level.shape) >= _MIN_SIDE:
        best = max(best, _regular(_candidates(level)))
        level = cv2.pyrDown(level)
    return best


def _candidates(grey: np.ndarray) -> np.ndarray:
    """Saddle points of ``grey`` strong enough to be checker corners, shape (N, 2) px."""
    lo, hi = grey_range(grey)
    smooth = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), _SIGMA)
    dxx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3)
    dyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3)
    dxy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3)
    strength = np.sqrt(np.maximum(dxy * dxy - dxx * dyy, 0.0)) * (_SIGMA**2 / max(hi - lo, 1.0))
    window = np.ones((2 * round(2 * _SIGMA) + 1,) * 2, np.uint8)
    peaks = (strength >= cv2.dilate(strength, window)) & (strength > _MIN_STRENGTH)
    # a flat-topped maximum is one candidate, at its centre
    _, _, _, centres = cv2.connectedComponentsWithStats(peaks.astype(np.uint8), connectivity=8)
    return centres[1:]


def _regular(points: np.ndarray) -> int:
    """How many of ``points`` (N, 2) have their four nearest neighbours at one distance, in
    two opposite pairs: the corners inside a grid."""
    if len(points) < 5:
        return 0
    from scipy.spatial import cKDTree  # here: ``import calib.boards`` loads no scipy

    dist, idx = cKDTree(points).query(points, k=5)
    dist, idx = dist[:, 1:], idx[:, 1:]
    spacing = np.median(dist, axis=1)
    even = (np.abs(dist / spacing[:, None] - 1.0) < _TOLERANCE).all(axis=1)
    steps = points[idx] - points[:, None, :]  # (N, 4, 2), in turn order below
    turn = np.argsort(np.arctan2(steps[..., 1], steps[..., 0]), axis=1)
    steps = np.take_along_axis(steps, turn[..., None], axis=1)
    opposite = ((np.linalg.norm(steps[:, 0] + steps[:, 2], axis=1) < _TOLERANCE * spacing)
                & (np.linalg.norm(steps[:, 1] + steps[:, 3], axis=1) < _TOLERANCE * spacing))
    return int((even & opposite).sum())

