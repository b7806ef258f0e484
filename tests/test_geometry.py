import numpy as np
import pytest

from calib.geometry import (
    check_transforms,
    check_ur_pose,
    check_ur_poses,
    invert,
    matrix_from_ur_pose,
    perturb,
    pose_error,
    rotation_angle,
    ur_pose_from_matrix,
)
from tests.support.helpers import random_transforms


def test_ur_pose_round_trip():
    rng = np.random.default_rng(0)
    T = random_transforms(rng, 50)
    np.testing.assert_allclose(matrix_from_ur_pose(ur_pose_from_matrix(T)), T, atol=1e-12)
    pose = ur_pose_from_matrix(T[0])
    assert pose.shape == (6,)
    np.testing.assert_allclose(matrix_from_ur_pose(pose), T[0], atol=1e-12)


def test_ur_pose_tiny_and_half_turn_rotations():
    for rotvec in ([1e-12, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-9], [0.0, np.pi, 0.0]):
        pose = np.array([0.1, 0.2, 0.3, *rotvec])
        T = matrix_from_ur_pose(pose)
        np.testing.assert_allclose(matrix_from_ur_pose(ur_pose_from_matrix(T)), T, atol=1e-12)


def test_invert_composes_to_identity():
    rng = np.random.default_rng(1)
    T = random_transforms(rng, 20, scale=3.0)
    np.testing.assert_allclose(T @ invert(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def test_pose_error_measures_known_offsets():
    T = matrix_from_ur_pose([0.0, 0.0, 0.0, 0.0, 0.0, 0.3])
    U = matrix_from_ur_pose([0.0, 0.004, 0.003, 0.0, 0.0, 0.31])
    dr, dt = pose_error(T, U)
    assert dr == pytest.approx(0.01, abs=1e-12)
    assert dt == pytest.approx(0.005, abs=1e-12)


def test_perturb_has_requested_spread():
    rng = np.random.default_rng(2)
    T = np.broadcast_to(np.eye(4), (20000, 4, 4))
    noisy = perturb(T, 0.001, 0.0005, rng)
    dr, dt = pose_error(noisy, T)
    # |Gaussian| with sigma s has RMS s
    assert np.sqrt(np.mean(dr**2)) == pytest.approx(0.001, rel=0.03)
    assert np.sqrt(np.mean(dt**2)) == pytest.approx(0.0005, rel=0.03)
    assert rotation_angle(noisy[:, :3, :3]).shape == (20000,)


@pytest.mark.parametrize("mutate, message", [
    (lambda T: T.__setitem__((2, 0, 3), np.nan), r"pose\[2\] contains NaN or inf"),
    (lambda T: T.__setitem__((1, 1, 1), np.inf), r"pose\[1\] contains NaN or inf"),
    (lambda T: T.__setitem__((3, 0, 0), 1.2), r"pose\[3\] rotation is not orthonormal"),
    (lambda T: T.__setitem__((0, slice(0, 3), 0), -T[0, :3, 0]), r"pose\[0\].*det"),
    (lambda T: T.__setitem__((4, 3, 0), 0.5), r"pose\[4\] is not a homogeneous transform"),
    (lambda T: T.__setitem__((1, 0, 3), 850.0), r"pose\[1\] translation is 850.0 m.*millimetres"),
])
def test_check_transforms_names_the_problem(mutate, message):
    T = random_transforms(np.random.default_rng(3), 5)
    mutate(T)
    with pytest.raises(ValueError, match=message):
        check_transforms(T, "pose")


def test_check_ur_poses_rejects_bad_shapes_and_values():
    with pytest.raises(ValueError, match="expected"):
        check_ur_poses(np.zeros((3, 5)), "tcp_pose")
    with pytest.raises(ValueError, match=r"tcp_pose\[0\] contains NaN"):
        check_ur_poses([[np.nan, 0, 0, 0, 0, 0]], "tcp_pose")
    T = check_ur_poses([[0.4, 0.1, 0.3, 0.0, 3.1, 0.0]], "tcp_pose")
    assert T.shape == (1, 4, 4)


def test_rotation_vectors_in_degrees_are_refused():
    deg = [[0.4, 0.1, 0.3, 0.0, 0.3, 0.0], [0.4, 0.1, 0.3, 0.0, 177.6, 11.0]]
    with pytest.raises(ValueError, match=r"tcp_pose\[1\] rotation vector has norm 178, more "
                                         r"than π rad: .*radians \(were degrees given\?\)"):
        check_ur_poses(deg, "tcp_pose")
    with pytest.raises(ValueError, match=r"^pose rotation vector has norm 3.16"):
        check_ur_pose([0.4, 0.1, 0.3, 0.0, np.pi + 0.02, 0.0], "pose")
    # A half turn printed with three decimals per component is still radians.
    half_turn = np.round(np.pi * np.array([0.6, 0.8, 0.0]), 3) + np.array([5e-4, 5e-4, 0.0])
    assert np.linalg.norm(half_turn) > np.pi
    assert check_ur_pose([0.4, 0.1, 0.3, *half_turn], "pose").shape == (4, 4)


def test_single_pose_and_joint_checks():
    from calib.geometry import check_joint_positions, check_ur_pose
    assert check_ur_pose([0.4, 0.1, 0.3, 0.0, 3.1, 0.0], "pose").shape == (4, 4)
    with pytest.raises(ValueError, match=r"pose: expected \[x, y, z, rx, ry, rz\], got shape"):
        check_ur_pose([[0.4, 0.1, 0.3, 0.0, 3.1, 0.0]], "pose")
    assert check_joint_positions([0.0, -1.5, 1.5, -1.5, -1.57, 0.0]).shape == (6,)
    with pytest.raises(ValueError, match="q: expected 6 finite joint angles"):
        check_joint_positions([0.0, np.nan, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="were degrees given"):
        check_joint_positions([0.0, -90.0, 90.0, 0, 0, 0])
