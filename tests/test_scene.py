"""Mock scene: JSON round trip, validation messages, true geometry, station sampling."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from calib.geometry import invert, make_transform, pose_error, rotation_angle
from mocks.scene import (
    MockScene,
    StationSpread,
    camera_pose_for_tcp,
    default_scene,
    load_scene,
    sample_station_poses,
    tcp_pose_for_camera,
)


def _scene_dict(**changes: object) -> dict:
    d = json.loads(default_scene().model_dump_json())
    d.update(changes)
    return d


def _eye_to_hand_scene() -> MockScene:
    """Camera fixed 1.2 m above the table looking down; board held 12 cm below the flange."""
    T_base_cam = make_transform(np.diag([1.0, -1.0, -1.0]), [0.5, 0.0, 1.2])
    T_tcp_target = make_transform(np.eye(3), [-0.15, -0.105, 0.12])
    return MockScene.model_validate(_scene_dict(
        setup="eye_to_hand", hand_eye=T_base_cam.tolist(), target_pose=T_tcp_target.tolist()))


def test_json_round_trip(tmp_path):
    scene = default_scene()
    path = tmp_path / "scene.json"
    path.write_text(scene.model_dump_json(indent=2))
    assert load_scene(path) == scene


def test_default_scene_is_realistic():
    scene = default_scene()
    assert scene.camera.image_size == (1280, 1024)
    assert (scene.target.inner_corners[0] + scene.target.inner_corners[1]) % 2 == 1
    assert 0.08 < np.linalg.norm(scene.hand_eye_matrix[:3, 3]) < 0.12
    assert 0.45 < scene.target_pose_matrix[0, 3] + 0.15 < 0.55


@pytest.mark.parametrize(("changes", "match"), [
    ({"setup": "eye_on_hand"}, "setup"),
    ({"colour": "red"}, "colour"),
    ({"hand_eye": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}, "det"),
    ({"hand_eye": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, "hand_eye"),
    ({"target_pose": make_transform(np.eye(3), [500.0, 0, 0]).tolist()}, "millimetres"),
    ({"camera": {"image_size": [1280, 1024], "K": [[1, 0], [0, 1]]}}, "3x3"),
    ({"camera": {"image_size": [1280, 1024], "K": np.eye(3).tolist(), "dist": [0.1] * 3}},
     "4, 5, 8, 12 or 14"),
    ({"target": {"inner_corners": [11, 8], "square_size_m": 30}}, "square_size_m"),
    ({"target": {"inner_corners": [1, 8], "square_size_m": 0.03}}, "inner_corners"),
    ({"target": {"type": "charuco", "inner_corners": [11, 8], "square_size_m": 0.03}}, "type"),
    ({"start_tcp_pose": [0.1, 0.2, 0.3]}, "start_tcp_pose"),
])
def test_validation_errors_name_the_problem(changes, match):
    with pytest.raises(ValidationError, match=match):
        MockScene.model_validate(_scene_dict(**changes))


@pytest.mark.parametrize("make", [default_scene, _eye_to_hand_scene])
def test_camera_and_tcp_poses_are_inverse(make):
    scene = make()
    rng = np.random.default_rng(3)
    T_base_tcp = sample_station_poses(scene, 5, rng)
    T_cam_target = camera_pose_for_tcp(scene, T_base_tcp)
    rot, trans = pose_error(tcp_pose_for_camera(scene, T_cam_target), T_base_tcp)
    assert rot.max() < 1e-9 and trans.max() < 1e-9


def test_camera_pose_closes_the_loop_eye_in_hand():
    scene = default_scene()
    T_base_tcp = scene.start_pose()
    T = T_base_tcp @ scene.hand_eye_matrix @ camera_pose_for_tcp(scene, T_base_tcp)
    assert np.allclose(T, scene.target_pose_matrix, atol=1e-12)


def test_camera_pose_closes_the_loop_eye_to_hand():
    scene = _eye_to_hand_scene()
    T_base_tcp = scene.start_pose()
    T = invert(T_base_tcp) @ scene.hand_eye_matrix @ camera_pose_for_tcp(scene, T_base_tcp)
    assert np.allclose(T, scene.target_pose_matrix, atol=1e-12)


@pytest.mark.parametrize("make", [default_scene, _eye_to_hand_scene])
def test_default_start_pose_looks_straight_at_the_target_centre(make):
    scene = make()
    T = camera_pose_for_tcp(scene, scene.start_pose())
    centre_cam = T[:3, :3] @ scene.pattern_centre() + T[:3, 3]
    assert np.allclose(centre_cam[:2], 0.0, atol=1e-9)
    assert centre_cam[2] == pytest.approx(scene.working_distance())
    assert rotation_angle(T[:3, :3]) < 1e-9


def test_explicit_start_pose_wins():
    pose = [0.4, 0.1, 0.5, 3.1, 0.0, 0.0]
    scene = MockScene.model_validate(_scene_dict(start_tcp_pose=pose))
    assert np.allclose(scene.start_pose()[:3, 3], pose[:3])


@pytest.mark.parametrize("make", [default_scene, _eye_to_hand_scene])
def test_sampled_stations_keep_the_board_in_view(make):
    scene = make()
    T_cam_target = camera_pose_for_tcp(scene, sample_station_poses(scene, 30,
                                                                   np.random.default_rng(0)))
    cols, rows = scene.target.inner_corners
    s = scene.target.square_size_m * scene.target.kappa
    sx = s * scene.target.nu
    plate = np.array([[-2 * sx, -2 * s, 0], [(cols + 1) * sx, -2 * s, 0],
                      [(cols + 1) * sx, (rows + 1) * s, 0], [-2 * sx, (rows + 1) * s, 0]])
    w, h = scene.camera.image_size
    tilts, rolls = [], []
    for T in T_cam_target:
        uv, _ = cv2.projectPoints(plate, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3],
                                  scene.camera.k_matrix, scene.camera.dist_coeffs)
        uv = uv.reshape(-1, 2)
        assert (uv > 0.03 * h).all() and (uv < [w - 0.03 * h, h - 0.03 * h]).all()
        tilts.append(np.degrees(np.arccos(T[2, 2])))
        x_axis = T[:2, 0]
        rolls.append(np.degrees(np.arctan2(x_axis[1], x_axis[0])))
    assert max(tilts) <= 35.0 + 1e-9 and max(tilts) > 20.0
    assert np.ptp(rolls) > 180.0
    assert (T_cam_target[:, 2, 3] > 0).all()


def test_cut_stations_cut_the_board_near_an_image_corner():
    """Every other station cuts the board: some corners outside the image, >= 12 inside, one
    within 15 % of the smaller image side of an image corner; the rest show it whole."""
    scene = default_scene()
    T_cam_target = camera_pose_for_tcp(scene, sample_station_poses(
        scene, 10, np.random.default_rng(3), StationSpread(cut_fraction=0.5)))
    w, h = scene.camera.image_size
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]])
    cut = []
    for T in T_cam_target:
        uv, _ = cv2.projectPoints(scene.true_board_points(), cv2.Rodrigues(T[:3, :3])[0],
                                  T[:3, 3], scene.camera.k_matrix, scene.camera.dist_coeffs)
        uv = uv.reshape(-1, 2)
        inside = ((uv >= 0) & (uv <= [w, h])).all(axis=1)
        cut.append(not inside.all())
        if cut[-1]:
            assert inside.sum() >= 12
            assert np.linalg.norm(uv[inside][:, None] - corners, axis=-1).min() < 0.15 * h
    assert cut == [False, True] * 5
