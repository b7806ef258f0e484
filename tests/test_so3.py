"""calib.so3: cross products, exp/log against scipy, and the left Jacobian against finite
differences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib import so3

RNG = np.random.default_rng(3)
# generic angles, a tiny one (Taylor branch) and one just below a half turn
ROTVECS = np.concatenate([RNG.normal(size=(5, 3)), [[3e-6, -1e-6, 2e-6], [0.0, 0.0, 0.0],
                                                   [0.0, 3.1, 0.0]]])


def test_skew_is_the_cross_product():
    v, w = RNG.normal(size=(4, 3)), RNG.normal(size=(4, 3))
    assert np.allclose(np.einsum("nij,nj->ni", so3.skew(v), w), np.cross(v, w))
    assert np.allclose(so3.skew(v), -np.swapaxes(so3.skew(v), -1, -2))


def test_exp_and_log_are_inverse_and_agree_with_scipy():
    R = so3.exp(ROTVECS)
    assert R.shape == (len(ROTVECS), 3, 3)
    assert np.allclose(R, Rotation.from_rotvec(ROTVECS).as_matrix(), atol=1e-15)
    assert np.allclose(so3.exp(so3.log(R)), R, atol=1e-14)
    assert so3.exp(ROTVECS[0]).shape == (3, 3) and so3.log(R[0]).shape == (3,)
    assert so3.exp(ROTVECS.reshape(2, 4, 3)).shape == (2, 4, 3, 3)


@pytest.mark.parametrize("k", range(len(ROTVECS)))
def test_left_jacobian_matches_finite_differences(k):
    """exp(φ + h e_j) exp(φ)ᵀ = exp(h J_l(φ) e_j) + O(h²): central differences of the log."""
    phi, h = ROTVECS[k], 1e-6
    R0 = so3.exp(phi)
    numeric = np.column_stack([
        (so3.log(so3.exp(phi + h * e) @ R0.T) - so3.log(so3.exp(phi - h * e) @ R0.T)) / (2 * h)
        for e in np.eye(3)])
    assert np.allclose(so3.left_jacobian(phi), numeric, atol=1e-8)


def test_left_jacobian_gives_the_derivative_of_a_rotated_point():
    """d(exp(φ) p)/dφ = -[exp(φ) p]x J_l(φ), the form the projection Jacobians use."""
    phi, p, h = ROTVECS[1], np.array([0.3, -0.2, 1.1]), 1e-6
    numeric = np.column_stack([(so3.exp(phi + h * e) @ p - so3.exp(phi - h * e) @ p) / (2 * h)
                               for e in np.eye(3)])
    analytic = -so3.skew(so3.exp(phi) @ p) @ so3.left_jacobian(phi)
    assert np.allclose(analytic, numeric, atol=1e-8)
    stacked = so3.left_jacobian(ROTVECS)
    assert stacked.shape == (len(ROTVECS), 3, 3)
    assert np.allclose(stacked[-2], np.eye(3))


def test_left_update_rotates_on_the_left_and_adds_the_translation():
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = so3.exp(ROTVECS[0]), [0.1, 0.2, 0.3]
    xi = np.array([0.01, -0.02, 0.03, 0.001, 0.002, -0.003])
    T = so3.left_update(T0, xi)
    assert np.allclose(T[:3, :3], so3.exp(xi[:3]) @ T0[:3, :3])
    assert np.allclose(T[:3, 3], T0[:3, 3] + xi[3:]) and np.allclose(T[3], [0, 0, 0, 1])
    assert np.allclose(so3.left_update(T0, np.zeros(6)), T0)


def test_quaternions_agree_with_scipy_either_way():
    """``quaternion`` and ``from_quaternion`` are inverse, and match scipy's (x, y, z, w)
    convention up to the sign of q; ``from_quaternion`` normalises its input."""
    R = so3.exp(ROTVECS)
    q = so3.quaternion(R)
    assert q.shape == (len(ROTVECS), 4) and so3.quaternion(R[0]).shape == (4,)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    reference = Rotation.from_matrix(R).as_quat()
    assert np.allclose(np.abs(np.sum(q * reference, axis=1)), 1.0, atol=1e-15)
    assert np.allclose(so3.from_quaternion(q), R, atol=1e-15)
    raw = RNG.normal(size=(6, 4)) * 3.0  # not unit
    assert np.allclose(so3.from_quaternion(raw), Rotation.from_quat(raw).as_matrix(),
                       atol=1e-15)
    assert so3.from_quaternion(raw.reshape(2, 3, 4)).shape == (2, 3, 3, 3)


@pytest.mark.parametrize("spread", [0.05, 0.8, 2.5])
def test_mean_is_scipys_chordal_mean(spread):
    """The chordal L2 mean of clustered and of widely spread rotations, against scipy's
    ``Rotation.mean``; the order of the rotations does not matter, and a tight cluster's
    mean lies near its centre."""
    rng = np.random.default_rng(11)
    centre = so3.exp(np.array([0.4, -1.2, 2.0]))
    R = so3.exp(rng.normal(0.0, spread, (9, 3))) @ centre
    M = so3.mean(R)
    assert M.shape == (3, 3)
    assert np.allclose(M @ M.T, np.eye(3), atol=1e-14) and np.isclose(np.linalg.det(M), 1.0)
    assert np.allclose(M, Rotation.from_matrix(R).mean().as_matrix(), atol=1e-13)
    assert np.allclose(so3.mean(R[::-1]), M, atol=1e-13)
    if spread < 0.1:
        assert np.linalg.norm(so3.log(M.T @ centre)) < spread
