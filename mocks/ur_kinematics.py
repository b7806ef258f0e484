"""UR5e forward and numerical inverse kinematics for the controller emulator.

Standard Denavit-Hartenberg parameters published by Universal Robots for the UR5e
(``T_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``), no tool offset: the emulated TCP is the
flange, as on a controller with a zero TCP set. Poses follow ``docs/conventions.md``
(``[x, y, z, rx, ry, rz]``, T_base_tcp, metres and radians).

``DHOffsets`` give the simulated arm systematic kinematic errors: its true DH table differs from
the nominal one its controller computes poses with (``kinematic_error``).

The inverse is numerical (damped least squares on the geometric Jacobian) rather than the closed
form: the emulator only needs the solution nearest a seed (the current joints), which is what the
real controller's ``get_inverse_kin(x, qnear)`` returns too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib import matrix_from_ur_pose, ur_pose_from_matrix

#: UR5e DH parameters (metres, radians).
DH_A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
DH_D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])

#: A comfortable start configuration (radians): arm up and bent, tool pointing down.
HOME_Q = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


@dataclass(frozen=True)
class DHOffsets:
    """Differences of an arm's true DH parameters from the nominal table, each shape (6,).

    ``theta`` (rad) adds to the joint angle (a zero offset), ``d``, ``a`` (m) and ``alpha``
    (rad) to the link parameters: the systematic errors a real arm's controller does not know
    (tenths of a millimetre, hundredths of a degree on a UR), which bend every reading of a
    configuration the same way.
    """

    theta: np.ndarray = field(default_factory=lambda: np.zeros(6))
    d: np.ndarray = field(default_factory=lambda: np.zeros(6))
    a: np.ndarray = field(default_factory=lambda: np.zeros(6))
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(6))


def _frames(q: np.ndarray, offsets: DHOffsets | None = None) -> list[np.ndarray]:
    """T_base_i for i = 0..6 (base, then each link frame), each shape (4, 4)."""
    o = offsets or DHOffsets()
    T = np.eye(4)
    out = [T]
    for theta, d, a, alpha in zip(q + o.theta, DH_D + o.d, DH_A + o.a, DH_ALPHA + o.alpha,
                                  strict=True):
        ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
        link = np.array([[ct, -st * ca, st * sa, a * ct],
                         [st, ct * ca, -ct * sa, a * st],
                         [0.0, sa, ca, d],
                         [0.0, 0.0, 0.0, 1.0]])
        T = T @ link
        out.append(T)
    return out


def fk_matrix(q: np.ndarray, offsets: DHOffsets | None = None) -> np.ndarray:
    """T_base_tcp, shape (4, 4), for joint angles ``q`` shape (6,) (of the arm with
    ``offsets`` from the nominal DH table, default none)."""
    return _frames(np.asarray(q, dtype=float), offsets)[-1]


def kinematic_error(T_base_tcp: np.ndarray, offsets: DHOffsets,
                    q_seed: np.ndarray = HOME_Q) -> np.ndarray:
    """T_tcp_truetcp of an arm with ``offsets`` commanded to T_base_tcp ``T_base_tcp`` (4, 4).

    The controller solves the nominal inverse kinematics and reports the nominal forward
    kinematics of the joints it reached, while the flange is where the true parameters put
    it: ``inv(fk(q)) @ fk(q, offsets)`` with ``q = ik(T_base_tcp)``. Raises ``ValueError``
    beyond the UR5e's reach.
    """
    q = ik(ur_pose_from_matrix(T_base_tcp), q_seed, iterations=500)
    if q is None:
        raise ValueError("pose beyond the reach of the UR5e model: its kinematic error is "
                         "undefined")
    return np.linalg.inv(fk_matrix(q)) @ fk_matrix(q, offsets)


def fk_pose(q: np.ndarray) -> np.ndarray:
    """T_base_tcp as a UR pose vector, shape (6,), for joint angles shape (6,)."""
    return ur_pose_from_matrix(fk_matrix(q))


def jacobian(q: np.ndarray) -> np.ndarray:
    """Geometric Jacobian in the base frame, shape (6, 6): rows vx vy vz wx wy wz."""
    frames = _frames(np.asarray(q, dtype=float))
    p_end = frames[-1][:3, 3]
    J = np.empty((6, 6))
    for i in range(6):
        z = frames[i][:3, 2]
        J[:3, i] = np.cross(z, p_end - frames[i][:3, 3])
        J[3:, i] = z
    return J


def pose_twist_error(T_target: np.ndarray, T_actual: np.ndarray) -> np.ndarray:
    """Error (dx, dy, dz, drx, dry, drz) from actual to target in the base frame, shape (6,)."""
    dR = T_target[:3, :3] @ T_actual[:3, :3].T
    return np.concatenate([T_target[:3, 3] - T_actual[:3, 3],
                           Rotation.from_matrix(dR).as_rotvec()])


def ik(pose: np.ndarray, q_seed: np.ndarray, *, iterations: int = 100,
       damping: float = 1e-3) -> np.ndarray | None:
    """Joint angles (6,) reaching UR pose ``pose`` (6,) nearest ``q_seed``, or None if unreachable.

    Damped least squares (Levenberg-Marquardt style) on the geometric Jacobian; converged when
    every error component is below 1e-10; accepted if below 1e-6 (m or rad) after ``iterations``.
    A target on the other side of the base than the seed's TCP (the iteration would pass the
    shoulder singularity and wander) is tried again from the seed with its base joint turned
    toward the target.
    """
    T_target = matrix_from_ur_pose(pose)
    q_seed = np.asarray(q_seed, dtype=float)
    q = _dls(T_target, q_seed, iterations, damping)
    if q is None:
        p_seed, p_target = fk_matrix(q_seed)[:3, 3], T_target[:3, 3]
        turned = q_seed.copy()
        turned[0] += (np.arctan2(p_target[1], p_target[0])
                      - np.arctan2(p_seed[1], p_seed[0]))
        q = _dls(T_target, turned, iterations, damping)
    return q


def _dls(T_target: np.ndarray, q_seed: np.ndarray, iterations: int,
         damping: float) -> np.ndarray | None:
    """``ik``'s damped least squares from one seed."""
    q = q_seed.copy()
    for _ in range(iterations):
        err = pose_twist_error(T_target, fk_matrix(q))
        if float(np.abs(err).max()) < 1e-10:
            return q
        J = jacobian(q)
        step = J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(6), err)
        q = q + step
    err = pose_twist_error(T_target, fk_matrix(q))
    return q if float(np.abs(err).max()) < 1e-6 else None
