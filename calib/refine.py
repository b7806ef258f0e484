"""Nonlinear hand-eye refinement from poses: X, Y and optionally the pattern scale kappa.

Model (eye-in-hand form of ``docs/conventions.md``): ``P_i X C_i(kappa) = Y`` for every station,
where ``C_i(kappa)`` is the measured camera pose with its translation scaled by kappa (the
board's true size over its nominal size; Strobl & Hirzinger eq. 6, the function Phi). The robot
pose predicted from the camera, ``Y C_i^-1 X^-1``, is compared with the measured one; rotation
and translation residuals are divided by their noise levels so both are unitless.

Weighting follows Strobl & Hirzinger's optimal hand-eye idea: weights from the expected noise
of each quantity. The caller's noise levels (defaults: UR-class 0.05 deg / 0.25 mm) start the
solve; the rotation and translation noise are then re-estimated from the residuals (variance
components) and the solve repeated, because pose-only data says nothing about the camera's own
pose noise, which adds to the robot's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib import so3
from calib.chain import RobotNoise, robot_from_camera
from calib.geometry import invert
from calib.levmar import solve_dense


@dataclass(frozen=True)
class RefineOptions:
    """Options of :func:`refine`: the starting noise levels (re-estimated from the residuals),
    whether to estimate the board scale κ (eq. 6), and how often to re-weight."""

    noise: RobotNoise = field(default_factory=RobotNoise)
    estimate_kappa: bool = False
    reweight_iterations: int = 3


@dataclass(frozen=True)
class Refinement:
    """Estimates and their covariance.

    ``covariance`` is over ``(dθ_X, dt_X, dθ_Y, dt_Y[, kappa])`` (12 or 13): ``dθ`` are small
    rotations applied on the left (in the frame of the transform's first index, e.g. tcp for
    X = T_tcp_cam), ``dt`` translations in metres in that same frame.
    """

    X: np.ndarray
    Y: np.ndarray
    kappa: float
    covariance: np.ndarray
    noise_rot: float
    noise_trans: float
    residuals: np.ndarray  # shape (n, 6): rotation (rad) and translation (m) per station


def scale_translations(T_cam_target: np.ndarray, kappa: float) -> np.ndarray:
    """Camera poses (n, 4, 4) with their translations times κ: the true-scale poses (eq. 6)."""
    C = np.array(T_cam_target, dtype=float)
    C[..., :3, 3] *= kappa
    return C


def pose_residuals(T_base_tcp: np.ndarray, T_cam_target: np.ndarray, hand_eye: np.ndarray,
                   target_pose: np.ndarray, setup: str) -> np.ndarray:
    """Per-station robot-pose prediction error in the tcp frame, shape (n, 6): rotvec, metres.

    The robot pose predicted from the camera (at true scale) through X and Y,
    :func:`calib.chain.robot_from_camera`, against the reading: ``inv(T_base_tcp) @ T̂_base_tcp``,
    taken in the tcp frame where robot reading noise lives. Identity for perfect data.
    """
    E = invert(T_base_tcp) @ robot_from_camera(T_cam_target, hand_eye, target_pose, setup)
    return np.hstack([so3.log(E[:, :3, :3]), E[:, :3, 3]])


def refine(T_base_tcp: np.ndarray, T_cam_target: np.ndarray, start: tuple[np.ndarray, np.ndarray],
           setup: str, options: RefineOptions) -> Refinement:
    """Least-squares X, Y (and κ) from all stations, started at ``start`` = (X0, Y0).

    Parameters
    ----------
    T_base_tcp : shape (n, 4, 4), robot readings.
    T_cam_target : shape (n, 4, 4), camera poses at nominal board scale.
    start : X0, Y0, shape (4, 4) each, starting values (e.g. from SM).
    setup : ``eye_in_hand`` or ``eye_to_hand``.
    options : starting noise levels, κ estimation, re-weighting.
    """
    X0, Y0 = start
    n = len(T_base_tcp)
    estimate_kappa = options.estimate_kappa
    n_par = 13 if estimate_kappa else 12
    x = np.zeros(n_par)
    if estimate_kappa:
        x[12] = 1.0
    noise_rot, noise_trans = options.noise.rot_rad, options.noise.trans_m
    weights = np.array([1.0 / noise_rot] * 3 + [1.0 / noise_trans] * 3)

    def residuals(p: np.ndarray) -> np.ndarray:
        C = scale_translations(T_cam_target, p[12]) if estimate_kappa else T_cam_target
        return pose_residuals(T_base_tcp, C, so3.left_update(X0, p[0:6]),
                              so3.left_update(Y0, p[6:12]), setup)

    def fun(p: np.ndarray) -> np.ndarray:
        return (residuals(p) * weights).ravel()

    dof = max(6 * n - n_par, 1)
    # Levenberg-Marquardt with a forward-difference Jacobian (calib.levmar; the same minimum
    # as least_squares' MINPACK, without importing scipy.optimize)
    for _ in range(max(options.reweight_iterations, 1)):
        sol = solve_dense(fun, x)
        x = sol.x
        r = sol.residuals.reshape(-1, 6) / weights
        # variance components: each block's mean square, corrected for the fitted parameters
        correction = 6 * n / dof
        noise_rot = max(float(np.sqrt(np.mean(r[:, :3] ** 2) * correction)), 1e-9)
        noise_trans = max(float(np.sqrt(np.mean(r[:, 3:] ** 2) * correction)), 1e-12)
        weights = np.array([1.0 / noise_rot] * 3 + [1.0 / noise_trans] * 3)
    sol = solve_dense(fun, x)
    J = sol.jacobian
    s2 = sol.cost / dof
    covariance = np.linalg.pinv(J.T @ J) * s2
    return Refinement(X=so3.left_update(X0, sol.x[0:6]), Y=so3.left_update(Y0, sol.x[6:12]),
                      kappa=float(sol.x[12]) if estimate_kappa else 1.0, covariance=covariance,
                      noise_rot=noise_rot, noise_trans=noise_trans, residuals=residuals(sol.x))
