"""Hand-eye calibration from station poses: one entry point, every method, one result type.

``calibrate_hand_eye`` takes the robot poses (T_base_tcp) and camera observations
(T_cam_target) of the stations, validates them, builds the motion pairs, checks that they
determine the solution, and runs the chosen method:

* ``sm`` — screw motions (Zhao & Liu), exact on noise-free data (``calib.screw``);
* ``tsai``, ``park``, ``horaud``, ``andreff``, ``daniilidis``, ``shah``, ``li`` — OpenCV;
* ``refine`` (default) — SM, then the weighted least-squares refinement of X, Y (and kappa on
  request) from all stations (``calib.refine``), which also reports uncertainty.

(``joint``, the corner-level maximum likelihood of ``calib.joint``, needs the corners, not
only the poses; ``calib.pipeline`` runs it.)

Every method returns the hand-eye *and* the target pose; for methods that only give one of
them, the other is the average of the per-station loop closures.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib import so3
from calib.chain import (
    MotionPairs,
    check_motion_diversity,
    hand_eye_from_station,
    robot_chain,
    target_from_station,
    tool_side_motions,
)
from calib.geometry import check_transforms, make_transform
from calib.options import POSE_METHODS
from calib.peers import OPENCV_HAND_EYE_METHODS, OPENCV_ROBOT_WORLD_METHODS, solve_opencv
from calib.refine import RefineOptions, pose_residuals, refine
from calib.screw import solve_sm

MIN_STATIONS = 3


@dataclass(frozen=True)
class HandEyeResult:
    """Hand-eye estimate with what a user needs to trust it.

    ``hand_eye`` is T_tcp_cam (eye-in-hand) or T_base_cam (eye-to-hand); ``target_pose`` is
    T_base_target or T_tcp_target. ``sigmas`` (from ``refine`` only) holds standard deviations:
    ``hand_eye_rot_rad`` and ``target_pose_rot_rad`` (3,) as small rotations in the frame of the
    transform's first index, ``hand_eye_trans_m`` and ``target_pose_trans_m`` (3,) in that frame,
    and ``kappa``. ``station_residuals`` has shape (n, 2): per-station rotation (rad) and
    translation (m) of the robot pose predicted through the estimate.
    """

    setup: str
    method: str
    hand_eye: np.ndarray
    target_pose: np.ndarray
    kappa: float = 1.0
    sigmas: dict[str, np.ndarray | float] = field(default_factory=dict)
    station_residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    motions_used: int = 0
    motions_skipped: int = 0
    noise: dict[str, float] = field(default_factory=dict)


def validate_stations(T_base_tcp: np.ndarray, T_cam_target: np.ndarray) -> tuple[np.ndarray,
                                                                                  np.ndarray]:
    """Check the station poses at the boundary; return them as float (n, 4, 4) arrays."""
    P = check_transforms(T_base_tcp, "tcp_pose")
    C = check_transforms(T_cam_target, "target_pose")
    if P.shape[0] != C.shape[0]:
        raise ValueError(f"{P.shape[0]} robot poses but {C.shape[0]} camera poses: "
                         "every station needs both")
    if P.shape[0] < MIN_STATIONS:
        raise ValueError(f"need at least {MIN_STATIONS} stations, got {P.shape[0]}")
    return P, C


def average_transform(Ts: np.ndarray) -> np.ndarray:
    """Mean of transforms (n, 4, 4): chordal rotation mean and mean translation, (4, 4)."""
    return make_transform(so3.mean(Ts[:, :3, :3]), Ts[:, :3, 3].mean(axis=0))


def solve_screw(T_base_tcp: np.ndarray, C: np.ndarray, setup: str,
                motions: MotionPairs) -> tuple[np.ndarray, np.ndarray]:
    """X and Y by SM on the tool-side motions; the other unknown from the averaged loop."""
    length = float(np.median(np.linalg.norm(motions.A[:, :3, 3], axis=1))) or 1.0
    Z = solve_sm(motions.A, motions.B, length_scale=length)
    if setup == "eye_in_hand":  # Z = T_tcp_cam
        return Z, average_transform(target_from_station(T_base_tcp, Z, C, setup))
    # Z = T_tcp_target
    return average_transform(hand_eye_from_station(T_base_tcp, Z, C, setup)), Z


def calibrate_hand_eye(T_base_tcp: np.ndarray, T_cam_target: np.ndarray, *,
                       setup: str = "eye_in_hand", method: str = "refine",
                       options: RefineOptions | None = None) -> HandEyeResult:
    """Hand-eye and target pose from station poses.

    Parameters
    ----------
    T_base_tcp : shape (n, 4, 4), robot readings T_base_tcp, metres.
    T_cam_target : shape (n, 4, 4), camera observations T_cam_target, metres.
    setup : ``eye_in_hand`` or ``eye_to_hand``.
    method : one of ``POSE_METHODS``.
    options : ``refine`` only: the expected robot pose noise (starting weights) and whether to
        estimate the board scale κ (camera translations scale with it, Strobl & Hirzinger
        eq. 6; off by default for pose-only data).
    """
    if method not in POSE_METHODS:
        raise ValueError(f"unknown method '{method}': choose one of {', '.join(POSE_METHODS)}")
    options = RefineOptions() if options is None else options
    if options.estimate_kappa and method != "refine":
        raise ValueError("kappa can only be estimated by the 'refine' method")
    T_base_tcp, C = validate_stations(T_base_tcp, T_cam_target)
    motions = tool_side_motions(T_base_tcp, C, setup)
    check_motion_diversity(motions)

    if method in OPENCV_HAND_EYE_METHODS or method in OPENCV_ROBOT_WORLD_METHODS:
        X, Y = solve_opencv(robot_chain(T_base_tcp, setup), C, method)
        if Y is None:
            Y = average_transform(target_from_station(T_base_tcp, X, C, setup))
    else:
        X, Y = solve_screw(T_base_tcp, C, setup, motions)
    common = dict(setup=setup, method=method, motions_used=len(motions.A),
                  motions_skipped=motions.skipped)
    if method != "refine":
        res = pose_residuals(T_base_tcp, C, X, Y, setup)
        return HandEyeResult(hand_eye=X, target_pose=Y, station_residuals=_norms(res), **common)

    fit = refine(T_base_tcp, C, (X, Y), setup, options)
    sd = np.sqrt(np.clip(np.diag(fit.covariance), 0.0, None))
    sigmas: dict[str, np.ndarray | float] = {
        "hand_eye_rot_rad": sd[0:3], "hand_eye_trans_m": sd[3:6],
        "target_pose_rot_rad": sd[6:9], "target_pose_trans_m": sd[9:12]}
    if options.estimate_kappa:
        sigmas["kappa"] = float(sd[12])
    return HandEyeResult(hand_eye=fit.X, target_pose=fit.Y, kappa=fit.kappa, sigmas=sigmas,
                         station_residuals=_norms(fit.residuals),
                         noise={"rot_rad": fit.noise_rot, "trans_m": fit.noise_trans}, **common)


def _norms(res: np.ndarray) -> np.ndarray:
    """Per-station (rotation angle, translation distance) from residual vectors (n, 6)."""
    return np.stack([np.linalg.norm(res[:, :3], axis=1), np.linalg.norm(res[:, 3:], axis=1)], 1)
