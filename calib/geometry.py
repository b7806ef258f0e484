"""Rigid transforms: UR pose vectors, 4x4 matrices, inverses, errors and validation.

Conventions are in ``docs/conventions.md``: ``T_a_b`` maps frame-b coordinates to frame a,
UR poses are ``[x, y, z, rx, ry, rz]`` with a rotation vector, metres and radians.
Rotations go through :mod:`calib.so3`. Functions accept a single transform
or a stack: shapes ``(..., 6)`` and ``(..., 4, 4)``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from calib import so3

#: Largest translation we accept as metres; anything beyond is almost surely millimetres.
MAX_TRANSLATION_M = 20.0
#: Largest rotation-vector norm we accept as radians: π plus a margin for rounded printouts
#: (three decimals per component shift the norm by < 1e-3). A larger norm is degrees.
MAX_ROTVEC_NORM_RAD = np.pi + 0.01


def matrix_from_ur_pose(pose: np.ndarray) -> np.ndarray:
    """4x4 transform(s) from UR pose vector(s), shape (..., 6) -> (..., 4, 4)."""
    pose = np.asarray(pose, dtype=float)
    flat = pose.reshape(-1, 6)
    T = np.zeros((flat.shape[0], 4, 4))
    T[:, :3, :3] = so3.exp(flat[:, 3:])
    T[:, :3, 3] = flat[:, :3]
    T[:, 3, 3] = 1.0
    return T.reshape(*pose.shape[:-1], 4, 4)


def ur_pose_from_matrix(T: np.ndarray) -> np.ndarray:
    """UR pose vector(s) from 4x4 transform(s), shape (..., 4, 4) -> (..., 6)."""
    T = np.asarray(T, dtype=float)
    flat = T.reshape(-1, 4, 4)
    out = np.empty((flat.shape[0], 6))
    out[:, :3] = flat[:, :3, 3]
    out[:, 3:] = so3.log(flat[:, :3, :3])
    return out.reshape(*T.shape[:-2], 6)


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotation(s) (..., 3, 3) and translation(s) (..., 3) into (..., 4, 4)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s), shape (..., 4, 4), using R^T (exact for proper R)."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_transform(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in radians of rotation matrices, shape (..., 3, 3) -> (...)."""
    return np.linalg.norm(so3.log(R), axis=-1)


class PoseError(NamedTuple):
    """How far apart two poses are: rotation angle (rad) and translation distance (m)."""

    rot_rad: float
    trans_m: float


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle (rad) and translation distance (m) between transforms, shapes (..., 4, 4).

    The one tolerance helper for comparing poses: angle of ``R_est^T R_true`` and
    ``|t_est - t_true|``.
    """
    T_est = np.asarray(T_est, dtype=float)
    T_true = np.asarray(T_true, dtype=float)
    dR = np.swapaxes(T_est[..., :3, :3], -1, -2) @ T_true[..., :3, :3]
    return rotation_angle(dR), np.linalg.norm(T_est[..., :3, 3] - T_true[..., :3, 3], axis=-1)


def perturb(T: np.ndarray, rot_sigma: float, trans_sigma: float,
            rng: np.random.Generator) -> np.ndarray:
    """Transform(s) (..., 4, 4) with random rotation and translation noise applied on the right.

    The noise rotation has a Gaussian angle (sigma ``rot_sigma`` rad) about a uniformly random
    axis and the translation a Gaussian length (sigma ``trans_sigma`` m) in a uniformly random
    direction, as in Strobl & Hirzinger section IV-A.
    """
    T = np.asarray(T, dtype=float)
    n = int(np.prod(T.shape[:-2]))
    axes = _unit_vectors(rng, n)
    dirs = _unit_vectors(rng, n)
    dR = so3.exp(axes * rng.normal(0.0, rot_sigma, (n, 1)))
    dt = dirs * rng.normal(0.0, trans_sigma, (n, 1))
    noise = make_transform(dR, dt).reshape(*T.shape[:-2], 4, 4)
    return T @ noise


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def check_transforms(T: np.ndarray, name: str, *, max_translation: float = MAX_TRANSLATION_M,
                     tol: float = 1e-6) -> np.ndarray:
    """Validate a stack of rigid transforms at a public boundary; return it as float (N, 4, 4).

    Raises ``ValueError`` naming ``name``, the first offending index and the problem: wrong
    shape, NaN/inf, a rotation that is not orthonormal with det +1, a bottom row that is not
    [0 0 0 1], or a translation beyond ``max_translation`` metres (likely millimetres).
    """
    T = np.asarray(T, dtype=float)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected 4x4 transforms, got shape {T.shape}")
    bad = ~np.isfinite(T).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{name}[{int(np.argmax(bad))}] contains NaN or inf")
    if not np.allclose(T[:, 3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        i = int(np.argmax(~np.isclose(T[:, 3], [0, 0, 0, 1], atol=tol).all(axis=1)))
        raise ValueError(f"{name}[{i}] is not a homogeneous transform (bottom row != [0 0 0 1])")
    R = T[:, :3, :3]
    ortho = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (ortho > tol) | (det < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{name}[{i}] rotation is not orthonormal with det +1 "
            f"(|R^T R - I| = {ortho[i]:.2e}, det = {det[i]:.6f})")
    _check_translation_units(T[:, :3, 3], name, max_translation)
    return T


def check_ur_poses(poses: np.ndarray, name: str, *,
                   max_translation: float = MAX_TRANSLATION_M) -> np.ndarray:
    """Validate UR pose vectors (N, 6) and return them as 4x4 transforms (N, 4, 4).

    Refuses NaN/inf, a rotation vector longer than π (+ a rounding margin, i.e. degrees)
    and translations beyond ``max_translation`` metres (millimetres), naming the index.
    """
    return matrix_from_ur_pose(check_ur_vectors(poses, name, max_translation=max_translation))


def check_ur_vectors(poses: np.ndarray, name: str, *,
                     max_translation: float = MAX_TRANSLATION_M) -> np.ndarray:
    """``check_ur_poses`` without making the transforms: the vectors (N, 6) as floats (a
    station file of 20,000 poses is checked in milliseconds instead of seconds)."""
    poses = np.asarray(poses, dtype=float)
    if poses.ndim == 1:
        poses = poses[None]
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise ValueError(f"{name}: expected [x, y, z, rx, ry, rz] vectors, got shape {poses.shape}")
    bad = ~np.isfinite(poses).all(axis=1)
    if bad.any():
        raise ValueError(f"{name}[{int(np.argmax(bad))}] contains NaN or inf")
    angle = np.linalg.norm(poses[:, 3:], axis=1)
    if (angle > MAX_ROTVEC_NORM_RAD).any():
        i = int(np.argmax(angle))
        raise ValueError(
            f"{name}[{i}] rotation vector has norm {angle[i]:.3g}, more than π rad: "
            "rotations must be rotation vectors in radians (were degrees given?)")
    _check_translation_units(poses[:, :3], name, max_translation)
    return poses


def check_ur_pose(pose: np.ndarray, name: str) -> np.ndarray:
    """Validate one UR pose vector, shape (6,); return it as a 4x4 transform."""
    return matrix_from_ur_pose(check_ur_vector(pose, name))


def check_ur_vector(pose: np.ndarray, name: str) -> np.ndarray:
    """``check_ur_pose`` without making the transform: the vector (6,) as floats."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,):
        raise ValueError(f"{name}: expected [x, y, z, rx, ry, rz], got shape {pose.shape}")
    try:
        return check_ur_vectors(pose, name)[0]
    except ValueError as exc:  # one pose: name it without the stack index
        raise ValueError(str(exc).replace(f"{name}[0]", name, 1)) from None


def check_joint_positions(q: np.ndarray, name: str = "q") -> np.ndarray:
    """Validate six joint angles in radians; return them as float, shape (6,)."""
    angles = np.asarray(q, dtype=float)
    if angles.shape != (6,) or not np.isfinite(angles).all():
        raise ValueError(f"{name}: expected 6 finite joint angles in radians, got {q!r}")
    if np.abs(angles).max() > 2.0 * np.pi:
        raise ValueError(f"{name}: joint angles beyond ±2π rad: were degrees given?")
    return angles


def _check_translation_units(t: np.ndarray, name: str, max_translation: float) -> None:
    """Translations ``t`` (N, 3) within ``max_translation`` metres, or ValueError."""
    dist = np.linalg.norm(t, axis=1)
    if (dist > max_translation).any():
        i = int(np.argmax(dist))
        raise ValueError(
            f"{name}[{i}] translation is {dist[i]:.1f} m, more than {max_translation:g} m: "
            "poses must be in metres (were millimetres given?)")
