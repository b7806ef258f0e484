"""A simulated arm with systematic kinematic errors (UR5e DH offsets in the mock scene), and the
honesty of the reported uncertainty on it (issue 8, part 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib import pose_error, ur_pose_from_matrix
from mocks import ur_kinematics as kin
from mocks.devices import MockRobot
from mocks.scene import Kinematics, load_scene, sample_station_poses, true_tcp_pose

SCENE = Path(__file__).resolve().parents[1] / "mocks" / "scenes" / "ur5e_kinematic_errors.json"


def test_zero_offsets_are_the_nominal_arm():
    q = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.4])
    assert np.allclose(kin.fk_matrix(q, kin.DHOffsets()), kin.fk_matrix(q), atol=1e-15)
    T = kin.fk_matrix(q)
    assert np.allclose(kin.kinematic_error(T, kin.DHOffsets()), np.eye(4), atol=1e-9)


def test_scene_offsets_give_errors_of_a_real_arm_that_depend_on_the_pose():
    scene = load_scene(SCENE)
    P = sample_station_poses(scene, 8, np.random.default_rng(2))
    rot, trans = pose_error(P, true_tcp_pose(scene, P))
    # a few 0.01 deg / 0.1 mm per joint add up to about 0.1 deg / 1 mm at the tool
    assert np.all(rot > np.deg2rad(0.005)) and np.all(rot < np.deg2rad(0.3))
    assert np.all(trans > 0.02e-3) and np.all(trans < 2e-3)
    assert np.ptp(trans) > 0.1e-3  # systematic, but not the same offset everywhere


def test_mock_robot_reports_the_commanded_pose_while_the_camera_sees_the_true_one():
    scene = load_scene(SCENE).model_copy(update={"noise": load_scene(SCENE).noise.model_copy(
        update={"robot_rot_deg": 0.0, "robot_trans_mm": 0.0})})
    robot = MockRobot(scene)
    robot.connect()
    target = sample_station_poses(scene, 1, np.random.default_rng(4))[0]
    for _ in range(2):  # the same error at every visit: systematic, not noise
        robot.move_linear(ur_pose_from_matrix(target))
        assert np.allclose(robot.tcp_pose(), ur_pose_from_matrix(target), atol=1e-12)
        assert np.allclose(robot.true_pose, true_tcp_pose(scene, target), atol=1e-9)
        robot.move_linear(ur_pose_from_matrix(scene.start_pose()))


def test_offsets_are_validated():
    with pytest.raises(ValueError, match="within"):
        Kinematics(dh_theta_deg=[2.0, 0, 0, 0, 0, 0])


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("kinematic_errors", [True, False], ids=["kinematic-errors", "control"])
def test_reported_sigma_matches_the_monte_carlo_spread(kinematic_errors):
    """30 simulated calibrations of 20 stations (``benchmarks.uncertainty``): the hand-eye
    errors are the size the reported 1σ says (RMS of error / σ within 0.8-1.25) and the σ is
    never far below the fold jackknife (>= 0.7)."""
    from benchmarks.uncertainty import monte_carlo, ratios

    scene = load_scene(SCENE)
    if not kinematic_errors:
        scene = scene.model_copy(update={"kinematics": None})
    r = ratios(monte_carlo(scene, seeds=30))
    for block in ("rot", "trans"):
        assert 0.8 <= r[f"z_sigma_{block}"] <= 1.25, r
        assert r[f"sigma_over_jk_{block}"] >= 0.7, r
