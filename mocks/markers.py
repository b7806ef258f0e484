"""ArUco markers of a ChArUco board for the renderer, in OpenCV's board layout.

OpenCV's ``cv2.aruco.CharucoBoard((cols, rows), square, marker, dictionary)`` puts square (x, y)
(x right, y down as printed, square (0, 0) at the board's top-left) at [x s, (x + 1) s] x
[y s, (y + 1) s]; it is black when x + y is even, unless ``legacy_pattern`` is set on a board
with an even number of rows, which swaps the colours. Every white square holds a marker of
side ``marker``, centred, with ids 0, 1, 2, ... in row-major order of the white squares. A
marker is a (bits + 2)² grid of cells (one black border cell each side) whose top row lies
towards -y. Chessboard corner k sits at ((k mod (cols - 1)) + 1) s, (k div (cols - 1) + 1) s).

The renderer works in *grid units* where chessboard corner (i, j) is at (i, j): square (x, y)
spans [x - 1, x] x [y - 1, y] there. :func:`marker_coverage` gives the fraction of a sample's
footprint (a box of ``fx`` x ``fy`` grid units) covered by black marker cells, with the same
linear-ramp box filter as the squares: exact while the footprint is smaller than a marker cell
and than the white gap between marker and square edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np


@dataclass(frozen=True)
class MarkerLayout:
    """What fixes a ChArUco board's markers: ``squares`` (cols, rows), ``marker_frac`` (marker
    side / square side, in (0, 1)), ``dictionary`` (OpenCV's name, e.g. ``DICT_5X5_100``) and
    ``legacy_pattern`` (OpenCV's pre-4.6 layout)."""

    squares: tuple[int, int]
    marker_frac: float
    dictionary: str
    legacy_pattern: bool = False

    @property
    def swapped_colours(self) -> bool:
        """True when square (0, 0) is white (legacy pattern with an even number of rows)."""
        return self.legacy_pattern and self.squares[1] % 2 == 0


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary ``name`` (``ValueError`` naming the choices if unknown)."""
    code = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(code, int):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise ValueError(f"unknown ArUco dictionary {name!r}; one of {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(code)


def marker_count(squares: tuple[int, int]) -> int:
    """Number of markers (white squares) on a board of ``squares`` (cols, rows)."""
    cols, rows = squares
    return cols * rows // 2


@lru_cache(maxsize=8)
def marker_tables(layout: MarkerLayout) -> tuple[np.ndarray, np.ndarray]:
    """Which marker each square holds and the markers' black cells.

    Returns ``table`` (rows, cols) int: marker index of square (x, y) at ``table[y, x]``, -1
    for a black square; and ``black`` (n_markers, n + 2, n + 2) float32: 1 on black cells of
    marker k's (n x n)-cell grid, padded by one white cell on each side.
    """
    cols, rows = layout.squares
    dictionary = aruco_dictionary(layout.dictionary)
    n_markers = marker_count(layout.squares)
    if n_markers > dictionary.bytesList.shape[0]:
        raise ValueError(f"a {cols}x{rows} ChArUco board needs {n_markers} markers; "
                         f"{layout.dictionary} has only {dictionary.bytesList.shape[0]}")
    x, y = np.meshgrid(np.arange(cols), np.arange(rows))
    white = (x + y) % 2 == (0 if layout.swapped_colours else 1)
    table = np.full((rows, cols), -1)
    table[white] = np.arange(n_markers)
    n = dictionary.markerSize + 2
    black = np.zeros((n_markers, n + 2, n + 2), dtype=np.float32)
    for k in range(n_markers):
        cells = cv2.aruco.generateImageMarker(dictionary, k, n, borderBits=1)
        black[k, 1:-1, 1:-1] = cells < 128
    table.setflags(write=False)
    black.setflags(write=False)
    return table, black


def marker_coverage(layout: MarkerLayout, gx: np.ndarray, gy: np.ndarray, fx: np.ndarray,
                    fy: np.ndarray) -> np.ndarray:
    """Black marker coverage of every sample, shape of ``gx`` (float32, 0 outside markers).

    ``gx``, ``gy``: sample centres in grid units (NaN off the board plane); ``fx``, ``fy``:
    footprint extents in grid units. Along each axis the footprint straddles at most the two
    cells around the nearest cell boundary k; cell k gets the ramp weight
    clip((u - k) / f + 1/2, 0, 1), cell k - 1 the rest (as ``render._box``).
    """
    table, black = marker_tables(layout)
    cols, rows = layout.squares
    out = np.zeros(gx.shape, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        sx = np.floor(gx) + 1.0
        sy = np.floor(gy) + 1.0
        on_board = (sx >= 0) & (sx < cols) & (sy >= 0) & (sy < rows)
    sel = np.flatnonzero(on_board)
    sx_i, sy_i = sx.flat[sel].astype(np.intp), sy.flat[sel].astype(np.intp)
    marker = table[sy_i, sx_i]
    keep = marker >= 0
    sel, marker, sx_i, sy_i = sel[keep], marker[keep], sx_i[keep], sy_i[keep]
    n = black.shape[1] - 2
    cell = layout.marker_frac / n
    gap = (1.0 - layout.marker_frac) / 2.0

    def weights(g: np.ndarray, square: np.ndarray, f: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest padded-cell boundary k (ints) and the weight of cell k."""
        u = (g.flat[sel] - (square - 1) - gap) / cell + 1.0
        k = np.clip(np.rint(u), 1, n + 1)
        w = np.clip((u - k) / (f.flat[sel] / cell) + 0.5, 0.0, 1.0)
        return k.astype(np.intp), w.astype(np.float32)

    kx, wx = weights(gx, sx_i, fx)
    ky, wy = weights(gy, sy_i, fy)
    cov = (black[marker, ky - 1, kx - 1] * (1 - wx) + black[marker, ky - 1, kx] * wx) * (1 - wy)
    cov += (black[marker, ky, kx - 1] * (1 - wx) + black[marker, ky, kx] * wx) * wy
    out.flat[sel] = cov
    return out
