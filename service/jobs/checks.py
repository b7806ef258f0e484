"""Re-checks of a calibration (``POST /calibrations/{id}/checks``): has the camera mount moved?

A check revisits stations of the calibration's run (or poses the caller gives), grabs and
detects the board at each, and compares what the camera sees with the prediction of the stored
calibration from the robot pose read after the grab (``calib.recheck``). The limits come from
the calibration's own cross-validated errors, so a result without cross-validation cannot be
checked (422). ``service.jobs.validations`` claims the robot and stores the report.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib import (
    Expected,
    StationCheck,
    StoredCell,
    Target,
    check_ur_poses,
    check_verdict,
    matrix_from_ur_pose,
)
from drivers.base import Camera, Robot
from drivers.capture import CaptureOptions, capture_station
from drivers.frozen import FrameWatch
from service.errors import UnprocessableError
from service.results.document import stored_cell
from service.schemas import CheckCreate

#: Stations revisited when the request names neither a number nor poses.
DEFAULT_STATIONS = 5


@dataclass(frozen=True)
class CheckPlan:
    """A checked re-check request: where to go and what to expect there."""

    cell: StoredCell
    expected: Expected
    poses: list[list[float]]  # commanded UR poses, T_base_tcp
    station_ids: list[int | None]  # the run's station index of each pose, or None


def check_plan(result: dict[str, Any], target: Target,
               stations: list[tuple[int, list[float]]], body: CheckCreate) -> CheckPlan:
    """Check a re-check request against a result document, the run's board and its captured
    stations (index, commanded pose) (422 if the calibration cannot be checked that way)."""
    cell, cv = stored_cell(result, target, use="A re-check"), result.get("cross_validation")
    if not cv or not all(cv.get(k) for k in ("rms_px", "rot_deg", "trans_mm")):
        raise UnprocessableError("A re-check takes its limits from the calibration's "
                                 "cross-validated errors, which this result does not have; "
                                 "calibrate again to get them.", code="no_cross_validation")
    expected = Expected(rms_px=float(cv["rms_px"]), rot_rad=float(np.radians(cv["rot_deg"])),
                        trans_m=1e-3 * float(cv["trans_mm"]))
    if body.poses is not None:
        try:
            check_ur_poses(np.asarray(body.poses, dtype=float), "poses")
        except ValueError as exc:
            raise UnprocessableError(str(exc), code="invalid_pose") from None
        poses, ids = body.poses, [None] * len(body.poses)
    else:
        n = body.stations or DEFAULT_STATIONS
        if len(stations) < n:
            raise UnprocessableError(f"stations: {n} asked, the calibration's run captured "
                                     f"{len(stations)}.", code="too_few_stations")
        picked = [stations[int(k)] for k in np.round(np.linspace(0, len(stations) - 1, n))]
        ids, poses = [index for index, _ in picked], [pose for _, pose in picked]
    return CheckPlan(cell=cell, expected=expected, poses=poses, station_ids=ids)


def run_check(robot: Robot, camera: Camera, plan: CheckPlan, options: CaptureOptions,
              report: Callable[[dict[str, Any]], None] = lambda event: None
              ) -> dict[str, Any]:
    """Visit the plan's poses, compare each view with the prediction; the report document.

    ``report`` gets a ``progress`` event after each station (station k of N and its state).
    A station where the board is not detected is reported with its reason and left out of
    the verdict; if none is left, the check fails (ValueError)."""
    stations: list[dict[str, Any]] = []
    seen: list[StationCheck] = []
    frames = FrameWatch()  # a frozen camera would look like a moved mount
    for pose, station_id in zip(plan.poses, plan.station_ids, strict=True):
        taken = capture_station(robot, camera, np.asarray(pose), options, frames)
        det = plan.cell.board.detect(taken.image)
        entry: dict[str, Any] = {"station": station_id, "pose": list(pose),
                                 "tcp_pose": [float(v) for v in taken.tcp_pose]}
        if not det.ok or det.corners is None:
            stations.append({**entry, "state": "not_detected", "reason": det.reason})
        else:
            check = plan.cell.check(matrix_from_ur_pose(taken.tcp_pose), det.corners,
                                    ids=det.ids, ambiguous=det.ambiguous)
            seen.append(check)
            stations.append({**entry, "state": plan.expected.station_state(check),
                             "rms_px": check.rms_px, "max_px": check.max_px,
                             "offset": {"rot_deg": float(np.degrees(check.rot_rad)),
                                        "trans_mm": 1e3 * check.trans_m}})
        k, n, state = len(stations), len(plan.poses), stations[-1]["state"]
        report({"type": "progress", "stage": "station", "step": k, "of": n,
                "station": station_id, "state": state,
                "message": f"station {k} of {n} checked: {state.replace('_', ' ')}"})
    if not seen:
        raise ValueError("The board was not detected at any of the checked stations: "
                         "is it still in place and lit?")
    v = check_verdict(seen, plan.expected)
    return {
        "kind": "check", "state": v.state,
        "offset": {"rot_deg": float(np.degrees(v.rot_rad)), "trans_mm": 1e3 * v.trans_m},
        "limits": {"rot_deg": float(np.degrees(v.rot_limit_rad)),
                   "trans_mm": 1e3 * v.trans_limit_m, "station_px": v.station_limit_px},
        "rms_px": v.rms_px,
        "expected": {"rms_px": plan.expected.rms_px,
                     "rot_deg": float(np.degrees(plan.expected.rot_rad)),
                     "trans_mm": 1e3 * plan.expected.trans_m},
        "stations": stations,
        "note": "offset: mean over the stations of the predicted camera pose against the "
                "observed one (a moved mount shifts every station alike); degraded when its "
                "rotation or translation is more than twice the calibration's cross-validated "
                "error of a single station. A station is degraded when its corner error "
                "(rms_px) exceeds limits.station_px.",
    }
