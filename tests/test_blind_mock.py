"""The blind mock: a simulated cell that reveals only what a real one does, and refuses any
move outside its safety box with a protective stop, counted (issue 17, item 7)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib import (
    board_from_target,
    make_transform,
    matrix_from_ur_pose,
    pose_error,
    ur_pose_from_matrix,
)
from drivers import registry
from drivers.base import GroundTruthSource
from drivers.errors import ProtectiveStopError
from mocks.blindcells import (
    BOX_HALF_M,
    CornerCell,
    box_draws,
    box_poses,
    random_blind_scene,
    readings_hand_eye,
)
from mocks.camera import MockCamera
from mocks.devices import BlindMockRobot, MockRobot
from mocks.scene import default_scene


def _opened(scene):
    robot = MockRobot.from_url("mock://", config=scene)
    robot.connect()
    return robot


def test_blind_scene_describes_only_what_a_user_configures():
    scene = random_blind_scene(0, "eye_in_hand")
    hints = registry.describe_cell("mock://", scene)
    assert hints.setup == "eye_in_hand"
    assert hints.target == scene.nominal_target()
    assert hints.hand_eye is None and hints.K is None and hints.dist is None
    robot = _opened(scene)
    assert isinstance(robot, BlindMockRobot)
    assert not isinstance(robot, GroundTruthSource)
    # the informed mock still knows its scene and its truth
    informed = registry.describe_cell("mock://", default_scene())
    assert informed.hand_eye is not None and informed.K is not None
    assert isinstance(_opened(default_scene()), GroundTruthSource)


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
def test_move_outside_the_box_is_a_counted_protective_stop(setup):
    scene = random_blind_scene(1, setup)
    robot = _opened(scene)
    start = robot.tcp_pose()
    inside = start.copy()
    inside[2] += 0.05
    robot.move_linear(inside)
    assert robot.refused_moves == 0
    outside = start.copy()
    outside[0] += BOX_HALF_M + 0.05
    with pytest.raises(ProtectiveStopError, match="safety box"):
        robot.move_linear(outside)
    assert robot.refused_moves == 1
    assert robot.status().protective_stop
    assert np.allclose(robot.tcp_pose()[:3], inside[:3], atol=1e-3)  # not moved


def test_eye_in_hand_camera_outside_the_box_is_refused():
    scene = random_blind_scene(2, "eye_in_hand")
    robot = _opened(scene)
    P0 = matrix_from_ur_pose(robot.tcp_pose())
    cam = (P0 @ scene.hand_eye_matrix)[:3, 3]
    lo = np.array(scene.workspace.lo)
    # put the tcp just inside the box wall nearest the camera's side so the camera leaves it
    axis = int(np.argmax(np.abs(cam - P0[:3, 3])))
    sign = np.sign(cam[axis] - P0[:3, 3][axis])
    P = P0.copy()
    wall = scene.workspace.hi[axis] if sign > 0 else lo[axis]
    P[axis, 3] = wall - sign * 0.005
    assert scene.workspace.contains(P[:3, 3])
    with pytest.raises(ProtectiveStopError, match="camera"):
        robot.move_linear(ur_pose_from_matrix(P))
    assert robot.refused_moves == 1


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
def test_random_blind_cells_show_the_board_at_the_start(setup):
    for seed in (3, 4):
        scene = random_blind_scene(seed, setup)
        f = scene.camera.k_matrix[0, 0]
        hfov = np.degrees(2 * np.arctan(scene.camera.image_size[0] / 2 / f))
        assert 50 <= hfov <= 90
        assert abs(scene.camera.dist_coeffs[0]) <= 0.3
        offset = np.linalg.norm((scene.hand_eye_matrix if setup == "eye_in_hand"
                                 else scene.target_pose_matrix)[:3, 3])
        assert 0.05 <= offset <= 0.20
        robot = _opened(scene)
        camera = MockCamera.from_url("mock://", robot=robot)
        camera.open()
        assert board_from_target(scene.nominal_target()).detect(camera.grab()).ok


def test_corner_cell_counts_refusals_and_reports_lost_boards():
    scene = random_blind_scene(5, "eye_in_hand")
    cell = CornerCell(scene)
    shot = cell.shoot(cell.start())
    assert shot.corners is not None and len(shot.corners) == len(shot.ids)
    away = cell.start() @ make_transform(np.eye(3), [0.0, 0.0, -0.0])
    away[:3, :3] = away[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # camera turned away
    assert cell.shoot(away).reason is not None
    far = cell.start().copy()
    far[0, 3] += 1.0
    with pytest.raises(ValueError, match="safety box"):
        cell.shoot(far)
    assert cell.refused == 1


@pytest.mark.slow  # 1,000 poses of numerical inverse kinematics, about 25 s
def test_readings_hand_eye_is_what_the_readings_see():
    """Eye-to-hand cell 1: the arm's kinematic error that is the same over the box (mostly a
    base-side turn) moves the camera the readings see by about 1 mm from the physical one;
    an arm without kinematic errors sees the physical camera."""
    scene = random_blind_scene(1, "eye_to_hand")
    X, X_r = scene.hand_eye_matrix, readings_hand_eye(scene)
    assert 0.3e-3 < np.linalg.norm(X_r[:3, 3] - X[:3, 3]) < 3e-3
    exact = scene.model_copy(update={"kinematics": None})
    assert np.array_equal(readings_hand_eye(exact), X)
    assert np.array_equal(readings_hand_eye(exact, scale=True), X)


@pytest.mark.slow  # 1,015 poses of numerical inverse kinematics
def test_readings_hand_eye_over_given_poses():
    """Eye-in-hand cell 6: over 15 poses within a few degrees and centimetres of the start,
    the readings see a hand-eye more than 0.03° from the one they see over the box (the arm's
    kinematic errors differ between the two regions); over the box's own poses, the box's;
    ``box_draws`` gives those poses, in order."""
    scene = random_blind_scene(6, "eye_in_hand")
    X_box = readings_hand_eye(scene, scale=True)
    rng = np.random.default_rng(0)
    near = np.stack([scene.start_pose() @ make_transform(Rotation.from_rotvec(
        rng.normal(0.0, np.deg2rad(8.0), 3)).as_matrix(), rng.normal(0.0, 0.03, 3))
        for _ in range(15)])
    rot, _ = pose_error(readings_hand_eye(scene, scale=True, poses=near), X_box)
    assert np.degrees(rot) > 0.03
    assert np.allclose(readings_hand_eye(scene, scale=True, poses=box_poses(scene)), X_box)
    # box_draws: the box's draws in order, those beyond the arm's reach included
    box = box_poses(scene)
    kept = [P for P in box_draws(scene, 30) if any(np.array_equal(P, Q) for Q in box[:30])]
    assert len(kept) >= 20 and np.array_equal(np.stack(kept), box[:len(kept)])


@pytest.mark.slow  # 1,000 poses of numerical inverse kinematics (the box drawn once)
def test_readings_hand_eye_with_a_common_scale_of_the_readings():
    """Eye-to-hand cell 11 (camera 1.2 m from the base): the readings' translations are
    about 0.02 % long; the hand-eye in their units moves by a few tenths of a millimetre
    from the rigid fit's, its rotation hardly."""
    scene = random_blind_scene(11, "eye_to_hand")
    X_r, X_s = readings_hand_eye(scene), readings_hand_eye(scene, scale=True)
    assert 0.1e-3 < np.linalg.norm(X_s[:3, 3] - X_r[:3, 3]) < 1e-3
    assert np.allclose(X_s[:3, :3], X_r[:3, :3], atol=1e-5)
