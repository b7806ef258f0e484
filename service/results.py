"""The result file (``cellcal/result@1``, product.md): estimate, uncertainty, provenance."""

from __future__ import annotations

import datetime as dt
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import numpy as np

from calib.geometry import ur_pose_from_matrix
from calib.handeye import HandEyeResult


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
