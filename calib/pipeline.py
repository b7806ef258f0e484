"""From images (or detected corners) and robot poses to a result a user can trust.

The image path of :func:`calib.calibrate` (``product.md``, "Pipeline"),
:func:`calibrate_stations`::

    detect the board (calib.boards)  a bad image becomes a rejected station, never an abort;
                                     partial views carry their point ids through every stage
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

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from calib.boards import Board
from calib.camera import Pinhole
from calib.chain import (
    camera_from_robot,
    robot_chain,
)
from calib.crossval import predict_dropped
from calib.evidence import JointChoice, Trust, choose_joint, method_cross_validation
from calib.extrapolation import box_shift_sigmas
from calib.geometry import check_ur_poses
from calib.handeye import calibrate_hand_eye
from calib.intrinsics import IntrinsicsOptions, calibrate_intrinsics
from calib.joint import (
    CellParameters,
    CornerStations,
    JointOptions,
    JointResult,
    solve_joint,
)
from calib.jointfit import JointData, JointModel
from calib.nu import NuSearch, nu_from_extrinsics
from calib.options import SolverOptions
from calib.quality import QualityInputs, assess, irreconcilable
from calib.refine import RefineOptions, scale_translations
from calib.result import StationFit
from calib.stations import (
    Observation,
    StationInputs,
    check_intrinsics,
    detect_all,
    poses_from_known_intrinsics,
    resolve_symmetric_origin,
    usable_stations,
)
from calib.uncertainty import hand_eye_rss, with_extrapolation
from calib.validation import (
    leave_one_out,
    motion_residuals,
    reprojection_rms,
)

#: Leave-one-out validation holds out at most this many stations (evenly spread).
MAX_HELD_OUT = 15

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
    covariance was scaled. ``trust`` holds the cross-validation, model selection, honest
    uncertainty and verdict (``calib.evidence``); ``sigmas`` are the honest σ. ``robot_map``
    (3, 3): the linear map of the robot's translations the chosen model estimated
    (``calib.chain.corrected_readings``; predictions from robot readings apply it), None when
    the readings are used as they are.
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
    stations: tuple[StationFit, ...]
    rejected: tuple[tuple[str, str], ...]
    validation: dict[str, float]
    options: dict[str, Any] = field(default_factory=dict)
    sigma_px: float = float("nan")
    variance_factor: float | None = None
    trust: Trust | None = None
    robot_map: np.ndarray | None = None


@dataclass
class _Stage:
    """The estimate as the stages refine it; ``C`` (n, 4, 4) are the per-image camera poses
    at nominal scale, ``rms_img`` (n,) their reprojection RMS, ``keep`` the stations kept."""

    K: np.ndarray
    dist: np.ndarray
    nu: float
    C: np.ndarray
    sigma_px: float
    rms_img: np.ndarray
    sigmas: dict[str, float | np.ndarray]
    kappa: float = 1.0
    hand_eye: np.ndarray | None = None
    target_pose: np.ndarray | None = None
    keep: np.ndarray | None = None
    joint: JointResult | None = None
    fix: tuple[str, ...] = ()
    choice: JointChoice | None = None
    image_size: tuple[int, int] = (0, 0)
    setup: str = "eye_in_hand"
    method: str = "joint"
    pose_residuals: np.ndarray | None = None  # (n, 2) of the pose-level fit, rad and m


@threadpool_limits.wrap(limits=1, user_api="blas")
def calibrate_stations(stations: StationInputs, board: Board,
                       options: SolverOptions | None = None, *,
                       progress: Callable[[Iterable[Observation]], Iterable[Observation]]
                       | None = None,
                       on_stage: Callable[[str], None] | None = None) -> CalibrationResult:
    """Calibrate a station set: camera, board κ and ν, hand-eye and target pose, validation.

    BLAS runs on one thread meanwhile: the solvers' matrices are small (tens of columns), so
    a multi-threaded BLAS spends its time in thread hand-offs — 5x slower on 2 busy cores.

        ``board`` is the printed target (:class:`calib.boards.Board`: checkerboard, ChArUco);
    each station may see part of it (its detection's point ids), with at least
    ``MIN_STATION_POINTS`` points. ``progress`` wraps the observation iterable, e.g. a
    progress bar; ``on_stage`` is called with the name of each stage as it begins
    (``intrinsics``, ``hand-eye``, ``model selection by cross-validation`` (joint method),
    ``validation``, ``cross-validation``), e.g. for a service's progress events.

    Raises
    ------
    ValueError
        Bad arguments, too few usable stations (with the rejection reasons), or stations
        that cannot determine the calibration.
    """
    options = SolverOptions() if options is None else options
    items = stations.observations if progress is None else progress(stations.observations)
    detections = detect_all(items, board)
    ids, usable, rejected, size = usable_stations(detections, stations, board)
    corners = [detections[k][0].corners for k in usable]
    measured = CornerStations(corners, np.zeros((len(usable), 4, 4)), board,
                              [detections[k][0].ids for k in usable])
    begin = on_stage or (lambda name: None)
    begin("intrinsics")
    stage = _camera_stage(measured, size, stations.intrinsics, options)
    stage.image_size, stage.setup = size, stations.setup
    stage.method = options.solver("images")
    common = dict(setup=stage.setup, image_size=size, options=options.record(
        stations.intrinsics is not None))
    if stations.tcp_poses is None or all(p is None for p in stations.tcp_poses):
        res = _view_residuals(measured, stage.C, stage.nu, stage.K, stage.dist)
        return CalibrationResult(
            method="intrinsics", K=stage.K, dist=stage.dist, sigma_px=stage.sigma_px,
            rms_px=float(np.sqrt(np.mean(stage.rms_img ** 2))), nu=stage.nu, kappa=1.0,
            hand_eye=None, target_pose=None, sigmas=stage.sigmas,
            stations=tuple(StationFit.of_image(ids[k], corners[i], res[i], measured.ids()[i],
                                               rms_px=stage.rms_img[i])
                           for i, k in enumerate(usable)),
            rejected=tuple(rejected), validation={}, trust=Trust(
                cross_validation=None, model_selection=None, uncertainty=None,
                quality=assess(QualityInputs(
                    setup=stage.setup, T_base_tcp=None, corrections=None, cv=None,
                    square_size_m=board.square_size, corners=tuple(corners),
                    image_size=size))), **common)

    T_base_tcp = check_ur_poses([stations.tcp_poses[k] for k in usable], "tcp_pose")
    if any(d.ambiguous for d, _ in (detections[k] for k in usable)):
        stage.C, corners = resolve_symmetric_origin(robot_chain(T_base_tcp, stage.setup),
                                                     stage.C, corners, board.points(), stage.nu)
    measured = replace(measured, image_points=corners, T_base_tcp=T_base_tcp)
    begin("hand-eye")
    _hand_eye_stage(stage, measured, size, options, stations.intrinsics is not None)
    station_ids = [ids[k] for k in usable]
    if stage.joint is not None:
        begin("model selection by cross-validation")
        _choose_model(stage, measured, station_ids, options)
        rejected += [(ids[usable[i]], reason) for i, reason in stage.joint.rejected]
    begin("validation")
    reports, validation = _validate(stage, measured, station_ids)
    begin("cross-validation")
    joint = stage.joint
    rms = (joint.rms_px if joint is not None
           else float(np.sqrt(np.mean(stage.rms_img[stage.keep] ** 2))))
    return CalibrationResult(
        method=stage.method, K=stage.K, dist=stage.dist, sigma_px=stage.sigma_px, rms_px=rms,
        nu=stage.nu, kappa=stage.kappa, hand_eye=stage.hand_eye, target_pose=stage.target_pose,
        sigmas=stage.sigmas, stations=tuple(reports), rejected=tuple(rejected),
        validation=validation, variance_factor=None if joint is None
        else joint.variance_factor, robot_map=None if joint is None else joint.robot_map,
        trust=_trust(stage, measured, station_ids, options, rejected), **common)


def _camera_stage(views: CornerStations, size: tuple[int, int],
                  intrinsics: tuple[np.ndarray, np.ndarray] | None,
                  options: SolverOptions) -> _Stage:
    """Intrinsics with ν (Method #1), or the known camera and per-image PnP poses, from the
    corners and point ids of ``views`` (its robot poses are not used)."""
    if intrinsics is None:
        intr = calibrate_intrinsics(views.image_points, views.board, size,
                                    IntrinsicsOptions(estimate_nu=options.estimate_nu),
                                    point_ids=views.ids())
        return _Stage(K=intr.K, dist=intr.dist, nu=intr.nu, C=intr.T_cam_target,
                      sigma_px=intr.sigma_px, rms_img=intr.rms_px_per_image,
                      sigmas={**intr.sigmas, "kappa": 0.0})
    K, dist = check_intrinsics(*intrinsics)
    all_points = views.board.points()
    C, sigma_px, rms_img = poses_from_known_intrinsics(
        list(views.image_points), [all_points[i] for i in views.ids()], K, dist)
    return _Stage(K=K, dist=dist, nu=1.0, C=C, sigma_px=sigma_px, rms_img=rms_img, sigmas={})


def _hand_eye_stage(stage: _Stage, stations: CornerStations, size: tuple[int, int],
                    options: SolverOptions, known_intrinsics: bool) -> None:
    """Hand-eye by the pose-level method, then (``joint``) the joint ML; updates ``stage``."""
    method, noise = stage.method, options.noise
    pose_method = "refine" if method == "joint" else method
    fit = calibrate_hand_eye(stations.T_base_tcp, stage.C, setup=stage.setup,
                             method=pose_method, options=RefineOptions(
                                 noise=noise,
                                 estimate_kappa=pose_method == "refine"
                                 and options.kappa_mode != "fixed"))
    stage.hand_eye, stage.target_pose, stage.kappa = fit.hand_eye, fit.target_pose, fit.kappa
    stage.pose_residuals = fit.station_residuals
    stage.keep = np.arange(len(stations.image_points))
    if method == "refine":
        stage.sigmas.update(fit.sigmas)
    if method != "joint":
        return
    fix = ("kappa",) * (options.kappa_mode == "fixed") + ("nu",) * (not options.estimate_nu)
    if known_intrinsics:
        fix += ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    if options.nu_method == "extrinsics":
        stage.nu, sigma_nu = nu_from_extrinsics(stations, size, stage.nu,
                                                NuSearch(setup=stage.setup, noise=noise))
        fix += ("nu",)
    joint = solve_joint(stations, CellParameters(stage.K, stage.dist, stage.nu, stage.kappa,
                                                 stage.hand_eye, stage.target_pose),
                        JointOptions(sigma_px=stage.sigma_px, setup=stage.setup, noise=noise,
                                     fix=fix, outlier_sigma=None if irreconcilable(
                                         fit.station_residuals) else options.outlier_sigma))
    stage.K, stage.dist, stage.nu, stage.kappa = joint.K, joint.dist, joint.nu, joint.kappa
    stage.hand_eye, stage.target_pose, stage.keep = joint.hand_eye, joint.target_pose, \
        joint.stations
    stage.sigmas = dict(joint.sigmas)
    if options.nu_method == "extrinsics":
        stage.sigmas["nu"] = sigma_nu
    stage.joint, stage.fix = joint, fix


def _choose_model(stage: _Stage, stations: CornerStations, ids: list[str],
                  options: SolverOptions) -> None:
    """Model selection by cross-validation on the joint stage's stations (``calib.evidence``):
    the chosen model's result, with honest σ, replaces the joint stage's."""
    first = stage.joint
    assert first is not None
    kept = first.stations
    data = JointData(stations.subset(kept), stage.setup, stage.sigma_px)
    stage.choice = choose_joint(data, [ids[i] for i in kept],
                                JointModel("all estimated", stage.fix, options.noise), first,
                                kappa=options.kappa_mode)
    if options.workspace is not None:
        # the stations' estimate used over the whole box (calib.extrapolation); ``data`` holds
        # the kept stations in the order of the result's corrections (its ``stations`` index
        # all the stations, so they do not index ``data``)
        result = stage.choice.result
        stage.choice = replace(stage.choice, uncertainty=with_extrapolation(
            stage.choice.uncertainty, box_shift_sigmas(
                data.stations.T_base_tcp, result.corrections,
                result.hand_eye, data.setup, options.workspace)))
    joint = stage.choice.result
    stage.K, stage.dist, stage.nu, stage.kappa = joint.K, joint.dist, joint.nu, joint.kappa
    stage.hand_eye, stage.target_pose, stage.joint = joint.hand_eye, joint.target_pose, joint
    sigmas = dict(stage.choice.uncertainty.sigmas)
    if options.nu_method == "extrinsics":
        sigmas["nu"] = stage.sigmas["nu"]
    stage.sigmas = sigmas


def _trust(stage: _Stage, stations: CornerStations, ids: list[str],
           options: SolverOptions, rejected: list[tuple[str, str]]) -> Trust:
    """Cross-validation, selection, uncertainty and the verdict of the finished stages."""
    keep = stage.keep
    data = JointData(stations.subset(keep), stage.setup, stage.sigma_px)
    kept_ids = [ids[i] for i in keep]
    if stage.choice is None:
        cell = CellParameters(stage.K, stage.dist, stage.nu, stage.kappa, stage.hand_eye,
                              stage.target_pose)
        cv = method_cross_validation(data, kept_ids, cell, stage.C[keep], stage.method)
        selection, uncertainty, corrections = None, None, stage.pose_residuals
        kappa_sigma = stage.sigmas.get("kappa") if stage.method == "refine" else None
    else:
        selection, uncertainty = stage.choice.selection, stage.choice.uncertainty
        dropped = [i for i, _ in stage.choice.result.rejected]
        cv = predict_dropped(selection.chosen.cv,
                             JointData(stations.subset(dropped), stage.setup, stage.sigma_px),
                             [ids[i] for i in dropped], dropped, ids)
        delta = stage.choice.result.corrections
        corrections = np.column_stack([np.linalg.norm(delta[:, :3], axis=1),
                                       np.linalg.norm(delta[:, 3:], axis=1)])
        held = "kappa" in (selection.chosen.model.fix if selection.chosen.model else ())
        kappa_sigma = None if held else stage.sigmas.get("kappa")
    quality = assess(QualityInputs(
        setup=stage.setup, T_base_tcp=data.stations.T_base_tcp, corrections=corrections,
        cv=cv, square_size_m=stations.board.square_size, kappa=stage.kappa,
        kappa_sigma=None if kappa_sigma is None else float(kappa_sigma),
        sigma_px=stage.sigma_px, corners=tuple(data.stations.image_points),
        image_size=stage.image_size, rejected=tuple(rejected),
        robot_map=None if stage.joint is None else stage.joint.robot_map,
        hand_eye_rss=hand_eye_rss(stage.sigmas), tolerance=options.tolerance))
    return Trust(cross_validation=cv, model_selection=selection, uncertainty=uncertainty,
                 quality=quality)


def _validate(stage: _Stage, stations: CornerStations, ids: list[str]
              ) -> tuple[list[StationFit], dict[str, Any]]:
    """Reports of the kept stations and the validation figures, camera poses at true scale."""
    keep, joint, X, Y = stage.keep, stage.joint, stage.hand_eye, stage.target_pose
    setup = stage.setup
    P, Ck = stations.T_base_tcp[keep], scale_translations(stage.C[keep], stage.kappa)
    kept = stations.subset(keep)
    pts, point_ids = kept.image_points, kept.ids()
    true_grids = [kept.board.points(i, kappa=stage.kappa, nu=stage.nu) for i in point_ids]
    chain = reprojection_rms(pts, true_grids, stage.K, stage.dist,
                             camera_from_robot(P, X, Y, setup,
                                               None if joint is None else joint.robot_map))
    held = np.unique(np.linspace(0, len(keep) - 1, min(len(keep), MAX_HELD_OUT)).astype(int))
    loo = leave_one_out(P, Ck, setup=setup, held_out=held)
    motion = motion_residuals(P, Ck, X, setup=setup)
    loo_rot, loo_trans = np.full(len(keep), np.nan), np.full(len(keep), np.nan)
    loo_rot[loo.stations], loo_trans[loo.stations] = loo.rot_rad, loo.trans_m
    if joint is not None:
        fit_rms = joint.rms_px_per_station
        fit_res = np.split(joint.residuals_px, np.cumsum([len(m) for m in pts])[:-1])
    else:
        fit_rms = stage.rms_img[keep]
        fit_res = _view_residuals(kept, stage.C[keep], stage.nu, stage.K, stage.dist)
    reports = []
    for j, i in enumerate(keep):
        extra = {} if joint is None else dict(
            correction_rot_rad=np.linalg.norm(joint.corrections[j, :3]),
            correction_trans_m=np.linalg.norm(joint.corrections[j, 3:]),
            mahalanobis=joint.mahalanobis[j])
        reports.append(StationFit.of_image(ids[i], pts[j], fit_res[j], point_ids[j],
                                           rms_px=fit_rms[j], chain_rms_px=chain[j],
                                           loo_rot_rad=loo_rot[j], loo_trans_m=loo_trans[j],
                                           **extra))
    validation = {
        "E_R": motion.E_R, "E_t": motion.E_t, "n_motions": motion.n_motions,
        "loo_rot_rad_mean": float(np.nanmean(loo.rot_rad)),
        "loo_trans_m_mean": float(np.nanmean(loo.trans_m)),
        "loo_rot_rad_max": float(np.nanmax(loo.rot_rad)),
        "loo_trans_m_max": float(np.nanmax(loo.trans_m)),
        "loo_solver": "sm", "loo_stations": len(loo.stations),
        "chain_rms_px": float(np.sqrt(np.mean(chain ** 2))),
    }
    return reports, validation


def _view_residuals(views: CornerStations, T_cam_target: np.ndarray, nu: float,
                    K: np.ndarray, dist: np.ndarray) -> list[np.ndarray]:
    """Projected minus detected corners (N_i, 2) per view, each at its own board pose
    ``T_cam_target`` (n, 4, 4) in the nominal-scale target frame, the board's aspect ``nu``.
    """
    return [Pinhole(K, dist).project(views.board.points(i, nu=nu) @ T[:3, :3].T + T[:3, 3]) - m
            for m, i, T in zip(views.image_points, views.ids(), T_cam_target, strict=True)]
