"""The result file (``cellcal/result@1``, product.md): estimate, uncertainty, provenance."""

from __future__ import annotations

import dataclasses
import datetime as dt
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import numpy as np

from calib import (
    CAMERA_PARAMS,
    CalibrationResult,
    HandEyeResult,
    StationReport,
    ur_pose_from_matrix,
)


def software_version() -> str:
    try:
        return version("cellcal")
    except PackageNotFoundError:
        return "unknown"


def _transform(T: np.ndarray) -> dict[str, Any]:
    return {"matrix": np.asarray(T).tolist(), "pose": ur_pose_from_matrix(T).tolist()}


def hand_eye_result_json(result: HandEyeResult, station_ids: list[str], *,
                         options: dict[str, Any], command: str | None = None) -> dict[str, Any]:
    """The result document of a pose-only hand-eye calibration (no camera model)."""
    uncertainty = {k: (np.asarray(v).tolist() if np.ndim(v) else float(v))
                   for k, v in result.sigmas.items()}
    return {
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
        },
        "noise_estimate": result.noise,
        "stations": [
            {"id": sid, "residual_rot_rad": float(r[0]), "residual_trans_m": float(r[1])}
            for sid, r in zip(station_ids, result.station_residuals, strict=True)],
        "rejected": [],
        "motions": {"used": result.motions_used, "skipped": result.motions_skipped},
        "method": result.method,
        "options": options,
        "software": {"name": "cellcal", "version": software_version(), "command": command},
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }


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
        "uncertainty": {
            "note": "1-sigma from the Jacobian at the optimum, scaled by variance_factor; "
                    "rotations as small angles (rad) about the axes of the frame named first "
                    "(tcp for hand_eye eye-in-hand), translations in metres; 0 = held fixed",
            "variance_factor": result.variance_factor,
            "camera": camera_sigmas,
            **pose_sigmas,
        },
        "stations": [_station_json(s) for s in result.stations],
        "rejected": [{"id": sid, "reason": reason} for sid, reason in result.rejected],
        "validation": result.validation,
        "method": result.method,
        "options": result.options,
        "software": {"name": "cellcal", "version": software_version(), "command": command},
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    })


def _station_json(station: StationReport) -> dict[str, Any]:
    """A station's report; corner positions and residuals to 0.001 px (far below their noise)
    to keep the file small."""
    doc = dataclasses.asdict(station)
    for key in ("corners_px", "residuals_px"):
        if doc[key] is not None:
            doc[key] = np.round(doc[key], 3)
    return doc
