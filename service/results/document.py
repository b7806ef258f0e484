"""The result file (``cellcal/result@1``, product.md): estimate, uncertainty, provenance; and a
stored result read back as the cell it describes (:func:`stored_cell`)."""

from __future__ import annotations

import datetime as dt
from typing import Any

import numpy as np

from calib import (
    CAMERA_PARAMS,
    SELECTION_RULE,
    CalibrationResult,
    CrossValidation,
    HandEyeResult,
    ModelCandidate,
    PoseError,
    Selection,
    StationReport,
    StoredCell,
    Target,
    Trust,
    board_from_target,
    ur_pose_from_matrix,
)
from service.errors import UnprocessableError
from service.version import software_version


def stored_cell(result: dict[str, Any], target: Target, *, use: str) -> StoredCell:
    """The cell a stored result document describes (camera, hand-eye, target pose) with the
    run's board at the calibrated κ, ν: what a validation (``use``, said in the 422 message)
    tests against. 422 ``incomplete_result`` for a result without a camera model."""
    camera, hand_eye, target_pose = (result.get(k) for k in ("camera", "hand_eye",
                                                              "target_pose"))
    if not camera or not hand_eye or not target_pose:
        raise UnprocessableError(f"{use} compares the board with the calibration's camera "
                                 "model, hand-eye and target pose; this result has none "
                                 "(pose-only).", code="incomplete_result")
    return StoredCell(setup=result["setup"], K=np.asarray(camera["K"], dtype=float),
                      dist=np.asarray(camera["dist"], dtype=float),
                      hand_eye=np.asarray(hand_eye["matrix"], dtype=float),
                      target_pose=np.asarray(target_pose["matrix"], dtype=float),
                      board=board_from_target(target), kappa=float(result["target"]["kappa"]),
                      nu=float(result["target"]["nu"]),
                      robot_map=None if result.get("robot_translation_map") is None
                      else np.asarray(result["robot_translation_map"], dtype=float))


def _transform(T: np.ndarray) -> dict[str, Any]:
    return {"matrix": np.asarray(T).tolist(), "pose": ur_pose_from_matrix(T).tolist()}


def hand_eye_result_json(result: HandEyeResult, station_ids: list[str], *,
                         options: dict[str, Any], command: str | None = None,
                         trust: Trust | None = None) -> dict[str, Any]:
    """The result document of a pose-only hand-eye calibration (no camera model)."""
    sigmas = result.sigmas if trust is None or trust.uncertainty is None \
        else trust.uncertainty.sigmas
    uncertainty = {k: (np.asarray(v).tolist() if np.ndim(v) else float(v))
                   for k, v in sigmas.items()}
    return _plain({
        "format": "cellcal/result@1",
        "setup": result.setup,
        "camera": None,
        "target": {"kappa": result.kappa, "nu": 1.0},
        "hand_eye": _transform(result.hand_eye),
        "target_pose": _transform(result.target_pose),
        "uncertainty": {
            "note": "1-sigma; rotations as small angles (rad) about the axes of the frame "
                    "named first (tcp for hand_eye eye-in-hand), translations in metres",
            **uncertainty,
            **uncertainty_extras(trust),
        },
        "noise_estimate": result.noise,
        "stations": [
            {"id": sid, "residual_rot_rad": float(r[0]), "residual_trans_m": float(r[1])}
            for sid, r in zip(station_ids, result.station_residuals, strict=True)],
        "rejected": [],
        "motions": {"used": result.motions_used, "skipped": result.motions_skipped},
        "method": result.method,
        "options": options,
        **trust_json(trust),
        "software": {"name": "cellcal", "version": software_version(), "command": command},
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    })


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


def calibration_result_json(result: CalibrationResult, *,
                            command: str | None = None) -> dict[str, Any]:
    """The result document of an image-based calibration (``calib.pipeline``)."""
    camera_sigmas = {k: v for k, v in result.sigmas.items() if k in CAMERA_PARAMS}
    pose_sigmas = {k: v for k, v in result.sigmas.items() if k not in CAMERA_PARAMS}
    has_pose = result.hand_eye is not None
    return _plain({
        "format": "cellcal/result@1",
        "setup": result.setup,
        "camera": {"image_size": list(result.image_size), "K": result.K, "dist": result.dist,
                   "rms_px": result.rms_px, "sigma_px": result.sigma_px},
        "target": {"kappa": result.kappa, "nu": result.nu,
                   "kappa_sigma": result.sigmas.get("kappa"),
                   "nu_sigma": result.sigmas.get("nu")},
        "hand_eye": _transform(result.hand_eye) if has_pose else None,
        "target_pose": _transform(result.target_pose) if has_pose else None,
        "robot_translation_map": result.robot_map,
        "uncertainty": {
            "note": "1-sigma from the Jacobian at the optimum, scaled by variance_factor; "
                    "rotations as small angles (rad) about the axes of the frame named first "
                    "(tcp for hand_eye eye-in-hand), translations in metres; 0 = held fixed",
            "variance_factor": result.variance_factor,
            "camera": camera_sigmas,
            **pose_sigmas,
            **uncertainty_extras(result.trust),
        },
        "stations": [_station_json(s) for s in result.stations],
        "rejected": [{"id": sid, "reason": reason} for sid, reason in result.rejected],
        "validation": result.validation,
        "method": result.method,
        "options": result.options,
        **trust_json(result.trust),
        "software": {"name": "cellcal", "version": software_version(), "command": command},
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    })


def _station_json(station: StationReport) -> dict[str, Any]:
    """A station's report; corner positions and residuals to 0.001 px (far below their noise)
    to keep the file small."""
    return {"id": station.id, "n_corners": station.n_corners, "rms_px": station.rms_px,
            "chain_rms_px": station.chain_rms_px,
            **_pose_error_json("correction", station.correction),
            "mahalanobis": station.mahalanobis, **_pose_error_json("loo", station.loo),
            "point_ids": None if station.point_ids is None else station.point_ids.tolist(),
            "corners_px": np.round(station.corners_px, 3),
            "residuals_px": np.round(station.residuals_px, 3)}


def _pose_error_json(name: str, error: PoseError | None) -> dict[str, float | None]:
    """``NAME_rot_rad`` and ``NAME_trans_m`` of a pose difference (None when there is none)."""
    return {f"{name}_rot_rad": None if error is None else error.rot_rad,
            f"{name}_trans_m": None if error is None else error.trans_m}


# ---- evidence (product.md "Trust"): every field below is built here and only here ----------

def trust_json(trust: Trust | None) -> dict[str, Any]:
    """``cross_validation``, ``model_selection``, ``quality`` and the ``uncertainty`` extras.

    Data in metres and radians like the rest of the document, plus millimetre and degree
    figures (names ending in ``_mm``, ``_deg``) for people reading the file.
    """
    if trust is None:
        return {}
    out: dict[str, Any] = {
        "cross_validation": None if trust.cross_validation is None
        else cross_validation_json(trust.cross_validation),
        "model_selection": None if trust.model_selection is None
        else _selection_json(trust.model_selection),
        "quality": None if trust.quality is None else {
            "verdict": trust.quality.verdict,
            "findings": [{"code": f.code, "severity": f.severity, "message": f.message,
                          **f.values} for f in trust.quality.findings]},
    }
    return out


def uncertainty_extras(trust: Trust | None) -> dict[str, Any]:
    """Fields merged into ``uncertainty``: the note saying which σ is reported, both figures."""
    if trust is None or trust.uncertainty is None:
        return {}
    u = trust.uncertainty
    return {"note": u.note, "jackknife_folds": u.folds, "source": u.source,
            "formal": u.formal, "jackknife": u.jackknife}


def cross_validation_json(cv: CrossValidation) -> dict[str, Any]:
    def mm(v: float | None) -> float | None:
        return None if v is None else 1e3 * v

    def deg(v: float | None) -> float | None:
        return None if v is None else float(np.degrees(v))

    kept = cv.kept()
    return {
        "kind": cv.kind, "folds": cv.folds,
        "rms_px": cv.rms_px, "rms_mm": mm(cv.rms_m),
        "rot_deg": deg(cv.rot_rad), "trans_mm": mm(cv.trans_m),
        "kept_rms_px": kept.rms_px, "kept_rms_mm": mm(kept.rms_m),
        "dropped": list(cv.dropped),
        "stations": [{"id": s.id, "fold": s.fold, "rms_px": s.rms_px, "max_px": s.max_px,
                      "rms_mm": mm(s.rms_m), "rot_deg": deg(s.rot_rad),
                      "trans_mm": mm(s.trans_m), "dropped": s.dropped}
                     for s in cv.stations],
        "note": "each station predicted from its robot pose alone by the estimator fitted on "
                "the other folds; the figures cover every station whose board was detected, "
                "the stations the fit dropped as outliers included (each predicted by the "
                "fold that held it out); kept_rms_px: the kept stations only; rms_mm: corner "
                "error on the board plane; rot_deg/trans_mm: predicted vs observed "
                "cam_T_target",
    }


def _candidate_json(c: ModelCandidate, chosen: ModelCandidate) -> dict[str, Any]:
    cv = c.cv
    out: dict[str, Any] = {"name": c.name, "chosen": c is chosen, "cv_rms_px": cv.rms_px,
                           "cv_rms_mm": None if cv.rms_m is None else 1e3 * cv.rms_m,
                           "cv_trans_mm": None if cv.trans_m is None else 1e3 * cv.trans_m,
                           "cv_range_mm": None if cv.range_m is None else 1e3 * cv.range_m,
                           "cv_rot_deg": None if cv.rot_rad is None
                           else float(np.degrees(cv.rot_rad))}
    m, fit = c.model, c.fit
    if m is not None and fit is not None:
        out.update(kappa="held at 1" if "kappa" in m.fix else "estimated",
                   nu="held at 1" if "nu" in m.fix else "estimated",
                   robot_noise="estimated" if m.estimate_noise else "assumed",
                   kappa_value=fit.cell.kappa, nu_value=fit.cell.nu,
                   robot_noise_rot_rad=fit.noise.rot_rad,
                   robot_noise_trans_m=fit.noise.trans_m, sigma_px=fit.sigma_px)
    return out


def _selection_json(sel: Selection) -> dict[str, Any]:
    return {"chosen": sel.chosen.name, "decisions": list(sel.decisions),
            "rule": SELECTION_RULE,
            "candidates": [_candidate_json(c, sel.chosen) for c in sel.candidates]}
