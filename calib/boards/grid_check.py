"""A checkerboard's corners checked against their neighbours.

Under a pinhole camera the board's grid maps to the image by a homography; lens distortion
bends it, but over a few squares a homography still fits to a small fraction of a square. So
each corner has a place its neighbours predict: the homography fitted to the corners within
three rows and columns, itself left out: linear least squares in the homography's entries
with h33 = 1 (Hartley and Zisserman, sec. 4.1.2), on coordinates in units of the spacing;
three, so that a board corner still has 15 neighbours for the 8 unknowns. Neighbours that
are themselves far from their predictions are down-weighted (iteratively reweighted,
squared Cauchy weights), so a bad corner or two do not move the others' predictions. On the
real sets in ``../shared/data`` real corners are within 0.062 of the square spacing of
their predictions (the most: the strongly distorted OpenCV ``left*.jpg`` under sensor
noise; 0.032 on the KUKA set).

The detector uses it where the sub-pixel refinement moved a corner far from where the grid
search put it: an occluding edge or a sensor artifact (a Kinect's depth-registration shadow
cutting across a row of squares) can pull ``cornerSubPix`` several pixels off the corner. And
it checks every grid it is given: a search on a reduced copy of a steeply tilted board can put
a corner a third of a square off, inside a square where the refinement finds no gradient to
move it by (a demo station: 19 px at a 50 px spacing; the full-size search placed it right).
"""

from __future__ import annotations

import numpy as np

#: Neighbours within this many rows and columns predict a corner.
_REACH = 3
#: Reweighting steps, and the Cauchy scale (in spacings): the misfit at which the Cauchy weight
#: is 1/2, so a neighbour's squared weight 1/4.
_STEPS = 3
_CAUCHY_SCALE = 0.05
#: A refinement that moved a corner by more than this fraction of the spacing is checked.
MOVE_CHECKED = 0.05
#: A corner farther than this (spacings) from where its neighbours put it was misread: 2.4x
#: the farthest real corner (0.062, module docstring).
STRAY = 0.15


def _median_spacing(grid: np.ndarray) -> float:
    """The median distance (px) between neighbours along the rows of ``grid`` (rows, cols, 2):
    the unit of the misfits here."""
    return float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))


def neighbour_prediction(grid: np.ndarray) -> np.ndarray:
    """Where each corner's neighbours put it, shape (rows, cols, 2), for a grid of corners
    (rows, cols, 2) in pixels (rows and columns of at least 3 corners)."""
    rows, cols, _ = grid.shape
    flat = grid.reshape(-1, 2)
    spacing = _median_spacing(grid)
    steps = np.arange(-_REACH, _REACH + 1)
    offsets = np.array([(dj, di) for dj in steps for di in steps if dj or di])  # (M, 2)
    jj, ii = np.divmod(np.arange(rows * cols), cols)
    qj, qi = jj[:, None] + offsets[:, 0], ii[:, None] + offsets[:, 1]  # (N, M)
    inside = (qj >= 0) & (qj < rows) & (qi >= 0) & (qi < cols)
    near = np.where(inside, qj * cols + qi, 0)
    # the homography from grid offsets (x, y) to pixel offsets (u, v) from the corner, in
    # spacings, with its last entry 1 (the corner's own offset (0, 0) maps to (h2, h5))
    uv = (flat[near] - flat[:, None]) / spacing
    u, v = uv[..., 0], uv[..., 1]
    x = np.broadcast_to(offsets[:, 1].astype(float), u.shape)
    y = np.broadcast_to(offsets[:, 0].astype(float), u.shape)
    zero, one = np.zeros_like(u), np.ones_like(u)
    rows_uv = np.concatenate([np.stack([x, y, one, zero, zero, zero, -u * x, -u * y], -1),
                              np.stack([zero, zero, zero, x, y, one, -v * x, -v * y], -1)],
                             axis=1)  # (N, 2M, 8)
    rhs = np.concatenate([u, v], axis=1)  # (N, 2M)
    misfit = np.zeros(len(flat))
    for _ in range(_STEPS):
        weight = np.where(inside, 1.0 / (1.0 + (misfit[near] / _CAUCHY_SCALE) ** 2) ** 2, 0.0)
        weighted = rows_uv.transpose(0, 2, 1) * np.concatenate([weight, weight], axis=1)[:, None]
        h = np.linalg.solve(weighted @ rows_uv, (weighted @ rhs[..., None]))[..., 0]
        at_corner = h[:, [2, 5]]
        misfit = np.linalg.norm(at_corner, axis=1)
    return (flat + at_corner * spacing).reshape(rows, cols, 2)


def keep_consistent(start: np.ndarray, refined: np.ndarray, inner_corners: tuple[int, int],
                    spacing: float) -> np.ndarray:
    """``refined`` corners (N, 2), row-major over ``inner_corners`` (cols, rows), where each
    that the refinement moved by more than ``MOVE_CHECKED`` spacings from ``start`` keeps
    the refined place only if it is nearer the place its neighbours predict than its start
    is. The common case (nothing moved that far) costs one comparison."""
    moved = np.linalg.norm(refined - start, axis=1) > MOVE_CHECKED * spacing
    cols, rows = inner_corners
    if not moved.any() or min(cols, rows) < 3:
        return refined
    predicted = neighbour_prediction(refined.reshape(rows, cols, 2)).reshape(-1, 2)
    strays = moved & (np.linalg.norm(refined - predicted, axis=1)
                      > np.linalg.norm(start - predicted, axis=1))
    return np.where(strays[:, None], start, refined)


def stray_corners(corners: np.ndarray, inner_corners: tuple[int, int]) -> np.ndarray:
    """Which corners (N, 2), row-major over ``inner_corners`` (cols, rows), lie more than
    ``STRAY`` spacings from where their neighbours put them, shape (N,) bool (none for a grid
    thinner than 3 corners, where no neighbourhood has enough of them)."""
    cols, rows = inner_corners
    if min(cols, rows) < 3:
        return np.zeros(len(corners), dtype=bool)
    grid = np.asarray(corners, dtype=float).reshape(rows, cols, 2)
    misfit = np.linalg.norm(neighbour_prediction(grid) - grid, axis=-1) / _median_spacing(grid)
    return misfit.reshape(-1) > STRAY
