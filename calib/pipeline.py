"""From images (or detected corners) and robot poses to a result a user can trust.

One entry point, :func:`calibrate_stations`, for the CLI and the service (``product.md``,
"Pipeline")::

    detect corners (calib.target)   a bad image becomes a rejected station, never an abort
      -> intrinsics with ν (Method #1, eq. 5; skipped when intrinsics are given)
      -> [no robot poses: intrinsics-only result]
      -> symmetric boards: one physical target origin in every image, from the robot motions
      -> hand-eye: SM, then the eq. (6) refinement of X, Y, κ (``calibrate_hand_eye``, ``refine``)
         [ν by Method #2 on request, ``calib.nu``]
      -> joint maximum likelihood over corners and robot poses (``calib.joint``; the default)
      -> validation (``calib.validation``)

With ``method`` ``refine`` the result is that of the pose-level refinement (κ estimated, no
joint stage); with one of the other hand-eye methods, the hand-eye comes from that method on
the per-image camera poses of the intrinsic stage (κ = 1, no joint stage).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.camera import Pinhole, solve_pnp
from calib.chain import (
    DEFAULT_ROBOT_NOISE_ROT_RAD,
    DEFAULT_ROBOT_NOISE_TRANS_M,
    RobotNoise,
    camera_from_robot,
    check_setup,
    robot_chain,
)
from calib.geometry import check_ur_poses, invert, make_transform, rotation_angle
from calib.handeye import POSE_METHODS, calibrate_hand_eye
from calib.intrinsics import MIN_IMAGES, IntrinsicsOptions, calibrate_intrinsics
from calib.joint import (
    OUTLIER_SIGMA,
    CellParameters,
    CornerStations,
    JointOptions,
    solve_joint,
)
from calib.nu import NuSearch, nu_from_extrinsics
from calib.refine import RefineOptions, scale_translations
from calib.target import Board, Detection, board_points, detect_checkerboard
from calib.validation import (
    leave_one_out,
    motion_residuals,
    reprojection_rms,
)

#: Calibration methods: the pose-level hand-eye solvers, and ``joint`` (the default), the
#: maximum likelihood over all corners and robot poses started from ``refine``.
METHODS = (*POSE_METHODS, "joint")
#: Ways to estimate ν: ``images`` (Method #1, eq. 5) or ``extrinsics`` (Method #2).
NU_METHODS = ("images", "extrinsics")
#: Leave-one-out validation holds out at most this many stations (evenly spread).
MAX_HELD_OUT = 15

Observation = np.ndarray | Detection


@dataclass(frozen=True)
class StationReport:
    """Per-station residuals of a calibration.

    ``rms_px`` is the reprojection RMS of the fitted model (the joint model with the robot
    correction, or the intrinsic stage's own pose); ``chain_rms_px`` predicts the image from
    the uncorrected robot reading through X and Y (validation, includes the robot's noise).
    ``correction_*`` and ``mahalanobis`` are the joint estimate's robot-pose correction;
    ``loo_*`` the eq. (23) leave-one-out prediction error (NaN if not held out).
    ``corners_px`` holds the detected corners (N, 2) and ``residuals_px`` the fitted model's
    projection minus them (N, 2), pixels, in the order of ``board_points``.
    """

    id: str
    n_corners: int
    rms_px: float
    chain_rms_px: float | None = None
    correction_rot_rad: float | None = None
    correction_trans_m: float | None = None
    mahalanobis: float | None = None
    loo_rot_rad: float | None = None
    loo_trans_m: float | None = None
    corners_px: np.ndarray | None = None
    residuals_px: np.ndarray | None = None


@dataclass(frozen=True)
class CalibrationResult:
    """Everything of the ``cellcal/result@1`` document (``product.md``) and more.

    ``hand_eye`` is T_tcp_cam (eye-in-hand) or T_base_cam (eye-to-hand), ``target_pose``
    T_base_target or T_tcp_target; both None for an intrinsics-only calibration. ``sigmas``
    holds 1-σ standard deviations: floats for ``fx fy cx cy k1 k2 p1 p2 k3 nu kappa`` (0 when
    fixed or not estimated), arrays (3,) for ``hand_eye_rot_rad``, ``hand_eye_trans_m``,
    ``target_pose_rot_rad``, ``target_pose_trans_m`` (small rotations about the axes of the
    frame named first; joint only). ``rejected`` lists ``(station id, reason)``.
    ``validation`` holds E_R, E_t (eq. 21-22), the leave-one-out prediction errors (eq. 23)
    and the chain reprojection RMS. ``variance_factor`` (joint) is the reduced χ² by which the
    covariance was scaled.
    """

    setup: str
    method: str
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    nu: float
    kappa: float
    hand_eye: np.ndarray | None
    target_pose: np.ndarray | None
    sigmas: dict[str, float | np.ndarray]
    stations: tuple[StationReport, ...]
    rejected: tuple[tuple[str, str], ...]
    validation: dict[str, float]
    options: dict[str, Any] = field(default_factory=dict)
    sigma_px: float = float("nan")
    variance_factor: float | None = None


def calibrate_stations(observations: Iterable[Observation],
                       tcp_poses: Sequence[Sequence[float] | None] | None = None, *,
                       inner_corners: Sequence[int], square_size: float,
                       setup: str = "eye_in_hand", station_ids: Sequence[str] | None = None,
                       image_size: Sequence[int] | None = None,
                       intrinsics: tuple[np.ndarray, np.ndarray] | None = None,
                       method: str = "joint", estimate_nu: bool = True,
                       estimate_kappa: bool = True, nu_method: str = "images",
                       robot_noise_rot: float = DEFAULT_ROBOT_NOISE_ROT_RAD,
                       robot_noise_trans: float = DEFAULT_ROBOT_NOISE_TRANS_M,
                       outlier_sigma: float | None = OUTLIER_SIGMA,
                       progress: Callable[[Iterable[Observation]], Iterable[Observation]]
                       | None = None) -> CalibrationResult:
    """Calibrate a station set: camera, board κ and ν, hand-eye and target pose, validation.

    Parameters
    ----------
    observations : iterable of n items, one per station
        A grey or BGR uint8 image (corners are detected), a :class:`calib.target.Detection`
        (e.g. ``ok=False`` with the reason a file could not be read), or detected corners,
        float shape (cols * rows, 2) in the order of ``board_points``. Consumed once, so a
        generator keeps only one image in memory.
    tcp_poses : n UR pose vectors T_base_tcp ``[x, y, z, rx, ry, rz]`` (m, rad) or None
        None (or no pose at all) gives an intrinsics-only calibration.
    inner_corners : (cols, rows)
    square_size : nominal square size, metres.
    setup : ``eye_in_hand`` or ``eye_to_hand``.
    station_ids : n names for reports (default ``000``, ``001``, ...).
    image_size : (width, height); required when no observation is an image.
    intrinsics : (K (3, 3), dist (5,)), optional
        Known camera: the intrinsic stage is skipped and K, dist are held in the joint stage.
    method : a name of ``METHODS``: ``joint`` (default), ``refine``, ``sm`` or an OpenCV solver.
    estimate_nu, estimate_kappa : bool
        False holds ν (κ) at 1: the traditional nominal-size calibration.
    nu_method : ``images`` (Method #1) or ``extrinsics`` (Method #2; ``joint`` only), then ν
        is held at the Method #2 value in the joint stage.
    robot_noise_rot, robot_noise_trans : robot reading noise (rad, m), the joint prior.
    outlier_sigma : joint stage: drop stations whose robot correction lies beyond this many σ
        (Mahalanobis); None keeps all.
    progress : wraps the observation iterable, e.g. a progress bar.

    Raises
    ------
    ValueError
        Bad arguments, too few usable stations (with the rejection reasons), or stations
        that cannot determine the calibration.
    """
    cols, rows = (int(v) for v in inner_corners)
    grid = board_points((cols, rows), square_size)
    check_setup(setup)
    if method not in METHODS:
        raise ValueError(f"unknown method '{method}': choose one of {', '.join(METHODS)}")
    if nu_method not in NU_METHODS:
        raise ValueError(f"unknown nu_method '{nu_method}': choose one of {NU_METHODS}")
    if nu_method == "extrinsics" and (method != "joint" or not estimate_nu):
        raise ValueError("nu_method 'extrinsics' (Method #2) needs method 'joint' and "
                         "estimate_nu")
    options = dict(method=method, estimate_nu=estimate_nu, estimate_kappa=estimate_kappa,
                   nu_method=nu_method, robot_noise_rot_rad=robot_noise_rot,
                   robot_noise_trans_m=robot_noise_trans, outlier_sigma=outlier_sigma,
                   known_intrinsics=intrinsics is not None)

    items = observations if progress is None else progress(observations)
    detections = _detect_all(items, (cols, rows))
    n = len(detections)
    ids = [f"{k:03d}" for k in range(n)] if station_ids is None else [str(s) for s in
                                                                        station_ids]
    if len(ids) != n or (tcp_poses is not None and len(tcp_poses) != n):
        raise ValueError(f"{n} observations but {len(ids)} station ids and "
                         f"{'no' if tcp_poses is None else len(tcp_poses)} robot poses")
    rejected: list[tuple[str, str]] = []
    size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
    usable: list[int] = []
    for k, (det, shape) in enumerate(detections):
        if shape is not None:
            size = size or shape
            if shape != size:
                det = Detection(ok=False, reason=(
                    f"image is {shape[0]}x{shape[1]}, the others {size[0]}x{size[1]}"))
        if det.ok:
            usable.append(k)
        else:
            rejected.append((ids[k], det.reason or "rejected"))
    hand_eye_mode = tcp_poses is not None and any(p is not None for p in tcp_poses)
    if hand_eye_mode:
        for k in [k for k in usable if tcp_poses[k] is None]:
            rejected.append((ids[k], "no tcp_pose, while the other stations have one"))
            usable.remove(k)
    if len(usable) < MIN_IMAGES:
        why = "; ".join(f"{i}: {r}" for i, r in rejected[:3])
        raise ValueError(f"only {len(usable)} of {n} stations usable, need at least "
                         f"{MIN_IMAGES}" + (f" ({why}{'; ...' if len(rejected) > 3 else ''})"
                                            if why else ""))
    if size is None:
        raise ValueError("image_size is required when no observation is an image")
    corners = [detections[k][0].corners for k in usable]

    if intrinsics is None:
        intr = calibrate_intrinsics(corners, Board((cols, rows), square_size), size,
                                    IntrinsicsOptions(estimate_nu=estimate_nu))
        K, dist, nu, C = intr.K, intr.dist, intr.nu, intr.T_cam_target
        sigma_px, rms_img = intr.sigma_px, intr.rms_px_per_image
        sigmas: dict[str, float | np.ndarray] = {**intr.sigmas, "kappa": 0.0}
    else:
        K, dist = _check_intrinsics(*intrinsics)
        nu = 1.0
        C, sigma_px, rms_img = _poses_from_known_intrinsics(corners, grid, K, dist)
        sigmas = {}
    common = dict(setup=setup, image_size=size, K=K, dist=dist, options=options,
                  sigma_px=sigma_px)
    if not hand_eye_mode:
        res = _view_residuals(corners, C, board_points((cols, rows), square_size, nu=nu), K,
                              dist)
        return CalibrationResult(
            method="intrinsics", rms_px=float(np.sqrt(np.mean(rms_img ** 2))), nu=nu,
            kappa=1.0, hand_eye=None, target_pose=None, sigmas=sigmas,
            stations=tuple(StationReport(ids[k], len(corners[i]), float(rms_img[i]),
                                         corners_px=corners[i], residuals_px=res[i])
                           for i, k in enumerate(usable)),
            rejected=tuple(rejected), validation={}, **common)

    T_base_tcp = check_ur_poses([tcp_poses[k] for k in usable], "tcp_pose")
    if any(d.ambiguous for d, _ in (detections[k] for k in usable)):
        C, corners = _resolve_symmetric_origin(robot_chain(T_base_tcp, setup), C, corners,
                                               grid, nu)
    noise = RobotNoise(robot_noise_rot, robot_noise_trans)
    pose_method = "refine" if method == "joint" else method
    fit = calibrate_hand_eye(T_base_tcp, C, setup=setup, method=pose_method, options=RefineOptions(
        noise=noise, estimate_kappa=pose_method == "refine" and estimate_kappa))
    X, Y, kappa = fit.hand_eye, fit.target_pose, fit.kappa
    if method == "refine":
        sigmas.update(fit.sigmas)
    keep = np.arange(len(usable))
    joint = None
    if method == "joint":
        fix = ("kappa",) * (not estimate_kappa) + ("nu",) * (not estimate_nu)
        if intrinsics is not None:
            fix += ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
        stations = CornerStations(corners, T_base_tcp, Board((cols, rows), square_size))
        if nu_method == "extrinsics":
            nu, sigma_nu = nu_from_extrinsics(stations, size, nu,
                                              NuSearch(setup=setup, noise=noise))
            fix += ("nu",)
        joint = solve_joint(stations, CellParameters(K, dist, nu, kappa, X, Y), JointOptions(
            sigma_px=sigma_px, setup=setup, noise=noise, fix=fix, outlier_sigma=outlier_sigma))
        K, dist, nu, kappa = joint.K, joint.dist, joint.nu, joint.kappa
        X, Y, keep = joint.hand_eye, joint.target_pose, joint.stations
        rejected += [(ids[usable[i]], reason) for i, reason in joint.rejected]
        sigmas = dict(joint.sigmas)
        if nu_method == "extrinsics":
            sigmas["nu"] = sigma_nu
        common.update(K=K, dist=dist)

    # Validation on the kept stations, camera poses at true scale.
    P, Ck = T_base_tcp[keep], scale_translations(C[keep], kappa)
    true_grid = board_points((cols, rows), square_size, kappa=kappa, nu=nu)
    pts = [corners[i] for i in keep]
    chain = reprojection_rms(pts, [true_grid] * len(keep), K, dist,
                             camera_from_robot(P, X, Y, setup))
    held = np.unique(np.linspace(0, len(keep) - 1, min(len(keep), MAX_HELD_OUT)).astype(int))
    loo = leave_one_out(P, Ck, setup=setup, held_out=held)
    motion = motion_residuals(P, Ck, X, setup=setup)
    loo_rot, loo_trans = np.full(len(keep), np.nan), np.full(len(keep), np.nan)
    loo_rot[loo.stations], loo_trans[loo.stations] = loo.rot_rad, loo.trans_m
    fit_rms = joint.rms_px_per_station if joint is not None else rms_img[keep]
    if joint is not None:
        fit_res = np.split(joint.residuals_px, np.cumsum([len(m) for m in pts])[:-1])
    else:
        fit_res = _view_residuals(pts, C[keep], board_points((cols, rows), square_size, nu=nu),
                                  K, dist)
    reports = []
    for j, i in enumerate(keep):
        extra = {} if joint is None else dict(
            correction_rot_rad=float(np.linalg.norm(joint.corrections[j, :3])),
            correction_trans_m=float(np.linalg.norm(joint.corrections[j, 3:])),
            mahalanobis=float(joint.mahalanobis[j]))
        reports.append(StationReport(ids[usable[i]], len(corners[i]), float(fit_rms[j]),
                                     chain_rms_px=float(chain[j]),
                                     loo_rot_rad=float(loo_rot[j]),
                                     loo_trans_m=float(loo_trans[j]),
                                     corners_px=corners[i], residuals_px=fit_res[j], **extra))
    validation = {
        "E_R": motion.E_R, "E_t": motion.E_t, "n_motions": motion.n_motions,
        "loo_rot_rad_mean": float(np.nanmean(loo.rot_rad)),
        "loo_trans_m_mean": float(np.nanmean(loo.trans_m)),
        "loo_rot_rad_max": float(np.nanmax(loo.rot_rad)),
        "loo_trans_m_max": float(np.nanmax(loo.trans_m)),
        "loo_solver": "sm", "loo_stations": len(loo.stations),
        "chain_rms_px": float(np.sqrt(np.mean(chain ** 2))),
    }
    rms = joint.rms_px if joint is not None else float(np.sqrt(np.mean(rms_img[keep] ** 2)))
    return CalibrationResult(
        method=method, rms_px=rms, nu=nu, kappa=kappa, hand_eye=X, target_pose=Y,
        sigmas=sigmas, stations=tuple(reports), rejected=tuple(rejected),
        validation=validation, variance_factor=None if joint is None
        else joint.variance_factor, **common)


def _detect_all(items: Iterable[Observation], inner_corners: tuple[int, int], *,
                workers: int | None = None) -> list[tuple[Detection, tuple[int, int] | None]]:
    """``_detect`` over all observations on a few threads, in order.

    OpenCV's detector releases the GIL, so threads use every core. At most ``2 x workers``
    observations are in flight, so a generator of images still holds only a few in memory.
    """
    workers = workers or min(4, os.cpu_count() or 1)
    out: list[tuple[Detection, tuple[int, int] | None]] = []
    with ThreadPoolExecutor(workers) as pool:
        pending: deque[Future] = deque()
        for obs in items:
            pending.append(pool.submit(_detect, obs, inner_corners))
            if len(pending) >= 2 * workers:
                out.append(pending.popleft().result())
        out.extend(f.result() for f in pending)
    return out


def _detect(obs: Observation, inner_corners: tuple[int, int]
            ) -> tuple[Detection, tuple[int, int] | None]:
    """Detection of one observation and the image size (w, h) if it was an image."""
    if isinstance(obs, Detection):
        return obs, None
    arr = np.asarray(obs)
    if arr.ndim == 2 and arr.shape[1] == 2 and np.issubdtype(arr.dtype, np.floating):
        n_grid = inner_corners[0] * inner_corners[1]
        if len(arr) != n_grid or not np.isfinite(arr).all():
            return Detection(ok=False, reason=(
                f"{len(arr)} corners given, the {inner_corners[0]}x{inner_corners[1]} board "
                f"has {n_grid} (or some are not finite)")), None
        return Detection(ok=True, corners=arr.astype(float)), None
    shape = (arr.shape[1], arr.shape[0]) if arr.ndim >= 2 else None
    return detect_checkerboard(arr, inner_corners), shape


def _check_intrinsics(K: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Known intrinsics as K (3, 3) and dist (5,); more than 5 non-zero terms are refused."""
    K, dist = np.asarray(K, dtype=float), np.asarray(dist, dtype=float).ravel()
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("intrinsics: K must be a finite 3x3 matrix with positive fx, fy")
    if len(dist) < 4 or not np.isfinite(dist).all() or np.any(dist[5:] != 0):
        raise ValueError("intrinsics: dist must be [k1, k2, p1, p2(, k3)]; terms beyond k3 "
                         "are not supported")
    return K, np.concatenate([dist, np.zeros(5)])[:5]


def _poses_from_known_intrinsics(corners: list[np.ndarray], grid: np.ndarray, K: np.ndarray,
                                 dist: np.ndarray
                                 ) -> tuple[np.ndarray, float, np.ndarray]:
    """Per-image T_cam_target (nominal board) by PnP, σ_px and per-image RMS (n,)."""
    poses, sq = [], []
    for m in corners:
        try:
            C, residuals = solve_pnp(grid, m, K, dist)
        except ValueError:
            raise ValueError("PnP failed with the given intrinsics: are K and dist right?"
                             ) from None
        sq.append(np.sum(residuals ** 2, axis=1))
        poses.append(C)
    total = np.concatenate(sq)
    sigma_px = float(np.sqrt(total.sum() / max(total.size * 2 - 6 * len(corners), 1)))
    return np.array(poses), sigma_px, np.sqrt(np.array([s.mean() for s in sq]))


def _view_residuals(corners: Sequence[np.ndarray], T_cam_target: np.ndarray, grid: np.ndarray,
                    K: np.ndarray, dist: np.ndarray) -> list[np.ndarray]:
    """Projected minus detected corners (N, 2) per view, each at its own board pose.

    ``T_cam_target`` (n, 4, 4) and ``grid`` (N, 3) in the same (nominal-scale) target frame.
    """
    return [Pinhole(K, dist).project(grid @ T[:3, :3].T + T[:3, 3]) - m
            for m, T in zip(corners, T_cam_target, strict=True)]


def _resolve_symmetric_origin(P: np.ndarray, C: np.ndarray, corners: list[np.ndarray],
                              grid: np.ndarray, nu: float
                              ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Put a 180°-symmetric board's origin at the same physical corner in every image.

    A camera motion rotates by the same angle as the robot motion (``A X = X B`` is a
    similarity). For each station the detected frame and the frame turned by 180° about the
    board centre are tried against the first station; the one whose motion angle agrees
    with the robot's wins. Turning the frame reverses the corner order.
    """
    centre = np.array([grid[-1, 0] * nu, grid[-1, 1], 0.0])  # far corner, nominal scale
    F = make_transform(np.diag([-1.0, -1.0, 1.0]), centre)  # T_old_new
    C, corners = C.copy(), list(corners)
    angle_A = rotation_angle((invert(P[0]) @ P[1:])[:, :3, :3])
    for k in range(1, len(C)):
        keep_err = abs(rotation_angle(C[0][:3, :3] @ C[k][:3, :3].T) - angle_A[k - 1])
        flip_err = abs(rotation_angle(C[0][:3, :3] @ (C[k] @ F)[:3, :3].T) - angle_A[k - 1])
        if flip_err < keep_err:
            C[k] = C[k] @ F
            corners[k] = corners[k][::-1].copy()
    return C, corners
