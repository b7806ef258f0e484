"""SO(3): cross-product matrices, exp/log and the left Jacobian, vectorised over stacks.

The one place for rotation-vector algebra. Exp and log go through
``scipy.spatial.transform.Rotation``, imported on first use (scipy.spatial takes a fifth of a
second to load, which the geometry and station-set checks do not need); the left Jacobian
(not in scipy) is the closed form

    J_l(φ) = I + (1 - cos θ)/θ² [φ]x + (θ - sin θ)/θ³ [φ]x²,   θ = |φ|

with Taylor series near θ = 0. It is the derivative of a left perturbation:
``exp(φ + dφ) ≈ exp(J_l(φ) dφ) exp(φ)``, so ``d(exp(φ) p)/dφ = -[exp(φ) p]x J_l(φ)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

# Below this rotation angle (rad) the left Jacobian uses its Taylor series.
_SMALL_ANGLE = 1e-4


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` with ``[v]x w = v x w``, shape (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros((*v.shape[:-1], 3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def exp(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors (rad), shape (..., 3) -> (..., 3, 3)."""
    rvec = np.asarray(rvec, dtype=float)
    R = _rotation().from_rotvec(rvec.reshape(-1, 3)).as_matrix()
    return R.reshape(*rvec.shape[:-1], 3, 3)


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (rad, angle in [0, π]) of rotation matrices, (..., 3, 3) -> (..., 3)."""
    R = np.asarray(R, dtype=float)
    rvec = _rotation().from_matrix(R.reshape(-1, 3, 3)).as_rotvec()
    return rvec.reshape(*R.shape[:-2], 3)


def _rotation() -> type[Rotation]:
    from scipy.spatial.transform import Rotation

    return Rotation


def left_jacobian(rvec: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l`` of SO(3) (module docstring), shape (..., 3) -> (..., 3, 3)."""
    rvec = np.asarray(rvec, dtype=float)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(t)) / (t * t))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (t - np.sin(t)) / (t * t * t))
    W = skew(rvec)
    return np.eye(3) + b * W + c * (W @ W)


def left_update(T0: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T0`` (4, 4) moved by ``xi = (δφ, δt)`` (6,): rotation ``exp(δφ) R0``, ``t0 + δt``.

    The local parameters in which the hand-eye solvers (``calib.refine``, ``calib.joint``)
    optimise a transform: a small rotation on the left, in the frame of the transform's
    first index, and a translation in metres in that frame.
    """
    T = np.array(T0, dtype=float)
    T[:3, :3] = exp(xi[:3]) @ T[:3, :3]
    T[:3, 3] = T[:3, 3] + xi[3:6]
    return T
