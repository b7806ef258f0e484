"""ChArUco views whose markers are mostly unreadable (blur, glare, small markers): the board's
checkerboard grid read whole, and placed by the markers that were decoded.

OpenCV's ``CharucoDetector`` places a corner only between markers it decoded, so a sharp enough
grid with a few decoded markers yields too few corners. The checkerboard detector reads the
grid of inner corners without the markers; which way round it lies (the ids) is then fixed by
the decoded markers: each marker id has one square on the board, and only one turn of the grid
puts the decoded markers on their own squares. Without that agreement the grid is not used.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.boards.checkerboard import detect_checkerboard

#: Fewest decoded markers on their own squares that place a grid, and the least fraction of
#: the decoded markers that must agree (a misread id may disagree).
MIN_PLACING_MARKERS = 2
MIN_AGREEING_FRACTION = 0.5
#: Fewer decoded markers than this fraction of the board's are "few": too few to tell the
#: board's layout (6 of 54 on a blurred view "suggested" 12x3 squares), so their count is the
#: reason a grid they cannot place is refused. More that do not place it mean another layout.
FEW_MARKERS = 0.25
#: A marker is on its square when its centre is within this fraction of a square's width of
#: where the grid puts it.
_ON_SQUARE = 0.3


@dataclass(frozen=True)
class Markers:
    """Decoded markers: ids (M,) and image centres (M, 2) px."""

    ids: np.ndarray
    centres: np.ndarray


def whole_grid(grey: np.ndarray, board: cv2.aruco.CharucoBoard, markers: Markers
               ) -> tuple[np.ndarray, np.ndarray] | str | None:
    """Every inner corner (N, 2) with its id (N,) when the grid is read and the decoded
    ``markers`` place it; the reason when it is read but ``FEW_MARKERS`` cannot place it;
    None otherwise (not read, or markers enough to tell that the layout is another)."""
    cols, rows = (n - 1 for n in board.getChessboardSize())
    read = detect_checkerboard(grey, (cols, rows), min_sharpness=0.0)
    if not read.ok:
        return None
    ids = _placement(read.corners.reshape(rows, cols, 2), board, markers)
    n_markers = len(board.getIds())
    if ids is None and len(markers.ids) >= FEW_MARKERS * n_markers:
        return None
    if ids is None:
        return (f"{len(markers.ids)} of {n_markers} markers decoded; too few to place the grid "
                f"(the {cols}x{rows} corners are in view, but at least {MIN_PLACING_MARKERS} "
                "decoded markers must fix which way round it lies: check for blur and glare)")
    return read.corners, ids


def _placement(grid: np.ndarray, board: cv2.aruco.CharucoBoard, markers: Markers
               ) -> np.ndarray | None:
    """The ids of ``grid``'s points (rows, cols, 2), row-major, for the one turn of the grid
    that puts the decoded markers on their squares; None when no turn clearly does."""
    rows, cols = grid.shape[:2]
    board_xy = np.asarray(board.getChessboardCorners(), dtype=np.float64)[:, :2]  # by corner id
    square_of = dict(zip(np.asarray(board.getIds()).ravel().tolist(),
                         np.asarray(board.getObjPoints())[:, :, :2].mean(axis=1), strict=True))
    known = np.array([int(m) in square_of for m in markers.ids], dtype=bool)
    if known.sum() < MIN_PLACING_MARKERS:
        return None
    on_board = np.array([square_of[int(m)] for m in markers.ids[known]])
    spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    ids = np.arange(rows * cols).reshape(rows, cols)
    agreeing = []
    for turn in range(4) if rows == cols else (0, 2):
        turned = np.rot90(ids, turn)  # which corner id sits at each detected point
        H, _ = cv2.findHomography(board_xy[turned.ravel()], grid.reshape(-1, 2))
        if H is None:
            agreeing.append(0)
            continue
        seen = cv2.perspectiveTransform(on_board.reshape(-1, 1, 2), H).reshape(-1, 2)
        agreeing.append(int((np.linalg.norm(seen - markers.centres[known], axis=1)
                             < _ON_SQUARE * spacing).sum()))
    best = int(np.argmax(agreeing))
    turns = list(range(4) if rows == cols else (0, 2))
    others = sorted(agreeing)[:-1]
    if (agreeing[best] < max(MIN_PLACING_MARKERS, MIN_AGREEING_FRACTION * len(markers.ids))
            or (others and others[-1] > 0)):
        return None
    return np.rot90(ids, turns[best]).ravel().astype(np.int64)
