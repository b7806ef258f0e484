"""Checkerboard geometry and detection: accuracy, canonical origin, rejection reasons."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.boards import board_points, detect_checkerboard, order_corners
from calib.geometry import make_transform
from mocks.render import RenderParams, render_board
from mocks.scene import MockScene, camera_pose_for_tcp, default_scene, sample_station_poses
from tests.support.helpers import OPENCV_LEFT

LEFT_IMAGES = sorted(OPENCV_LEFT.glob("left*.jpg"))
SCENE = default_scene()
CLEAN = RenderParams.from_scene(SCENE, image_noise=0.0, blur_px=0.0)
ROLL_180 = make_transform(np.diag([-1.0, -1.0, 1.0]), np.zeros(3))


def _start_view() -> np.ndarray:
    return camera_pose_for_tcp(SCENE, SCENE.start_pose())


def _projected(T: np.ndarray, scene: MockScene = SCENE) -> np.ndarray:
    uv, _ = cv2.projectPoints(scene.true_board_points(), cv2.Rodrigues(T[:3, :3])[0], T[:3, 3],
                              scene.camera.k_matrix, scene.camera.dist_coeffs)
    return uv.reshape(-1, 2)


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(((a - b) ** 2).sum(axis=1).mean()))


def _outside_square_grey(grey: np.ndarray, corners: np.ndarray, inner_corners: tuple[int, int],
                         at: tuple[float, float]) -> float:
    """Mean grey of a small patch at grid position ``at`` (corner units) via a homography."""
    cols, rows = inner_corners
    j, i = np.mgrid[0:rows, 0:cols]
    H, _ = cv2.findHomography(np.stack([i.ravel(), j.ravel()], 1).astype(float), corners)
    offs = np.array([[dx, dy] for dx in (-0.07, 0, 0.07) for dy in (-0.07, 0, 0.07)])
    uv = cv2.perspectiveTransform((np.array(at) + offs)[None].astype(float), H)[0]
    return float(np.mean([grey[round(v), round(u)] for u, v in uv]))


def _check_origin_rule(grey: np.ndarray, corners: np.ndarray,
                       inner_corners: tuple[int, int]) -> None:
    """Square (0, 0) (outside corner 0) is black, the opposite outer square white, and x → y
    turns clockwise on screen (board seen from the front). Samples sit 0.2 squares outside
    the corners because the printed OpenCV sample board has narrow edge squares."""
    cols, rows = inner_corners
    origin = _outside_square_grey(grey, corners, inner_corners, (-0.2, -0.2))
    opposite = _outside_square_grey(grey, corners, inner_corners, (cols - 0.8, rows - 0.8))
    assert origin + 60 < opposite
    x_dir = corners[cols - 1] - corners[0]
    y_dir = corners[(rows - 1) * cols] - corners[0]
    assert x_dir[0] * y_dir[1] - x_dir[1] * y_dir[0] > 0


def test_board_points_order_and_scale():
    pts = board_points((4, 3), 0.03, kappa=1.01, nu=0.99)
    assert pts.shape == (12, 3)
    assert np.allclose(pts[1], [0.03 * 1.01 * 0.99, 0, 0])
    assert np.allclose(pts[4], [0, 0.03 * 1.01, 0])
    assert np.allclose(pts[2 * 4 + 3], [3 * 0.03 * 1.01 * 0.99, 2 * 0.03 * 1.01, 0])
    assert np.allclose(board_points((4, 3), 0.03)[:, 2], 0)


@pytest.mark.parametrize(("inner", "size"), [((1, 5), 0.03), ((4, 3.5), 0.03), ((4, 3), -1.0)])
def test_board_points_rejects_bad_arguments(inner, size):
    with pytest.raises(ValueError):
        board_points(inner, size)


@pytest.mark.parametrize("path", LEFT_IMAGES, ids=lambda p: p.name)
def test_real_images_detect_with_consistent_origin(path):
    bgr = cv2.imread(str(path))
    det = detect_checkerboard(bgr, (9, 6))
    assert det.ok, det.reason
    assert det.corners.shape == (54, 2) and det.corners.dtype == np.float64
    assert not det.ambiguous
    assert det.sharpness > 0.2 and 0.05 < det.coverage < 0.5 and det.mean_contrast > 100
    _check_origin_rule(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), det.corners, (9, 6))


def test_real_image_count():
    assert len(LEFT_IMAGES) == 13


@pytest.mark.parametrize("roll", [False, True], ids=["upright", "rolled_180"])
def test_origin_follows_the_board_when_the_camera_rolls(roll):
    T = ROLL_180 @ _start_view() if roll else _start_view()
    img = render_board(CLEAN, T)
    det = detect_checkerboard(img, (11, 8))
    assert det.ok, det.reason
    assert _rms(det.corners, _projected(T)) < 0.06
    _check_origin_rule(img, det.corners, (11, 8))


def test_origin_follows_the_board_across_tilted_views():
    views = camera_pose_for_tcp(SCENE, sample_station_poses(SCENE, 4, np.random.default_rng(5)))
    for T in views:
        img = render_board(CLEAN, T)
        det = detect_checkerboard(img, (11, 8))
        assert det.ok, det.reason
        assert _rms(det.corners, _projected(T)) < 0.06


def test_order_corners_undoes_any_detector_order():
    T = _projected(ROLL_180 @ _start_view()).reshape(8, 11, 2)
    img = render_board(CLEAN, ROLL_180 @ _start_view())
    truth = T.reshape(-1, 2)
    for grid in (T, T[::-1, ::-1], T[:, ::-1], T[::-1]):
        for pts in (grid.reshape(-1, 2), grid.transpose(1, 0, 2).reshape(-1, 2)):
            ordered, ambiguous, contrast = order_corners(img, pts, (11, 8))
            assert np.array_equal(ordered, truth) and not ambiguous and contrast > 150


def test_transposed_inner_corners_give_a_valid_target_frame():
    img = render_board(CLEAN, _start_view())
    det = detect_checkerboard(img, (8, 11))
    assert det.ok, det.reason
    _check_origin_rule(img, det.corners, (8, 11))
    dist = np.linalg.norm(det.corners[:, None] - _projected(_start_view())[None], axis=-1)
    assert dist.min(axis=1).max() < 0.2


def test_symmetric_board_is_flagged_ambiguous():
    scene = MockScene.model_validate({**SCENE.model_dump(), "target": {
        "inner_corners": (10, 8), "square_size_m": 0.03}})
    params = RenderParams.from_scene(scene, image_noise=0.0, blur_px=0.0)
    for roll in (np.eye(4), ROLL_180):
        T = roll @ camera_pose_for_tcp(scene, scene.start_pose())
        det = detect_checkerboard(render_board(params, T), (10, 8))
        assert det.ok and det.ambiguous
        # canonical choice: x axis to the image right, whichever physical end that is
        assert det.corners[9, 0] > det.corners[0, 0]
        truth = _projected(T, scene)
        assert min(_rms(det.corners, truth), _rms(det.corners, truth[::-1])) < 0.06


def test_wrong_inner_corners_fail_with_a_reason():
    det = detect_checkerboard(render_board(CLEAN, _start_view()), (10, 8))
    assert not det.ok and det.corners is None
    assert "10x8" in det.reason and "inner_corners" in det.reason


def test_real_board_with_wrong_inner_corners_fails():
    det = detect_checkerboard(cv2.imread(str(LEFT_IMAGES[0])), (8, 6))
    assert not det.ok and det.corners is None and "8x6" in det.reason


def test_partly_visible_board_is_reported():
    T = _start_view()
    T[0, 3] += 0.2
    det = detect_checkerboard(render_board(CLEAN, T), (11, 8))
    assert not det.ok
    assert det.reason.startswith("only part of the board is visible")


def test_blurred_image_is_rejected():
    img = render_board(RenderParams.from_scene(SCENE, blur_px=6.0), _start_view())
    det = detect_checkerboard(img, (11, 8))
    assert not det.ok and det.reason.startswith("image too blurred")
    assert det.sharpness == pytest.approx(1 / (6.0 * np.sqrt(2 * np.pi)), rel=0.15)


@pytest.mark.parametrize(("image", "match"), [
    (np.zeros((0, 0), np.uint8), "empty/corrupt"),
    (np.zeros((480, 640), np.float64), "uint8"),
    (None, "expected an array"),
    (np.zeros((4, 480, 640, 3), np.uint8), "shape"),
    (np.zeros((480, 640), np.uint8), "blank"),
    (np.full((480, 640, 3), 255, np.uint8), "blank"),
])
def test_unusable_images_give_a_reason_not_an_exception(image, match):
    det = detect_checkerboard(image, (9, 6))
    assert not det.ok and det.corners is None and match in det.reason


def test_board_not_found_in_clutter():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (480, 640), dtype=np.uint8), (0, 0), 1.0)
    det = detect_checkerboard(img, (9, 6))
    assert not det.ok and det.reason.startswith("board not found")


def test_quality_metrics_on_a_clean_render():
    det = detect_checkerboard(render_board(CLEAN, _start_view()), (11, 8))
    assert det.ok and det.reason is None
    assert det.mean_contrast == pytest.approx(200, abs=5)
    assert det.sharpness > 0.3
    cols, rows = 11, 8
    s = SCENE.target.square_size_m * SCENE.target.kappa
    d = SCENE.working_distance()
    area = ((cols - 1) * s * SCENE.target.nu * 1400 / d) * ((rows - 1) * s * 1401.5 / d)
    assert det.coverage == pytest.approx(area / (1280 * 1024), rel=0.05)


def test_inner_corners_is_validated():
    with pytest.raises(ValueError, match="inner_corners"):
        detect_checkerboard(np.zeros((10, 10), np.uint8), (9,))
