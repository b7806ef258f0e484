"""Boards on a dark plate, in a white margin, in a frame: what surrounds a board is no larger
grid. Whatever ``findChessboardCornersSB`` reads under any of its flag sets is read, and a
wrong ``inner_corners`` is told with the board's true size.

The images are rendered (``mocks.render``) by a 1280x720 camera (a Kinect-like eye-to-hand
view, searched at full size) with the board's printed margin and the background around it set
to what a cell shows: ``margin_squares`` of white paper, then ``background`` grey levels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.boards import detect_checkerboard
from mocks.render import RenderParams, render_board
from mocks.scene import camera_pose_for_tcp, default_scene, sample_station_poses

SCENE = default_scene()
VIEWS = camera_pose_for_tcp(SCENE, sample_station_poses(SCENE, 8, np.random.default_rng(3)))
SB_FLAGS = (0, cv2.CALIB_CB_NORMALIZE_IMAGE, cv2.CALIB_CB_EXHAUSTIVE,
            cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE, cv2.CALIB_CB_ACCURACY)
#: (inner corners, square size m, white margin in squares, background grey level)
SURROUNDINGS = {
    "9x6 on a dark plate": ((9, 6), 0.04, 0.0, 20.0),
    "9x6, thin margin, dark plate": ((9, 6), 0.04, 0.3, 20.0),
    "8x5, one-square white margin": ((8, 5), 0.04, 1.0, 110.0),
    "8x5, two-square margin, dark frame": ((8, 5), 0.04, 2.0, 20.0),
    "8x5 small, half-square margin, dark plate": ((8, 5), 0.02, 0.5, 20.0),
    "9x6 small, one-square white margin": ((9, 6), 0.02, 1.0, 110.0),
}


def _render(name: str, view: int, size: tuple[int, int] = (1280, 720)) -> np.ndarray:
    board, square, margin, background = SURROUNDINGS[name]
    K = SCENE.camera.k_matrix.copy()
    K[:2, 2] -= (np.array(SCENE.camera.image_size) - size) / 2  # same centre of view
    params = RenderParams.from_scene(SCENE, image_size=size, K=tuple(K.ravel()),
                                     inner_corners=board, square_size=square,
                                     margin_squares=margin, background=background,
                                     image_noise=2.0, blur_px=0.7)
    return render_board(params, VIEWS[view], rng=np.random.default_rng(view))


def _same_grid(ours: np.ndarray, theirs: np.ndarray, board: tuple[int, int]) -> float:
    """Largest corner distance (px) between two detections of a grid, over the grid flips."""
    cols, rows = board
    g = theirs.reshape(rows, cols, 2)
    flips = [g, g[::-1, ::-1], g[::-1], g[:, ::-1]]
    return min(float(np.abs(f.reshape(-1, 2) - ours).max()) for f in flips)


@pytest.mark.slow
@pytest.mark.parametrize("name", SURROUNDINGS)
def test_every_board_opencv_reads_is_read(name):
    board = SURROUNDINGS[name][0]
    read_by_opencv = 0
    for view in range(0, len(VIEWS), 2):
        grey = _render(name, view)
        theirs = next((c for found, c in (cv2.findChessboardCornersSB(grey, board, flags=f)
                                          for f in SB_FLAGS) if found), None)
        if theirs is None:
            continue
        read_by_opencv += 1
        det = detect_checkerboard(grey, board)
        assert det.ok, f"view {view}: {det.reason}"
        assert _same_grid(det.corners, theirs.reshape(-1, 2), board) < 2.0
    assert read_by_opencv >= 2  # the scene shows the board; the test compares something


@pytest.mark.parametrize(("name", "view"), [("8x5, two-square margin, dark frame", 3),
                                            ("8x5 small, half-square margin, dark plate", 0)])
def test_views_once_refused_as_larger_grids_are_read(name, view):
    """Views that a survey counting the plate's edge refused ("a larger 6x8 grid is
    visible") although OpenCV reads them."""
    board = SURROUNDINGS[name][0]
    grey = _render(name, view)
    assert any(cv2.findChessboardCornersSB(grey, board, flags=f)[0] for f in SB_FLAGS)
    det = detect_checkerboard(grey, board)
    assert det.ok, det.reason


@pytest.mark.parametrize(("name", "view", "size"), [
    ("9x6 small, one-square white margin", 5, (1280, 1024)),
    ("8x5, two-square margin, dark frame", 4, (1280, 1024)),
])
def test_wrong_inner_corners_name_the_true_board(name, view, size):
    """Asked for a board one corner smaller, the reason names the board in view, not the
    board plus a row of points along its edge (these views were told "a larger 9x7 grid",
    "a larger 5x9 grid")."""
    cols, rows = SURROUNDINGS[name][0]
    det = detect_checkerboard(_render(name, view, size), (cols - 1, rows))
    assert not det.ok
    assert f"a larger {cols}x{rows} grid" in det.reason or f"a larger {rows}x{cols} grid" \
        in det.reason, det.reason
