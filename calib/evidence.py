"""The evidence every result carries (``product.md``, "Trust"), computed in one place.

* image stations, joint estimator: model selection by cross-validation
  (``calib.selection``), the chosen model's cross-validation, its honest uncertainty
  (``calib.uncertainty``);
* image stations, another hand-eye method: cross-validation of that method;
* pose-only stations: SM against its refinement (``refine``), chosen by cross-validation, so
  the refinement is never returned when it predicts held-out stations worse than the SM it
  starts from;
* every result: the quality verdict (``calib.quality``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.crossval import (
    CrossValidation,
    FoldEstimate,
    PoseStations,
    cross_validate_fixed_camera,
    cross_validate_poses,
    fold_indices,
)
from calib.handeye import HandEyeResult, calibrate_hand_eye
from calib.joint import CellParameters, JointResult
from calib.jointfit import JointData, JointFit, JointModel, fit_joint
from calib.options import SolverOptions
from calib.quality import QualityInputs, assess, irreconcilable
from calib.refine import RefineOptions, scale_translations
from calib.result import QualityBlock
from calib.selection import ModelCandidate, Modes, Selection, select_joint_model
from calib.uncertainty import UncertaintyEstimate, hand_eye_rss, honest, with_held_shift

#: Leading names of the pose-only candidates (``calib.handeye`` methods).
POSE_CANDIDATES = ("sm", "refine")


@dataclass(frozen=True)
class Trust:
    """Cross-validation, model selection, uncertainty and verdict of one result."""

    cross_validation: CrossValidation | None
    model_selection: Selection | None
    uncertainty: UncertaintyEstimate | None
    quality: QualityBlock


@dataclass(frozen=True)
class JointChoice:
    """The joint result to return (the chosen model) and its evidence."""

    result: JointResult
    selection: Selection
    uncertainty: UncertaintyEstimate


def choose_joint(data: JointData, station_ids: Sequence[str], base: JointModel,
                 first: JointResult, *, kappa: str = "auto") -> JointChoice:
    """Select the joint model by cross-validation, starting from ``first`` (the base fit).

    ``data`` and ``station_ids`` cover the stations ``first`` kept (``first.stations``).
    """
    if irreconcilable(np.linalg.norm(first.corrections.reshape(-1, 2, 3), axis=2)):
        # the robot poses contradict the images (calib.quality): no model can be chosen
        # by prediction, and refitting nonsense would only cost time
        selection = select_joint_model(data, station_ids, base, first, Modes(
            kappa="estimate", nu="estimate", noise="assumed", robot_map="off"))
    else:
        selection = select_joint_model(data, station_ids, base, first, Modes(kappa=kappa))
    fit = selection.chosen.fit
    assert fit is not None  # joint candidates always carry their fit
    # the noise levels the data show: those of the candidate that estimated them for the same
    # robot model (a robot whose translation map is left out shows that as noise); else the
    # chosen fit's own residuals give them (JointFit.result)
    chosen = selection.chosen.model
    estimated = next((c.fit for c in selection.candidates
                      if c.model is not None and c.model.estimate_noise and c.fit
                      and chosen is not None and c.model.robot_map == chosen.robot_map), None)
    noise = None if estimated is None else (
        estimated.sigma_px, estimated.noise.rot_rad, estimated.noise.trans_m)
    result = fit.result(first.stations, first.rejected, noise=noise)
    # what the jackknife over the chosen model's folds shows if that noise model holds
    folds = fold_indices(len(data))
    expected = fit.expected_jackknife(folds, noise=noise) \
        if len(folds) == selection.chosen.cv.folds else {}
    uncertainty = honest(result.sigmas, selection.chosen.cv.estimates, FoldEstimate.of(result),
                         expected)
    # κ, ν held at 1 by the selection (not by the user): the poses' σ include the bias the
    # shift to the same model estimating them shows (calib.uncertainty)
    held = [p for p in ("kappa", "nu") if chosen is not None and p in chosen.fix
            and p not in base.fix and not (p == "kappa" and kappa == "fixed")]
    if held and chosen is not None:
        freed = _freed(selection, data, fit, replace(chosen, fix=tuple(
            p for p in chosen.fix if p not in held)))
        uncertainty = with_held_shift(
            uncertainty, held, (FoldEstimate.of(fit.cell), result.sigmas),
            (FoldEstimate.of(freed.cell),
             freed.result(first.stations, first.rejected, noise=noise).sigmas))
    return JointChoice(result=result, selection=selection, uncertainty=uncertainty)


def _freed(selection: Selection, data: JointData, fit: JointFit, model: JointModel
           ) -> JointFit:
    """The fit of ``model`` (the chosen one with κ and/or ν freed) on all stations: its
    candidate's when the selection tried it, else fitted from the chosen ``fit`` at the noise
    levels that fit ended with."""
    for c in selection.candidates:
        if c.model is not None and c.fit is not None and set(c.model.fix) == set(model.fix) \
                and c.model.estimate_noise == model.estimate_noise \
                and c.model.robot_map == model.robot_map:
            return c.fit
    return fit_joint(replace(data, sigma_px=fit.sigma_px),
                     replace(model, noise=fit.noise, estimate_noise=False), fit.cell,
                     corrections=fit.corrections)


def method_cross_validation(data: JointData, station_ids: Sequence[str],
                            cell: CellParameters, T_cam_target: np.ndarray,
                            method: str) -> CrossValidation:
    """Cross-validation of a pose-level hand-eye ``method`` on image stations, the camera
    (and κ) held at ``cell``; ``T_cam_target`` (n, 4, 4) the per-image poses, nominal scale."""
    def solve(train: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        C = scale_translations(T_cam_target[train], cell.kappa)
        fit = calibrate_hand_eye(data.stations.T_base_tcp[train], C, setup=data.setup,
                                 method=method)
        return fit.hand_eye, fit.target_pose

    return cross_validate_fixed_camera(data, station_ids, cell, solve)


def choose_pose_only(stations: PoseStations, station_ids: Sequence[str], *, method: str,
                     options: SolverOptions, square_size_m: float | None
                     ) -> tuple[HandEyeResult, Trust]:
    """Pose-only hand-eye with evidence. ``method='refine'`` returns the refinement only when
    it predicts held-out stations at least as well as the SM it starts from, else SM. Of
    ``options`` it uses the robot noise, κ (estimated only for ``kappa='estimate'``: pose-only
    stations have no cross-validated choice) and the tolerance."""
    T_base_tcp, setup = stations.T_base_tcp, stations.setup
    estimate_kappa = options.kappa_mode == "estimate"
    refine = RefineOptions(noise=options.noise, estimate_kappa=estimate_kappa)

    def fit(name: str, train: np.ndarray | slice = slice(None)) -> HandEyeResult:
        opts = refine if name == "refine" else RefineOptions(noise=options.noise)
        return calibrate_hand_eye(T_base_tcp[train], stations.T_cam_target[train],
                                  setup=setup, method=name, options=opts)

    def solver(name: str) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, float]]:
        def solve(train: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
            res = fit(name, train)
            return res.hand_eye, res.target_pose, res.kappa
        return solve

    names = POSE_CANDIDATES if method == "refine" else (method,)
    cvs = {name: cross_validate_poses(stations, station_ids, solver(name)) for name in names}
    chosen, selection = names[-1], None
    if method == "refine":
        never_worse = (cvs["refine"].trans_m or 0.0) <= (cvs["sm"].trans_m or 0.0)
        chosen = "refine" if never_worse else "sm"
        candidates = tuple(ModelCandidate(name=n, cv=cvs[n]) for n in names)
        verdict = "no worse" if never_worse else "worse"
        selection = Selection(candidates=candidates, chosen=candidates[names.index(chosen)],
                              decisions=(f"pose-only: {chosen} (the refinement predicts "
                                         f"held-out stations {verdict} than SM)",))
    result = fit(chosen)
    uncertainty = honest(result.sigmas, cvs[chosen].estimates, FoldEstimate(
        hand_eye=result.hand_eye, target_pose=result.target_pose, kappa=result.kappa))
    kappa_sigma = uncertainty.sigmas.get("kappa") if estimate_kappa else None
    quality = assess(QualityInputs(
        setup=setup, T_base_tcp=T_base_tcp, corrections=result.station_residuals,
        cv=cvs[chosen], square_size_m=square_size_m, kappa=result.kappa,
        kappa_sigma=None if kappa_sigma is None else float(kappa_sigma),
        hand_eye_rss=hand_eye_rss(uncertainty.sigmas), tolerance=options.tolerance))
    return result, Trust(cross_validation=cvs[chosen], model_selection=selection,
                         uncertainty=uncertainty, quality=quality)
