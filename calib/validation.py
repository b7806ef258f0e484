"""How far to trust a calibration: the validation experiments of Zhao & Liu (eq. 21-24).

Pure functions over station data and an estimate; frames as in ``docs/conventions.md``.
Camera observations ``T_cam_target`` passed here must be at the *true* board scale (the
nominal-scale poses of the intrinsic stage with their translations multiplied by κ).

* :func:`motion_residuals` — E_R and E_t (eq. 21-22) over the motion pairs ``A X = X B``;
* :func:`reprojection_rms` — per-station reprojection RMS of given camera poses;
* :func:`leave_one_out` — pose prediction on held-out stations (eq. 23);
* :func:`dot_hit` — probe points reconstructed in the base frame (eq. 24) and their errors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib.camera import Pinhole
from calib.chain import camera_from_robot, robot_chain, station_motions
from calib.geometry import pose_error
from calib.handeye import calibrate_hand_eye


@dataclass(frozen=True)
class MotionResiduals:
    """Eq. (21)-(22) over ``n_motions`` station pairs.

    ``E_R = Σ |R_A R_X - R_X R_B|²_F`` (dimensionless, a sum as in the paper) and
    ``E_t = Σ |(R_A - I) t_X - R_X t_B + t_A|² / Σ |R_X t_B - t_A|²`` (relative).
    """

    E_R: float
    E_t: float
    n_motions: int


@dataclass(frozen=True)
class LeaveOneOut:
    """Eq. (23) prediction errors of each held-out station (input indices ``stations``).

    The hand-eye and target pose are re-estimated by SM (``calibrate_hand_eye(method='sm')``,
    target pose from the loop closures) without the station; its camera pose is then predicted
    from its robot reading alone. ``rot_rad``/``trans_m`` are NaN where the remaining stations
    cannot determine the hand-eye.
    """

    stations: np.ndarray  # shape (k,), int
    rot_rad: np.ndarray  # shape (k,)
    trans_m: np.ndarray  # shape (k,)


def motion_residuals(T_base_tcp: np.ndarray, T_cam_target: np.ndarray, hand_eye: np.ndarray, *,
                     setup: str = "eye_in_hand") -> MotionResiduals:
    """E_R and E_t (eq. 21-22) over the station pairs the hand-eye solvers use.

    Parameters
    ----------
    T_base_tcp : shape (n, 4, 4), robot readings.
    T_cam_target : shape (n, 4, 4), camera observations at true board scale.
    hand_eye : shape (4, 4), X.
    setup : ``eye_in_hand`` or ``eye_to_hand``.

    Notes
    -----
    With ``A`` the robot-chain motion and ``B`` the camera motion of a pair (our ``A X = X B``,
    ``docs/conventions.md``), eq. (3) reads ``(R_A - I) t_X - R_X t_B + t_A = 0``.
    """
    m = station_motions(robot_chain(T_base_tcp, setup), T_cam_target)
    RA, tA, RB, tB = m.A[:, :3, :3], m.A[:, :3, 3], m.B[:, :3, :3], m.B[:, :3, 3]
    RX, tX = hand_eye[:3, :3], hand_eye[:3, 3]
    E_R = float(np.sum((RA @ RX - RX @ RB) ** 2))
    RXtB = tB @ RX.T
    num = np.sum(((RA - np.eye(3)) @ tX - RXtB + tA) ** 2)
    den = np.sum((RXtB - tA) ** 2)
    return MotionResiduals(E_R=E_R, E_t=float(num / den) if den > 0 else float("nan"),
                           n_motions=len(m.A))


def reprojection_rms(image_points: Sequence[np.ndarray], points_target: Sequence[np.ndarray],
                     K: np.ndarray, dist: np.ndarray, T_cam_target: np.ndarray) -> np.ndarray:
    """RMS (norm per corner, pixels) of each station's corners against a projection, (n,).

    Parameters
    ----------
    image_points : n arrays, shape (N_i, 2), detected corners.
    points_target : n arrays, shape (N_i, 3), the same corners in the target frame (true
        geometry, e.g. ``board_points(..., kappa=κ, nu=ν)``).
    K : shape (3, 3); dist : shape (5,).
    T_cam_target : shape (n, 4, 4), camera poses to test (observed or predicted).
    """
    out = np.empty(len(image_points))
    for k, (m, p, C) in enumerate(zip(image_points, points_target, T_cam_target, strict=True)):
        uv = Pinhole(K, dist).project(np.asarray(p) @ C[:3, :3].T + C[:3, 3])
        out[k] = np.sqrt(np.mean(np.sum((uv - np.asarray(m)) ** 2, axis=1)))
    return out


def leave_one_out(T_base_tcp: np.ndarray, T_cam_target: np.ndarray, *,
                  setup: str = "eye_in_hand",
                  held_out: Sequence[int] | None = None) -> LeaveOneOut:
    """Pose-prediction error of each held-out station, calibrating without it (eq. 23).

    The held-out camera pose is predicted from its robot reading alone,
    ``inv(X) inv(P_i) Y`` (:func:`calib.chain.camera_from_robot`). Eq. (23) predicts from the
    first station's camera pose, ``Â_i = X B_i⁻¹ X⁻¹ A_1``; the estimated target pose is used
    instead, which averages over all stations rather than trusting one.

    Parameters
    ----------
    T_base_tcp, T_cam_target : shape (n, 4, 4), at true board scale.
    setup : ``eye_in_hand`` or ``eye_to_hand``.
    held_out : station indices to hold out in turn (default: all).
    """
    n = len(T_base_tcp)
    stations = np.arange(n) if held_out is None else np.asarray(held_out, dtype=int)
    rot, trans = np.full(len(stations), np.nan), np.full(len(stations), np.nan)
    for k, i in enumerate(stations):
        rest = np.delete(np.arange(n), i)
        try:
            fit = calibrate_hand_eye(T_base_tcp[rest], T_cam_target[rest], setup=setup,
                                     method="sm")
        except ValueError:
            continue
        pred = camera_from_robot(T_base_tcp[i], fit.hand_eye, fit.target_pose, setup)
        rot[k], trans[k] = pose_error(pred, T_cam_target[i])
    return LeaveOneOut(stations=stations, rot_rad=rot, trans_m=trans)


def dot_hit(points_cam: np.ndarray, probe_base: np.ndarray, hand_eye: np.ndarray, *,
            T_base_tcp: np.ndarray | None = None,
            setup: str = "eye_in_hand") -> tuple[np.ndarray, np.ndarray]:
    """Target points reconstructed in the base frame (eq. 24) and their distance to the probe.

    Eq. (24), ``D_r = C⁻¹ X D_c`` with ``C⁻¹`` = T_base_tcp: eye-in-hand the point seen at
    ``points_cam`` from the station with reading ``T_base_tcp`` is at ``T_base_tcp X D_c``;
    eye-to-hand (X = T_base_cam) at ``X D_c`` and ``T_base_tcp`` is not needed.

    Parameters
    ----------
    points_cam : shape (n, 3), the points in the camera frame (e.g. ``C_i p`` at true scale).
    probe_base : shape (n, 3), the same points touched with the robot's probe, base frame.
    hand_eye : shape (4, 4), X.
    T_base_tcp : shape (n, 4, 4), eye-in-hand only: reading of the station that saw each point.

    Returns
    -------
    reconstructed : shape (n, 3), base frame, metres.
    errors : shape (n,), ``|probe - reconstructed|``, metres.
    """
    D_c = np.asarray(points_cam, dtype=float)
    D = D_c @ hand_eye[:3, :3].T + hand_eye[:3, 3]
    if setup == "eye_in_hand":
        if T_base_tcp is None:
            raise ValueError("dot_hit: eye-in-hand needs the robot reading of each point's station")
        T = np.asarray(T_base_tcp, dtype=float)
        D = np.einsum("nij,nj->ni", T[:, :3, :3], D) + T[:, :3, 3]
    elif setup != "eye_to_hand":
        raise ValueError(f"unknown setup '{setup}': choose eye_in_hand or eye_to_hand")
    return D, np.linalg.norm(np.asarray(probe_base, dtype=float) - D, axis=1)
