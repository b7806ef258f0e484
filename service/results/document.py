"""The result (``cellcal/result@1``, product.md) of a calibration as the typed ``calib.result``
model, built here and only here from what ``calib`` returns: estimate, uncertainty, evidence,
provenance (the cellcal version and the time, which ``calib`` does not know); and a stored
result read back as the cell it describes (:func:`stored_cell`).

The service stores ``Result.document()`` as JSON and the command line writes it; everything
else reads the typed result."""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from typing import Any

import numpy as np

from calib import (
    CAMERA_PARAMS,
    RESULT_FORMAT,
    SELECTION_RULE,
    BoardScale,
    Calibration,
    CalibrationResult,
    CameraModel,
    Candidate,
    CrossValidation,
    CrossValidationBlock,
    HandEyeResult,
    HeldOutStation,
    ModelCandidate,
    ModelSelection,
    Motions,
    PoseOnlyResult,
    QualityBlock,
    Rejected,
    Result,
    Selection,
    Software,
    StationFit,
    StoredCell,
    Target,
    Transform,
    Trust,
    Uncertainty,
    board_from_target,
    parse_result,
    ur_pose_from_matrix,
)
from service.errors import UnprocessableError
from service.version import software_version

_FRAMES_NOTE = ("rotations as small angles (rad) about the axes of the frame named first (tcp "
                "for hand_eye eye-in-hand), translations in metres")
_CV_NOTE = ("each station predicted from its robot pose alone by the estimator fitted on the "
            "other folds; the figures cover every station whose board was detected, the "
            "stations the fit dropped as outliers included (each predicted by the fold that "
            "held it out); kept_rms_px: the kept stations only; rms_mm: corner error on the "
            "board plane; rot_deg/trans_mm: predicted vs observed T_cam_target")


def stored_cell(result: Result | Mapping[str, Any], target: Target, *, use: str) -> StoredCell:
    """The cell a stored result describes (camera, hand-eye, target pose) with the run's board
    at the calibrated κ, ν: what a validation (``use``, said in the 422 message) tests
    against. 422 ``incomplete_result`` for a result without a camera model."""
    doc = parse_result(result)
    camera, hand_eye, target_pose = doc.camera, doc.hand_eye, doc.target_pose
    if camera is None or hand_eye is None or target_pose is None:
        raise UnprocessableError(f"{use} compares the board with the calibration's camera "
                                 "model, hand-eye and target pose; this result has none "
                                 "(pose-only).", code="incomplete_result")
    robot_map = doc.robot_translation_map
    return StoredCell(setup=doc.setup, K=np.asarray(camera.K, dtype=float),
                      dist=np.asarray(camera.dist, dtype=float),
                      hand_eye=np.asarray(hand_eye.matrix, dtype=float),
                      target_pose=np.asarray(target_pose.matrix, dtype=float),
                      board=board_from_target(target), kappa=doc.target.kappa,
                      nu=doc.target.nu,
                      robot_map=None if robot_map is None else np.asarray(robot_map, float))


def _plain(value: Any) -> Any:
    """JSON-ready copy: arrays to lists, NaN/inf to None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_plain(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _transform(T: np.ndarray) -> Transform:
    return Transform(matrix=_plain(T), pose=_plain(ur_pose_from_matrix(T)))


def _provenance(command: str | None) -> dict[str, Any]:
    return {"software": Software(name="cellcal", version=software_version(), command=command),
            "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds")}


def result_of(calibration: Calibration, *, command: str | None = None) -> Result:
    """The result of what ``calib.calibrate`` returned; ``command`` says how it was asked for
    (the command line, or the service's request)."""
    if isinstance(calibration, PoseOnlyResult):
        return hand_eye_result(calibration.fit, list(calibration.station_ids),
                               options=calibration.options, command=command,
                               trust=calibration.trust)
    return calibration_result(calibration, command=command)


def hand_eye_result(result: HandEyeResult, station_ids: list[str], *,
                    options: dict[str, Any], command: str | None = None,
                    trust: Trust | None = None) -> Result:
    """The result of a pose-only hand-eye fit (no camera model)."""
    sigmas = result.sigmas if trust is None or trust.uncertainty is None \
        else trust.uncertainty.sigmas
    return Result(
        format=RESULT_FORMAT, setup=result.setup, camera=None,
        target=BoardScale(kappa=_plain(result.kappa), nu=1.0),
        hand_eye=_transform(result.hand_eye), target_pose=_transform(result.target_pose),
        uncertainty=Uncertainty.model_validate(_plain(
            {"note": f"1-sigma; {_FRAMES_NOTE}", **sigmas, **_uncertainty_extras(trust)})),
        noise_estimate=_plain(result.noise),
        stations=[StationFit(id=sid, residual_rot_rad=_plain(r[0]),
                             residual_trans_m=_plain(r[1]))
                  for sid, r in zip(station_ids, result.station_residuals, strict=True)],
        rejected=[], motions=Motions(used=result.motions_used, skipped=result.motions_skipped),
        method=result.method, options=_plain(options), **_evidence(trust),
        **_provenance(command))


def calibration_result(result: CalibrationResult, *, command: str | None = None) -> Result:
    """The result of an image-based calibration (``calib.pipeline``)."""
    camera_sigmas = {k: v for k, v in result.sigmas.items() if k in CAMERA_PARAMS}
    pose_sigmas = {k: v for k, v in result.sigmas.items() if k not in CAMERA_PARAMS}
    has_pose = result.hand_eye is not None
    return Result(
        format=RESULT_FORMAT, setup=result.setup,
        camera=CameraModel(image_size=list(result.image_size), K=_plain(result.K),
                           dist=_plain(result.dist), rms_px=_plain(result.rms_px),
                           sigma_px=_plain(result.sigma_px)),
        target=BoardScale(kappa=_plain(result.kappa), nu=_plain(result.nu),
                          kappa_sigma=_plain(camera_sigmas.get("kappa")),
                          nu_sigma=_plain(camera_sigmas.get("nu"))),
        hand_eye=_transform(result.hand_eye) if has_pose else None,
        target_pose=_transform(result.target_pose) if has_pose else None,
        robot_translation_map=_plain(result.robot_map),
        uncertainty=Uncertainty.model_validate(_plain({
            "note": "1-sigma from the Jacobian at the optimum, scaled by variance_factor; "
                    f"{_FRAMES_NOTE}; 0 = held fixed",
            "variance_factor": result.variance_factor, "camera": camera_sigmas,
            **pose_sigmas, **_uncertainty_extras(result.trust)})),
        stations=list(result.stations),
        rejected=[Rejected(id=sid, reason=reason) for sid, reason in result.rejected],
        validation=_plain(result.validation), method=result.method,
        options=_plain(result.options), **_evidence(result.trust), **_provenance(command))


# ---- evidence (product.md "Trust"): every block below is built here and only here ----------

def _evidence(trust: Trust | None) -> dict[str, Any]:
    """``cross_validation``, ``model_selection`` and ``quality`` of the result (none without
    ``trust``). Data in metres and radians like the rest of the result, plus millimetre and
    degree figures (names ending in ``_mm``, ``_deg``) for people reading the file."""
    if trust is None:
        return {}
    return {"cross_validation": None if trust.cross_validation is None
            else _cross_validation(trust.cross_validation),
            "model_selection": None if trust.model_selection is None
            else _selection(trust.model_selection),
            "quality": QualityBlock.model_validate(_plain(trust.quality.model_dump()))}


def _uncertainty_extras(trust: Trust | None) -> dict[str, Any]:
    """Fields merged into ``uncertainty``: the note saying which σ is reported, both figures."""
    if trust is None or trust.uncertainty is None:
        return {}
    u = trust.uncertainty
    return {"note": u.note, "jackknife_folds": u.folds, "source": u.source,
            "formal": u.formal, "jackknife": u.jackknife,
            **({"jackknife_expected": u.expected} if u.expected else {}),
            **({"held_at_one": list(u.held), "held_shift": u.shift, "held_bias": u.bias}
               if u.held else {}),
            **({"workspace_extrapolation": u.extrapolation} if u.extrapolation else {})}


def _mm(v: float | None) -> float | None:
    return None if v is None else _plain(1e3 * v)


def _deg(v: float | None) -> float | None:
    return None if v is None else _plain(np.degrees(v))


def _cross_validation(cv: CrossValidation) -> CrossValidationBlock:
    """A cross-validation as the result reports it: pixels, millimetres, degrees."""
    kept = cv.kept()
    return CrossValidationBlock(
        kind=cv.kind, folds=cv.folds, rms_px=_plain(cv.rms_px), rms_mm=_mm(cv.rms_m),
        rot_deg=_deg(cv.rot_rad), trans_mm=_mm(cv.trans_m), kept_rms_px=_plain(kept.rms_px),
        kept_rms_mm=_mm(kept.rms_m), dropped=list(cv.dropped),
        stations=[HeldOutStation(id=s.id, fold=s.fold, rms_px=_plain(s.rms_px),
                                 max_px=_plain(s.max_px), rms_mm=_mm(s.rms_m),
                                 rot_deg=_deg(s.rot_rad), trans_mm=_mm(s.trans_m),
                                 dropped=s.dropped)
                  for s in cv.stations],
        note=_CV_NOTE)


def _candidate(c: ModelCandidate, chosen: ModelCandidate) -> Candidate:
    cv = c.cv
    fields: dict[str, Any] = {"name": c.name, "chosen": c is chosen,
                              "cv_rms_px": _plain(cv.rms_px), "cv_rms_mm": _mm(cv.rms_m),
                              "cv_trans_mm": _mm(cv.trans_m), "cv_range_mm": _mm(cv.range_m),
                              "cv_rot_deg": _deg(cv.rot_rad)}
    m, fit = c.model, c.fit
    if m is not None and fit is not None:
        fields.update(kappa="held at 1" if "kappa" in m.fix else "estimated",
                      nu="held at 1" if "nu" in m.fix else "estimated",
                      robot_noise="estimated" if m.estimate_noise else "assumed",
                      kappa_value=_plain(fit.cell.kappa), nu_value=_plain(fit.cell.nu),
                      robot_noise_rot_rad=_plain(fit.noise.rot_rad),
                      robot_noise_trans_m=_plain(fit.noise.trans_m),
                      sigma_px=_plain(fit.sigma_px))
    return Candidate(**fields)


def _selection(sel: Selection) -> ModelSelection:
    return ModelSelection(chosen=sel.chosen.name, decisions=list(sel.decisions),
                          rule=SELECTION_RULE,
                          candidates=[_candidate(c, sel.chosen) for c in sel.candidates])
