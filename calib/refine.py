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

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calib import so3
from calib.geometry import invert


@dataclass(frozen=True)
class Refinement:
    """Estimates and their covariance.

    ``covariance`` is over ``(dθ_X, dt_X, dθ_Y, dt_Y[, kappa])`` (12 or 13): ``dθ`` are small
    rotations applied on the left (in the frame of the transform's first index, e.g. tcp for
    X = tcp_T_cam), ``dt`` translations in metres in that same frame.
    """

    X: np.ndarray
    Y: np.ndarray
    kappa: float
    covariance: np.ndarray
    noise_rot: float
    noise_trans: float
    residuals: np.ndarray  # shape (n, 6): rotation (rad) and translation (m) per station


def _compose(params: np.ndarray, X0: np.ndarray, Y0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return so3.left_update(X0, params[0:6]), so3.left_update(Y0, params[6:12])


def pose_residuals(P: np.ndarray, C: np.ndarray, X: np.ndarray, Y: np.ndarray,
                   kappa: float = 1.0, *, inverted: bool = False) -> np.ndarray:
    """Per-station robot-pose prediction error in the tcp frame, shape (n, 6): rotvec, metres.

    The predicted robot chain pose is ``Y inv(C_i(kappa)) inv(X)``. The error is taken in the
    tcp frame, where robot reading noise lives: ``inv(P_i) @ prediction`` when ``P`` is
    base_T_tcp (eye-in-hand), ``P_i @ inv(prediction)`` when ``P`` is its inverse
    (``inverted``, eye-to-hand). Identity for perfect data.
    """
    Ck = C.copy()
    Ck[:, :3, 3] *= kappa
    predicted = Y @ invert(Ck) @ invert(X)
    E = P @ invert(predicted) if inverted else invert(P) @ predicted
    return np.hstack([so3.log(E[:, :3, :3]), E[:, :3, 3]])


def refine(P: np.ndarray, C: np.ndarray, X0: np.ndarray, Y0: np.ndarray, *,
           noise_rot: float, noise_trans: float, estimate_kappa: bool = False,
           inverted: bool = False, reweight_iterations: int = 3) -> Refinement:
    """Least-squares X, Y (and kappa) from all stations, started at ``X0``, ``Y0``.

    Parameters
    ----------
    P : shape (n, 4, 4), robot chain poses.
    C : shape (n, 4, 4), cam_T_target at nominal board scale.
    X0, Y0 : shape (4, 4), starting values (e.g. from SM).
    noise_rot, noise_trans : initial noise levels (rad, m) of the pose residuals.
    estimate_kappa : also estimate the board scale kappa (eq. 6).
    inverted : ``P`` is tcp_T_base (eye-to-hand); see ``pose_residuals``.
    """
    n_par = 13 if estimate_kappa else 12
    x = np.zeros(n_par)
    if estimate_kappa:
        x[12] = 1.0
    weights = np.array([1.0 / noise_rot] * 3 + [1.0 / noise_trans] * 3)

    def fun(p: np.ndarray) -> np.ndarray:
        X, Y = _compose(p, X0, Y0)
        kappa = p[12] if estimate_kappa else 1.0
        return (pose_residuals(P, C, X, Y, kappa, inverted=inverted) * weights).ravel()

    dof = max(6 * P.shape[0] - n_par, 1)
    for _ in range(max(reweight_iterations, 1)):
        sol = least_squares(fun, x, method="lm", x_scale="jac", jac="3-point")
        x = sol.x
        r = sol.fun.reshape(-1, 6) / weights
        # variance components: each block's mean square, corrected for the fitted parameters
        correction = 6 * P.shape[0] / dof
        noise_rot = max(float(np.sqrt(np.mean(r[:, :3] ** 2) * correction)), 1e-9)
        noise_trans = max(float(np.sqrt(np.mean(r[:, 3:] ** 2) * correction)), 1e-12)
        weights = np.array([1.0 / noise_rot] * 3 + [1.0 / noise_trans] * 3)
    sol = least_squares(fun, x, method="lm", x_scale="jac", jac="3-point")
    J = sol.jac
    s2 = float(sol.fun @ sol.fun) / dof
    covariance = np.linalg.pinv(J.T @ J) * s2
    X, Y = _compose(sol.x, X0, Y0)
    kappa = float(sol.x[12]) if estimate_kappa else 1.0
    return Refinement(X=X, Y=Y, kappa=kappa, covariance=covariance, noise_rot=noise_rot,
                      noise_trans=noise_trans,
                      residuals=pose_residuals(P, C, X, Y, kappa, inverted=inverted))
