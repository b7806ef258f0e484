"""ChArUco boards: geometry against OpenCV's layout, detection with ids on images warped by a
known homography (full, rotated, cut at the image border), and the reasons for unusable views."""

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from calib.boards import (
    MIN_CHARUCO_CORNERS,
    Charuco,
    CharucoTarget,
    Checkerboard,
    CheckerboardTarget,
    Detection,
    TargetAdapter,
    board_from_target,
    detect_checkerboard,
    target_from_board,
)
from calib.boards.detection import refine_corners

BOARD = Charuco((8, 6), 0.04, 0.03, "DICT_5X5_100")
PX = 80  # pixels per square in the flat print
PAD = 40  # white paper around the print, px
IMAGE = (1280, 960)


def _print(board: Charuco) -> np.ndarray:
    """The board as OpenCV draws it, PX per square, on white paper."""
    cols, rows = board.squares
    flat = board.opencv_board().generateImage((cols * PX, rows * PX), marginSize=0)
    return cv2.copyMakeBorder(flat, PAD, PAD, PAD, PAD, cv2.BORDER_CONSTANT, value=255)


def _print_px(board: Charuco, ids: np.ndarray) -> np.ndarray:
    """Corners ``ids`` in print pixels (pixel centres at integers): corner 0 sits one square
    in from the print's top-left corner."""
    xy = board.points(ids)[:, :2] / board.square_size + 1.0
    return xy * PX - 0.5 + PAD


def _view(board: Charuco, H: np.ndarray, *, blur: float = 0.8, seed: int = 0
          ) -> tuple[np.ndarray, np.ndarray]:
    """The print seen through homography ``H`` (print px -> image px), blurred and noisy, and
    the true image position of every corner id, shape (N, 2)."""
    image = cv2.warpPerspective(_print(board), H, IMAGE, flags=cv2.INTER_AREA,
                                borderValue=140)
    image = cv2.GaussianBlur(image, (0, 0), blur)
    noise = np.random.default_rng(seed).normal(0.0, 1.5, image.shape)
    image = np.clip(image + noise, 0, 255).astype(np.uint8)
    truth = cv2.perspectiveTransform(_print_px(board, board.point_ids).reshape(-1, 1, 2), H)
    return image, truth.reshape(-1, 2)


def _homography(scale: float, angle_deg: float, shift: tuple[float, float],
                tilt: float = 0.0) -> np.ndarray:
    """Similarity of the print into the image plus a small perspective term ``tilt``."""
    a = np.deg2rad(angle_deg)
    H = np.array([[scale * np.cos(a), -scale * np.sin(a), shift[0]],
                  [scale * np.sin(a), scale * np.cos(a), shift[1]],
                  [tilt, 0.3 * tilt, 1.0]])
    return H


def _check_labels(det: Detection, truth: np.ndarray, tol: float) -> np.ndarray:
    """Every detected corner within ``tol`` px of its own id's truth; the errors."""
    assert det.ok, det.reason
    assert det.ids.dtype == np.int64 and det.corners.shape == (len(det.ids), 2)
    assert np.all(np.diff(det.ids) > 0)
    err = np.linalg.norm(det.corners - truth[det.ids], axis=1)
    assert err.max() < tol, (det.ids[err.argmax()], err.max())
    return err


def test_points_follow_opencv_layout_with_corner_zero_at_origin():
    for legacy in (False, True):
        board = Charuco((7, 6), 0.03, 0.022, "DICT_4X4_50", legacy_pattern=legacy)
        cv_corners = board.opencv_board().getChessboardCorners()
        assert np.allclose(board.points(), cv_corners - cv_corners[0])
    pts = BOARD.points([0, 1, 7, 8], kappa=1.01, nu=0.99)
    s = 0.04 * 1.01
    assert np.allclose(pts, [[0, 0, 0], [s * 0.99, 0, 0], [0, s, 0], [s * 0.99, s, 0]])
    assert np.array_equal(BOARD.point_ids, np.arange(35))
    # square (0, 0), diagonally outside corner 0, is black as on the checkerboard
    assert BOARD.black_squares()[0, 0] and not BOARD.black_squares()[0, 1]


def test_full_view_gives_every_id_at_its_true_position():
    image, truth = _view(BOARD, _homography(1.3, 4.0, (150.0, 80.0), tilt=1e-4))
    det = BOARD.detect(image)
    err = _check_labels(det, truth, 0.3)
    assert np.array_equal(det.ids, BOARD.point_ids)
    assert np.sqrt(np.mean(err ** 2)) < 0.1
    hull = cv2.contourArea(cv2.convexHull(truth.astype(np.float32))) / (IMAGE[0] * IMAGE[1])
    assert not det.ambiguous and det.coverage == pytest.approx(hull, rel=1e-3)
    assert det.sharpness > 0.2 and det.mean_contrast > 150


def test_upside_down_view_keeps_the_ids():
    """The markers fix the origin: a board turned by 180° is read with the same ids."""
    image, truth = _view(BOARD, _homography(1.2, 180.0, (1000.0, 700.0)))
    det = BOARD.detect(image)
    _check_labels(det, truth, 0.3)
    assert len(det.ids) == 35
    # id 0 is now at the lower right of id 34
    assert (det.corners[0] > det.corners[-1]).all()


@pytest.mark.parametrize("shift", [(-250.0, 60.0), (700.0, 500.0), (200.0, -260.0)])
def test_view_cut_at_the_image_border_reads_the_visible_part(shift):
    image, truth = _view(BOARD, _homography(1.5, -3.0, shift))
    det = BOARD.detect(image)
    err = _check_labels(det, truth, 0.3)
    inside = ((truth > 30) & (truth < np.array(IMAGE) - 30)).all(axis=1)
    assert set(det.ids) <= set(np.flatnonzero(inside)) | set(det.ids[err < 0.3])
    assert MIN_CHARUCO_CORNERS <= len(det.ids) < 35
    assert ((det.corners >= 0) & (det.corners < IMAGE)).all()
    # most corners that are well inside the image are read
    assert len(det.ids) >= 0.6 * inside.sum()


def test_legacy_pattern_board_is_read_with_its_flag():
    board = Charuco((6, 6), 0.04, 0.028, "DICT_4X4_50", legacy_pattern=True)
    image, truth = _view(board, _homography(1.3, 10.0, (250.0, 60.0)))
    det = board.detect(image)
    _check_labels(det, truth, 0.3)
    assert len(det.ids) == 25
    wrong = Charuco((6, 6), 0.04, 0.028, "DICT_4X4_50").detect(image)
    assert not wrong.ok and "legacy_pattern true: check squares and legacy_pattern" in wrong.reason


def test_wrong_dictionary_names_the_dictionary_in_view():
    printed = Charuco((8, 6), 0.04, 0.03, "DICT_4X4_50")
    image, _ = _view(printed, _homography(1.3, 0.0, (150.0, 80.0)))
    det = BOARD.detect(image)
    assert not det.ok and det.corners is None
    assert "DICT_5X5_100" in det.reason and "DICT_4X4_50" in det.reason
    assert "squares [8, 6]" in det.reason


def test_checkerboard_config_on_a_charuco_image_says_what_board_is_there():
    image, _ = _view(BOARD, _homography(1.3, 5.0, (150.0, 80.0)))
    det = detect_checkerboard(image, (11, 8))
    assert not det.ok
    assert "ArUco markers of DICT_5X5_50" in det.reason
    assert "squares [8, 6]" in det.reason and "charuco" in det.reason


def test_too_few_corners_says_how_many_and_the_minimum():
    image, truth = _view(BOARD, _homography(1.5, 0.0, (-820.0, -420.0)))
    visible = ((truth > 0) & (truth < IMAGE)).all(axis=1).sum()
    assert 0 < visible < MIN_CHARUCO_CORNERS + 2
    det = BOARD.detect(image)
    assert not det.ok
    assert f"at least {MIN_CHARUCO_CORNERS}" in det.reason and "corners" in det.reason


def test_blank_and_unreadable_images_have_reasons():
    assert "blank" in BOARD.detect(np.full((480, 640), 90, np.uint8)).reason
    assert "empty/corrupt" in BOARD.detect(np.zeros((4, 4), np.float32)).reason
    noise = np.random.default_rng(1).integers(0, 255, (480, 640), dtype=np.uint8)
    assert "no DICT_5X5_100 markers" in BOARD.detect(noise).reason


def test_board_rejects_inconsistent_geometry():
    with pytest.raises(ValueError, match="marker_size"):
        Charuco((8, 6), 0.03, 0.03, "DICT_5X5_100")
    with pytest.raises(ValueError, match="unknown ArUco dictionary"):
        Charuco((8, 6), 0.04, 0.03, "DICT_9X9_7")
    with pytest.raises(ValueError, match="needs 60 markers"):
        Charuco((12, 10), 0.04, 0.03, "DICT_4X4_50")


def test_target_union_parses_both_types_and_builds_the_board():
    old = TargetAdapter.validate_python({"inner_corners": [11, 8], "square_size_m": 0.03})
    assert isinstance(old, CheckerboardTarget)
    assert board_from_target(old) == Checkerboard((11, 8), 0.03)
    doc = {"type": "charuco", "squares": [8, 6], "square_size_m": 0.04,
           "marker_size_m": 0.03, "dictionary": "DICT_5X5_100"}
    parsed = TargetAdapter.validate_python(doc)
    target = TargetAdapter.validate_json(TargetAdapter.dump_json(parsed))
    assert isinstance(target, CharucoTarget) and board_from_target(target) == BOARD
    assert target_from_board(BOARD) == target
    for bad, words in [({**doc, "dictionary": "DICT_5X5_7"}, "unknown ArUco dictionary"),
                       ({**doc, "marker_size_m": 0.05}, "smaller than square_size_m"),
                       ({**doc, "type": "circles"}, "circles"),
                       ({**doc, "inner_corners": [3, 3]}, "Extra inputs")]:
        with pytest.raises(ValidationError, match=words):
            TargetAdapter.validate_python(bad)


@pytest.mark.parametrize("spacing", [9.0, 40.0])
def test_refinement_in_tiles_equals_refinement_on_the_whole_smoothed_image(spacing):
    """``refine_corners`` smooths only a tile around each corner (for speed); the corners
    are those of ``cornerSubPix`` on the whole smoothed image, also for windows next to the
    border (where the smoothing mirrors the image) and on an image smaller than a tile."""
    image, truth = _view(BOARD, _homography(1.5, -3.0, (-250.0, 60.0)))
    inside = ((truth > 2) & (truth < np.array(IMAGE) - 3)).all(axis=1)
    w, h = IMAGE
    edge = [[9.6, 400.3], [w - 10.2, 500.7], [300.4, 9.8], [700.2, h - 10.4]]  # tiles cross it
    start = np.vstack([truth[inside] + np.random.default_rng(4).normal(0.0, 0.4, (inside.sum(),
                                                                               2)), edge])
    small = image[:24, :30].copy()
    start_small = np.array([[12.3, 11.8], [16.2, 12.1]])
    for grey, corners in ((image, start), (small, start_small)):
        half = int(np.clip(0.3 * spacing, 2, 5))
        smooth = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.2)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        whole = cv2.cornerSubPix(smooth, corners.astype(np.float32).reshape(-1, 1, 2),
                                 (half, half), (-1, -1), criteria).reshape(-1, 2)
        moved = np.linalg.norm(whole - corners, axis=1) > 0.6 * half
        whole[moved] = corners[moved]
        np.testing.assert_allclose(refine_corners(grey, corners, spacing), whole, atol=2e-4)
