"""The stored station (``StationRecord`` row, its ``detection`` JSON) and the one station model
(``calib.Station``), and a run's stored ``target`` and the one target type
(``calib.boards``): the service's converters at its storage boundary, written once.

A row keeps what the capture loop knows besides the station (state, commanded pose, attempts,
error code, time); the model keeps what the solver, a station-set file and a report need.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from typing import Any

import numpy as np
from sqlalchemy import Row
from sqlalchemy.orm import Session

from calib import Detection, Station, Stations, Target, TargetAdapter
from service.store import queries
from service.store.records import RunRecord, StationRecord


def detection_json(det: Detection) -> dict[str, Any]:
    """A detection as the ``detection`` column stores it (corners (N, 2) as lists)."""
    return {"ok": det.ok, "reason": det.reason, "sharpness": det.sharpness,
            "coverage": det.coverage, "mean_contrast": det.mean_contrast,
            "ambiguous": det.ambiguous,
            "corners": None if det.corners is None else det.corners.tolist(),
            "ids": None if det.ids is None else det.ids.tolist()}


def detection_of(doc: dict[str, Any]) -> Detection:
    """The stored ``detection`` column as a :class:`calib.Detection`; a row stored before
    point ids were kept holds a whole checkerboard (ids 0 .. N-1)."""
    corners, ids = doc.get("corners"), doc.get("ids")
    return Detection(ok=bool(doc["ok"]), reason=doc.get("reason"),
                     corners=None if corners is None else np.asarray(corners, dtype=float),
                     ids=None if ids is None else np.asarray(ids, dtype=np.int64),
                     sharpness=doc.get("sharpness"), coverage=doc.get("coverage", 0.0),
                     mean_contrast=doc.get("mean_contrast"),
                     ambiguous=bool(doc.get("ambiguous", False)))


def station_of(row: StationRecord) -> Station:
    """A stored station as the one station model; its id is the index, ``000``, ``001``, ...;
    ``image`` is relative to the data directory."""
    return Station(
        id=f"{row.index:03d}",
        T_base_tcp=None if row.tcp_pose is None else np.asarray(row.tcp_pose, dtype=float),
        image=row.image_path,
        image_size=None if row.image_size is None else (int(row.image_size[0]),
                                                        int(row.image_size[1])),
        detection=None if row.detection is None else detection_of(row.detection),
        rejected=row.error, freshness=row.freshness)


def row_values(station: Station) -> dict[str, Any]:
    """The columns of a stored row that the station model fills: ``state`` (``captured``
    unless rejected), ``tcp_pose``, ``image_size``, ``detection`` and ``error`` (the rejection
    reason) and ``freshness``; the capture adds the index, commanded pose, joints, image path,
    code, attempts."""
    T = station.T_base_tcp
    return {"state": "skipped" if station.rejected else "captured",
            "tcp_pose": None if T is None else [float(v) for v in T],
            "image_size": None if station.image_size is None else list(station.image_size),
            "detection": None if station.detection is None else detection_json(station.detection),
            "error": station.rejected, "freshness": station.freshness}


def run_target(run: RunRecord | Row[Any]) -> Target:
    """The run's stored ``target`` column (of its record or a row read with it) as the one
    target type (a configuration stored without ``type`` is a checkerboard); a
    ``queries.RUN_VIEW_COLUMNS`` row holds the column's JSON text (``target_of_text``)."""
    if isinstance(run.target, str):
        return target_of_text(run.target)
    return TargetAdapter.validate_python(run.target)


@functools.lru_cache(maxsize=256)
def target_of_text(text: str) -> Target:
    """A stored ``target`` column's JSON text as the one target type, parsed once per distinct
    text: a plant's runs store a few boards, and ``GET /runs`` parsed and validated one per
    run, 0.4 ms of a 50-run page (issue 21). Targets are frozen models, so runs that store
    the same text share one."""
    return TargetAdapter.validate_python(json.loads(text))


def target_json(target: Target) -> dict[str, Any]:
    """A target as the run's ``target`` column stores it."""
    return TargetAdapter.dump_python(target, mode="json")


def stations_of(run: RunRecord, rows: Sequence[StationRecord]) -> Stations:
    """A run's stations ``rows`` as a station set of the run's setup and target."""
    return Stations(setup=run.setup, target=run_target(run),
                    stations=tuple(station_of(r) for r in rows))


def captured_station_set(s: Session, *, run_id: str) -> Stations:
    """The run's captured stations, the ones a calibration of the run solves with (404 for an
    unknown run)."""
    return stations_of(queries.get_run(s, run_id=run_id),
                       queries.captured_stations(s, run_id=run_id))
