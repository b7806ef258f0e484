"""Screw-motion hand-eye solver (SM) of Zhao & Liu, with the exact translation block.

Solves ``A X = X B`` for X from motion pairs (see ``docs/conventions.md`` for how stations become
motions). Each motion is decomposed into its screw (axis direction ``u``, angle ``theta``, axis
point ``c``; eq. 4-6), Chen's constraint (eq. 7-8) is written with quaternions (eq. 9-10) and
stacked into a linear ``6n x 8`` system in ``(q, q')`` with ``q' = t_X q`` (eq. 11-12), whose
two-dimensional null space is resolved with the unit-norm and orthogonality constraints
(eq. 13-17).

Two departures from the paper, both needed for an exact and well-behaved solver:

* The printed translation block ``-U_A q'`` of eq. (11) is not exact. We use the identity
  ``(U_A t_X) q = (q' + u_A q' u_B) / 2`` (``U_A`` projects out ``u_A``; pure quaternions), which
  keeps the system linear and puts the true solution exactly in the null space.
* The axis points ``c`` of A and B use the mean of their two (equal in theory) angles.
* Each motion's rows are scaled by ``sin(theta / 2)``: the axis ``u`` and the point ``c`` of a
  small rotation are ill-conditioned (their noise grows like ``1 / theta``), so unweighted rows
  would let the least informative motions dominate. Translation rows are further divided by a
  length scale so both blocks are unitless.

Quaternions here are scalar-first ``(w, x, y, z)``, internal only.
"""

from __future__ import annotations

import numpy as np

from calib import so3
from calib.geometry import make_transform, rotation_angle


def screw_parameters(T: np.ndarray, theta: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Screw axis of rigid motions (eq. 4-6).

    Parameters
    ----------
    T : shape (n, 4, 4), motions with rotation angles in (0, pi).
    theta : shape (n,), optional rotation angles to use in eq. (6) instead of the motions' own
        (``solve_sm`` passes the mean of the two equal angles of A and B).

    Returns
    -------
    u : shape (n, 3), unit axis directions.
    theta : shape (n,), rotation angles (rad) of ``T``.
    c : shape (n, 3), the axis point closest to the origin (``c . u = 0``), eq. (6).
    d : shape (n,), translation along the axis.
    """
    rotvec = so3.log(T[:, :3, :3])
    angle = np.linalg.norm(rotvec, axis=1)
    u = rotvec / angle[:, None]
    t = T[:, :3, 3]
    d = np.einsum("ij,ij->i", t, u)
    cot = 1.0 / np.tan((angle if theta is None else theta) / 2.0)
    c = (t - d[:, None] * u + cot[:, None] * np.cross(u, t)) / 2.0
    return u, angle, c, d


def _left(p: np.ndarray) -> np.ndarray:
    """Matrices of left multiplication by pure quaternions (0, p): ``L(p) q = p q``, (n, 4, 4)."""
    L = np.zeros((p.shape[0], 4, 4))
    L[:, 0, 1:] = -p
    L[:, 1:, 0] = p
    L[:, 1:, 1:] = so3.skew(p)
    return L


def _right(p: np.ndarray) -> np.ndarray:
    """Matrices of right multiplication by pure quaternions (0, p): ``R(p) q = q p``, (n, 4, 4)."""
    R = _left(p)
    R[:, 1:, 1:] *= -1.0
    return R


def sm_system(A: np.ndarray, B: np.ndarray, *, length_scale: float = 1.0) -> np.ndarray:
    """The weighted linear system of eq. (11)-(12) with the exact translation block.

    Parameters
    ----------
    A, B : shape (n, 4, 4), motion pairs with ``A X = X B`` and rotation angles in (0, pi).
    length_scale : metres; translation rows are divided by it so both blocks are unitless.

    Returns
    -------
    shape (6 n, 8), rows acting on ``(q, q')``.
    """
    # A and B rotate by the same angle (eq. 2 is a similarity); using the mean of the two
    # measured angles in eq. (6) halves the angle noise in the axis points.
    theta = (rotation_angle(A[:, :3, :3]) + rotation_angle(B[:, :3, :3])) / 2.0
    uA, _, cA, _ = screw_parameters(A, theta)
    uB, _, cB, _ = screw_parameters(B, theta)
    cA, cB = cA / length_scale, cB / length_scale
    n = A.shape[0]
    rows = np.zeros((n, 2, 4, 8))
    rows[:, 0, :, :4] = _left(uA) - _right(uB)
    rows[:, 1, :, :4] = _left(cA) - _right(cB)
    rows[:, 1, :, 4:] = -0.5 * (np.eye(4) + _left(uA) @ _right(uB))
    weight = np.sin(theta / 2.0)
    # the scalar (first) row of each quaternion equation is redundant (paper, after eq. 10)
    return (rows[:, :, 1:, :] * weight[:, None, None, None]).reshape(6 * n, 8)


def solve_sm(A: np.ndarray, B: np.ndarray, *, length_scale: float = 1.0) -> np.ndarray:
    """X (4x4) solving ``A X = X B`` by the screw-motion method (eq. 12-17).

    Parameters
    ----------
    A, B : shape (n, 4, 4), n >= 2 motions with non-parallel axes and angles in (0, pi).
    length_scale : typical translation length (m), for conditioning only.
    """
    M = sm_system(A, B, length_scale=length_scale)
    _, _, Vt = np.linalg.svd(M, full_matrices=False)
    v7, v8 = Vt[-2], Vt[-1]
    u1, w1, u2, w2 = v7[:4], v7[4:], v8[:4], v8[4:]
    # q^T q' = 0 as a quadratic form in (l1, l2): a l1^2 + b l1 l2 + c l2^2 = 0 (eq. 15, 17)
    a, b, c = u1 @ w1, u1 @ w2 + u2 @ w1, u2 @ w2
    disc = np.sqrt(max(b * b - 4.0 * a * c, 0.0))
    half = -0.5 * (b + np.copysign(disc, b))
    # the two roots as directions (l1, l2): l1/l2 = half/a and l1/l2 = c/half
    candidates = [np.array([half, a]), np.array([c, half])]
    best = None
    for lam in candidates:
        norm = np.linalg.norm(lam)
        if norm == 0.0:
            continue
        lam = lam / norm
        q = lam[0] * u1 + lam[1] * u2
        # eq. (16): choose the root whose q has the largest norm before normalisation
        if best is None or np.linalg.norm(q) > np.linalg.norm(best[0]):
            best = (q, lam[0] * w1 + lam[1] * w2)
    q, qp = best
    scale = np.linalg.norm(q)
    q, qp = q / scale, qp / scale
    # t_X = q' q^-1 (vector part); for unit q, q^-1 is the conjugate
    t = _quat_mul(qp, q * np.array([1.0, -1.0, -1.0, -1.0]))[1:]
    R = so3.from_quaternion(np.roll(q, -1))  # scalar first -> (x, y, z, w)
    return make_transform(R, t * length_scale)


def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of two scalar-first quaternions, shape (4,)."""
    w1, v1, w2, v2 = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])
