"""SO(3): cross-product matrices, exp/log, quaternions, the mean and the left Jacobian,
vectorised over stacks.

The one place for rotation algebra in ``calib``. Exp and log are closed forms on numpy arrays
(Rodrigues; the quaternion by Shepperd's method): the solvers call them hundreds of times on
a few dozen matrices, where ``scipy.spatial.transform.Rotation``'s per-call overhead (50-100
µs) was a fifth of a calibration's solve. The mean is the chordal L2 mean of the unit
quaternions (the eigenvector of largest eigenvalue of ``Σ q qᵀ``; Markley, Cheng, Crassidis
and Oshman, "Averaging Quaternions", J. Guidance Control Dyn. 30(4):1193, 2007), the same as scipy's
``Rotation.mean``. The left Jacobian is the closed form

    J_l(φ) = I + (1 - cos θ)/θ² [φ]x + (θ - sin θ)/θ³ [φ]x²,   θ = |φ|

with Taylor series near θ = 0. It is the derivative of a left perturbation:
``exp(φ + dφ) ≈ exp(J_l(φ) dφ) exp(φ)``, so ``d(exp(φ) p)/dφ = -[exp(φ) p]x J_l(φ)``.
"""

from __future__ import annotations

import numpy as np

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
    """Rotation matrices of rotation vectors (rad), shape (..., 3) -> (..., 3, 3).

    Rodrigues' formula ``R = I + (sin θ / θ) [φ]x + ((1 - cos θ) / θ²) [φ]x²``, with Taylor
    series below ``_SMALL_ANGLE``.
    """
    rvec = np.asarray(rvec, dtype=float)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(t)) / (t * t))
    W = skew(rvec)
    return np.eye(3) + a * W + b * (W @ W)


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (rad, angle in [0, π]) of rotation matrices, (..., 3, 3) -> (..., 3).

    Through the unit quaternion (Shepperd's method: from the largest of its four squared
    components, accurate at every angle, also near π), then ``φ = 2 atan2(|v|, w) v / |v|``
    with ``w ≥ 0``.
    """
    R = np.asarray(R, dtype=float)
    q = _quaternion(R.reshape(-1, 3, 3))
    q *= np.where(q[:, 3:] < 0.0, -1.0, 1.0)
    v, w = q[:, :3], q[:, 3]
    norm_v = np.linalg.norm(v, axis=1)
    angle = 2.0 * np.arctan2(norm_v, w)
    small = norm_v < 1e-12
    # φ = angle / |v| v; for tiny |v| angle / |v| -> 2 / w
    scale = np.where(small, 2.0 / np.where(small, w, 1.0), angle / np.where(small, 1.0, norm_v))
    return (v * scale[:, None]).reshape(*R.shape[:-2], 3)


def quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w) of rotation matrices, (..., 3, 3) -> (..., 4); the sign
    is either one (``q`` and ``-q`` are the same rotation)."""
    R = np.asarray(R, dtype=float)
    return _quaternion(R.reshape(-1, 3, 3)).reshape(*R.shape[:-2], 4)


def from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions (x, y, z, w), normalised first, (..., 4) -> (..., 3, 3).
    """
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz, ww = x * x, y * y, z * z, w * w
    xy, xz, xw, yz, yw, zw = x * y, x * z, x * w, y * z, y * w, z * w
    return np.stack([
        np.stack([xx - yy - zz + ww, 2.0 * (xy - zw), 2.0 * (xz + yw)], axis=-1),
        np.stack([2.0 * (xy + zw), -xx + yy - zz + ww, 2.0 * (yz - xw)], axis=-1),
        np.stack([2.0 * (xz - yw), 2.0 * (yz + xw), -xx - yy + zz + ww], axis=-1)], axis=-2)


def mean(R: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotation matrices (n, 3, 3) -> (3, 3) (module docstring): the
    rotation whose unit quaternion maximises ``Σ (qᵀ q_i)²``, sign-free."""
    q = quaternion(R).reshape(-1, 4)
    _, vectors = np.linalg.eigh(q.T @ q / len(q))
    return from_quaternion(vectors[:, -1])


def _quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w) of rotation matrices (n, 3, 3), Shepperd's method."""
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]],
                    axis=1)
    choice = np.argmax(diag, axis=1)
    q = np.empty((len(R), 4))
    for k in range(4):
        m = choice == k
        if not m.any():
            continue
        r = R[m]
        if k == 3:  # w largest
            q[m] = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0],
                             r[:, 1, 0] - r[:, 0, 1], 1.0 + diag[m, 3]], axis=1)
            continue
        i, j, h = k, (k + 1) % 3, (k + 2) % 3
        qm = np.empty((int(m.sum()), 4))
        qm[:, i] = 1.0 - diag[m, 3] + 2.0 * r[:, i, i]
        qm[:, j] = r[:, j, i] + r[:, i, j]
        qm[:, h] = r[:, h, i] + r[:, i, h]
        qm[:, 3] = r[:, h, j] - r[:, j, h]
        q[m] = qm
    return q / np.linalg.norm(q, axis=1, keepdims=True)


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
