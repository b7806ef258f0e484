"""Validation experiments of Zhao & Liu: residuals (eq. 21-22), prediction (23), dot-hit (24)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boards import board_points
from calib.camera import Pinhole
from calib.chain import camera_from_robot
from calib.geometry import make_transform, perturb
from calib.validation import (
    dot_hit,
    leave_one_out,
    motion_residuals,
    reprojection_rms,
)
from mocks.posesim import default_cell, robot_poses, sample_camera_poses
from tests.support.helpers import exact_stations


@pytest.fixture(params=["eye_in_hand", "eye_to_hand"])
def exact(request):
    return exact_stations(request.param, 8, seed=1)


def test_exact_data_has_zero_residuals_and_perfect_predictions(exact):
    cell, P, C = exact
    res = motion_residuals(P, C, cell.hand_eye, setup=cell.setup)
    assert res.n_motions == 28 and res.E_R < 1e-20 and res.E_t < 1e-20
    np.testing.assert_allclose(
        camera_from_robot(P, cell.hand_eye, cell.target_pose, cell.setup), C,
        atol=1e-12)
    loo = leave_one_out(P, C, setup=cell.setup)
    assert loo.stations.tolist() == list(range(8))
    assert loo.rot_rad.max() < 1e-9 and loo.trans_m.max() < 1e-9


def test_residuals_grow_with_a_wrong_hand_eye(exact):
    cell, P, C = exact
    wrong = perturb(cell.hand_eye, np.deg2rad(0.5), 2e-3, np.random.default_rng(2))
    res = motion_residuals(P, C, wrong, setup=cell.setup)
    assert res.E_R > 1e-5 and res.E_t > 1e-6


def test_leave_one_out_sees_robot_noise():
    cell = default_cell("eye_in_hand")
    rng = np.random.default_rng(3)
    C = sample_camera_poses(cell, 12, rng)
    P = perturb(robot_poses(cell, C), np.deg2rad(0.05), 0.25e-3, rng)
    loo = leave_one_out(P, C, held_out=[0, 5])
    assert loo.stations.tolist() == [0, 5]
    # one station's own robot noise dominates its prediction error
    assert (loo.rot_rad < np.deg2rad(0.3)).all() and (loo.trans_m < 3e-3).all()
    assert (loo.trans_m > 1e-5).all()


def test_leave_one_out_marks_undetermined_stations_nan():
    cell = default_cell("eye_in_hand")
    C = sample_camera_poses(cell, 3, np.random.default_rng(4))
    P = robot_poses(cell, C)
    loo = leave_one_out(P[:3], C[:3])  # 2 stations left: a single motion cannot fix X
    assert np.isnan(loo.rot_rad).all()


def test_reprojection_rms_per_station():
    cell = default_cell("eye_in_hand")
    C = sample_camera_poses(cell, 3, np.random.default_rng(5))
    pts = board_points((11, 8), 0.03)
    dist = np.array([-0.1, 0.05, 0.0, 0.0, 0.0])
    image = [Pinhole(cell.K, dist).project(pts @ c[:3, :3].T + c[:3, 3]) for c in C]
    image[1] = image[1] + [0.3, 0.4]
    rms = reprojection_rms(image, [pts] * 3, cell.K, dist, C)
    np.testing.assert_allclose(rms, [0.0, 0.5, 0.0], atol=1e-9)


def test_dot_hit_reconstructs_probe_points():
    cell = default_cell("eye_in_hand")
    rng = np.random.default_rng(6)
    C = sample_camera_poses(cell, 4, rng)
    P = robot_poses(cell, C)
    dots = board_points((11, 8), 0.03)[[0, 10, 44, 87]]
    cam = np.einsum("nij,nj->ni", C[:, :3, :3], dots) + C[:, :3, 3]
    probe = dots @ cell.target_pose[:3, :3].T + cell.target_pose[:3, 3]
    D, err = dot_hit(cam, probe, cell.hand_eye, T_base_tcp=P)
    np.testing.assert_allclose(D, probe, atol=1e-12)
    assert err.max() < 1e-12
    shifted = cell.hand_eye @ make_transform(np.eye(3), [0.0, 0.0, 1e-3])
    _, err = dot_hit(cam, probe, shifted, T_base_tcp=P)
    np.testing.assert_allclose(err, 1e-3, rtol=1e-9)
    with pytest.raises(ValueError, match="eye-in-hand needs the robot reading"):
        dot_hit(cam, probe, cell.hand_eye)


def test_dot_hit_eye_to_hand():
    cell = default_cell("eye_to_hand")
    pts = np.array([[0.1, 0.0, 0.9], [-0.05, 0.02, 1.0]])
    D, err = dot_hit(pts, pts @ cell.hand_eye[:3, :3].T + cell.hand_eye[:3, 3],
                     cell.hand_eye, setup="eye_to_hand")
    assert err.max() < 1e-12 and D.shape == (2, 3)
