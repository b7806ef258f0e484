"""Every read the service makes, in one place: lookups (404 written once), listings, counts,
events and figures; the writes are in ``service.store.writes``.

Functions take the session first and everything else by keyword, so a run id is never passed
where a calibration id belongs. Reads leave the session as it is. Routers and managers call
these instead of writing SQL.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Row, Text, cast, func, select
from sqlalchemy.orm import Session

from service.errors import NotFoundError
from service.store.pages import Cursor, newest_first
from service.store.records import (
    ACTIVE_RUN_STATES,
    ActivationRecord,
    ActiveCalibrationRecord,
    CalibrationRecord,
    InstanceRecord,
    JobEventRecord,
    RunEventRecord,
    RunRecord,
    StationRecord,
    Topic,
    ValidationRecord,
)

# ---- lookups (404 for unknown ids) ---------------------------------------------------------


def get_run(s: Session, *, run_id: str) -> RunRecord:
    run = s.get(RunRecord, run_id)
    if run is None:
        raise NotFoundError(f"No run {run_id}.")
    return run


def get_calibration(s: Session, *, cal_id: str) -> CalibrationRecord:
    cal = s.get(CalibrationRecord, cal_id)
    if cal is None:
        raise NotFoundError(f"No calibration {cal_id}.")
    return cal


def get_validation(s: Session, *, val_id: str) -> ValidationRecord:
    val = s.get(ValidationRecord, val_id)
    if val is None:
        raise NotFoundError(f"No validation {val_id}.")
    return val


def get_station(s: Session, *, run_id: str, index: int) -> StationRecord:
    get_run(s, run_id=run_id)
    station = s.scalars(select(StationRecord).where(StationRecord.run_id == run_id,
                                                    StationRecord.index == index)).first()
    if station is None:
        raise NotFoundError(f"Run {run_id} has no station {index}.")
    return station


# ---- listings ------------------------------------------------------------------------------


def _stations_counted(*where: Any) -> Any:
    """The number of the listed run's stations matching ``where`` (from the stations'
    ``(run_id, state)`` index), as a column of a run listing."""
    return select(func.count()).where(StationRecord.run_id == RunRecord.id, *where) \
        .correlate(RunRecord).scalar_subquery()


#: The columns of a run's public view, by name: the row without its owner, identity and poses
#: (only how many there are) and its stations counted in the same statement, so a page of 50
#: runs is one statement of plain rows, no ORM objects and no stations loaded. The target is
#: its JSON text (``stations.target_of_text`` parses each distinct one once). ``errors`` counts
#: the stations with an error (from their partial index), so their errors are read only for
#: the runs that have some.
RUN_VIEW_COLUMNS = (RunRecord.id, RunRecord.state, RunRecord.mode, RunRecord.cell,
                    RunRecord.robot, RunRecord.setup, cast(RunRecord.target, Text).label("target"),
                    RunRecord.cold_start,
                    RunRecord.error, RunRecord.error_code, RunRecord.created_at,
                    RunRecord.updated_at, func.json_array_length(RunRecord.poses).label("poses"),
                    _stations_counted(StationRecord.state == "captured").label("captured"),
                    _stations_counted().label("stored"),
                    _stations_counted(StationRecord.error.is_not(None)).label("errors"))


def list_run_views(s: Session, *, limit: int, cursor: Cursor | None = None) -> list[Row[Any]]:
    """Runs as rows of ``RUN_VIEW_COLUMNS``, newest first, after ``cursor`` (the previous
    page's last)."""
    return list(s.execute(newest_first(select(*RUN_VIEW_COLUMNS), RunRecord, cursor=cursor,
                                       limit=limit)))


def get_run_view(s: Session, *, run_id: str) -> Row[Any]:
    """One run as a row of ``RUN_VIEW_COLUMNS`` (404 for an unknown id)."""
    row = s.execute(select(*RUN_VIEW_COLUMNS).where(RunRecord.id == run_id)).first()
    if row is None:
        raise NotFoundError(f"No run {run_id}.")
    return row


def list_stations(s: Session, *, run_id: str) -> list[StationRecord]:
    """The run's stored stations in index order (404 for an unknown run)."""
    return list(get_run(s, run_id=run_id).stations)


def captured_stations(s: Session, *, run_id: str) -> list[StationRecord]:
    """The run's stations with a usable detection, in index order."""
    return [st for st in list_stations(s, run_id=run_id) if st.state == "captured"]


def next_station_index(s: Session, *, run_id: str) -> int:
    """The index after the run's highest stored one (0 for none)."""
    return s.scalar(select(func.coalesce(func.max(StationRecord.index) + 1, 0))
                    .where(StationRecord.run_id == run_id)) or 0


def stored_indices(s: Session, *, run_id: str) -> set[int]:
    """Indices of the run's stored stations (captured or skipped)."""
    return set(s.scalars(select(StationRecord.index).where(StationRecord.run_id == run_id)))


def list_calibrations(s: Session, *, run_id: str) -> list[CalibrationRecord]:
    """The run's calibrations, oldest first (404 for an unknown run)."""
    get_run(s, run_id=run_id)
    return list(s.scalars(select(CalibrationRecord).where(CalibrationRecord.run_id == run_id)
                          .order_by(CalibrationRecord.created_at)))


def list_validations(s: Session, *, cal_id: str) -> list[ValidationRecord]:
    """The calibration's validations, oldest first (404 for an unknown calibration)."""
    get_calibration(s, cal_id=cal_id)
    return list(s.scalars(select(ValidationRecord).where(ValidationRecord.calibration_id == cal_id)
                          .order_by(ValidationRecord.created_at)))


@dataclass(frozen=True)
class CalibrationFilter:
    """Which calibrations ``GET /calibrations`` lists (None: any)."""

    run_id: str | None = None
    cell: str | None = None
    #: True: only calibrations current on their cell; False: only the others.
    active: bool | None = None
    state: str | None = None
    setup: str | None = None


#: The columns of a listed calibration (``CalibrationSummary``'s fields): the row's own
#: without its options and result documents, the solver asked for, its run's setup and robot,
#: the RMS reprojection error (px; None for pose-only results) and verdict read from the result
#: in SQL, and whether it is some cell's current calibration.
SUMMARY_COLUMNS = (CalibrationRecord.id, CalibrationRecord.run_id, CalibrationRecord.cell,
                   RunRecord.setup, RunRecord.robot, CalibrationRecord.state,
                   CalibrationRecord.options["method"].as_string().label("method"),
                   CalibrationRecord.result[("camera", "rms_px")].as_float().label("rms_px"),
                   CalibrationRecord.result[("quality", "verdict")].as_string().label("verdict"),
                   CalibrationRecord.id.in_(select(ActiveCalibrationRecord.calibration_id))
                   .label("active"),
                   CalibrationRecord.error, CalibrationRecord.error_code,
                   CalibrationRecord.created_at, CalibrationRecord.finished_at)


#: How far a listing counts its matches: a page says "more than 1,000" rather than read a
#: year of history to give the exact number.
COUNT_LIMIT = 1000


def page_calibrations(s: Session, *, where: CalibrationFilter, limit: int, offset: int,
                      cursor: Cursor | None = None) -> tuple[list[Row[Any]], int]:
    """One page of calibrations, newest first (after ``cursor``, the previous page's last,
    or skipping ``offset``), as rows of ``SUMMARY_COLUMNS`` (by name), and how many match,
    counted up to ``COUNT_LIMIT`` + 1 in the page's statement (more than ``COUNT_LIMIT``
    means "more than that"). Plain rows, no ORM objects, and no documents: the options and
    results stay in the database (only the method, RMS error and verdict are read), so pages
    stay small and cheap."""
    filters = [column == value for column, value in ((CalibrationRecord.run_id, where.run_id),
                                                     (CalibrationRecord.cell, where.cell),
                                                     (CalibrationRecord.state, where.state),
                                                     (RunRecord.setup, where.setup))
               if value is not None]
    if where.active is not None:
        current = select(ActiveCalibrationRecord.calibration_id)
        filters.append(CalibrationRecord.id.in_(current) if where.active
                       else CalibrationRecord.id.not_in(current))
    # counted from the calibrations alone unless the setup filter needs their runs, and no
    # further than one past the limit: a full count read every matching row, which grew
    # the listing's cost with the plant's history (issue 21, benchmarks/README.md)
    matching = select(CalibrationRecord.id)
    if where.setup is not None:
        matching = matching.join(RunRecord, RunRecord.id == CalibrationRecord.run_id)
    matching = matching.where(*filters).limit(COUNT_LIMIT + 1).subquery()
    counted = select(func.count()).select_from(matching)
    # the total rides along as a column of the page's own statement (an uncorrelated
    # subquery, evaluated once): one round trip instead of two, and on PostgreSQL each is a
    # wait for the database server and then for the GIL (issue 21, benchmarks/README.md)
    page = select(*SUMMARY_COLUMNS, counted.correlate(None).scalar_subquery().label("total")) \
        .join(RunRecord, RunRecord.id == CalibrationRecord.run_id)
    rows = s.execute(newest_first(page.where(*filters), CalibrationRecord, cursor=cursor,
                                  limit=limit).offset(offset)).all()
    total = rows[0].total if rows else s.scalar(counted) or 0  # past the end: counted alone
    return list(rows), total


# ---- which calibration is active -----------------------------------------------------------


def activations(s: Session, *, cell: str, setup: str,
                limit: int | None = None) -> list[ActivationRecord]:
    """The cell's activations for ``setup``, newest first (the first one is the current
    one)."""
    query = select(ActivationRecord) \
        .where(ActivationRecord.cell == cell, ActivationRecord.setup == setup) \
        .order_by(ActivationRecord.id.desc())
    return list(s.scalars(query if limit is None else query.limit(limit)))



# ---- counts --------------------------------------------------------------------------------


def run_counts(s: Session, *, run: RunRecord) -> dict[str, int]:
    """Stations planned, captured and skipped, counted in SQL (never loading the stations with
    their corners, so polling stays fast on long runs)."""
    return runs_counts(s, runs=[run])[run.id]


def planned_stations(poses: int, cold_start: dict[str, Any] | None) -> int:
    """The stations a run plans: its ``poses`` count, or a cold-start run's count or station
    limit."""
    if cold_start is None:
        return poses
    return int(cold_start["stations"] or cold_start["stop_rule"]["max_stations"])


def runs_counts(s: Session, *, runs: list[RunRecord]) -> dict[str, dict[str, int]]:
    """``run_counts`` of many runs in one query (a page of ``GET /runs``), by run id."""
    by_state: dict[str, dict[str, int]] = {run.id: {} for run in runs}
    for run_id, state, n in s.execute(
            select(StationRecord.run_id, StationRecord.state, func.count())
            .where(StationRecord.run_id.in_(list(by_state)))
            .group_by(StationRecord.run_id, StationRecord.state)):
        by_state[run_id][state] = n
    return {run.id: {"stations_planned": planned_stations(len(run.poses), run.cold_start),
                     "stations_captured": by_state[run.id].get("captured", 0),
                     "stations_skipped": sum(by_state[run.id].values())
                     - by_state[run.id].get("captured", 0)} for run in runs}


def station_errors(s: Session, *, run_id: str) -> list[tuple[int, str | None, str]]:
    """``(index, code, detail)`` of the run's stations that have an error, in index order."""
    return runs_station_errors(s, run_ids=[run_id])[run_id]


def runs_station_errors(s: Session, *, run_ids: list[str]
                        ) -> dict[str, list[tuple[int, str | None, str]]]:
    """``station_errors`` of many runs in one query, by run id."""
    errors: dict[str, list[tuple[int, str | None, str]]] = {run_id: [] for run_id in run_ids}
    for run_id, index, code, detail in s.execute(
            select(StationRecord.run_id, StationRecord.index, StationRecord.error_code,
                   StationRecord.error)
            .where(StationRecord.run_id.in_(run_ids), StationRecord.error.is_not(None))
            .order_by(StationRecord.run_id, StationRecord.index)):
        errors[run_id].append((index, code, detail))
    return errors


# ---- who has the robot ---------------------------------------------------------------------


def running_validation(s: Session, *, cell: str, robot: str) -> ValidationRecord | None:
    """The validation moving the cell's robot, if any (one whose worker has ended shows its
    outcome, ``service.jobs.outcomes``, even before the database has it, and holds nothing)."""
    return next((v for v in s.scalars(select(ValidationRecord).where(
        ValidationRecord.cell == cell, ValidationRecord.robot == robot,
        ValidationRecord.state == "running")) if v.state == "running"), None)


def active_run(s: Session, *, cell: str, robot: str) -> RunRecord | None:
    """The cell's robot's capturing or paused run, if any."""
    return s.scalars(select(RunRecord).where(RunRecord.cell == cell, RunRecord.robot == robot,
                                             RunRecord.state.in_(ACTIVE_RUN_STATES))).first()


def owns_run(s: Session, *, run_id: str, token: str) -> bool:
    """True while the capture thread ``token`` owns the run and it is capturing."""
    return s.scalar(select(func.count()).select_from(RunRecord).where(
        RunRecord.id == run_id, RunRecord.owner == token, RunRecord.state == "capturing")) == 1


# ---- service instances ---------------------------------------------------------------------


def instances(s: Session, *, cell: str) -> list[InstanceRecord]:
    """The cell's registered service instances."""
    return list(s.scalars(select(InstanceRecord).where(InstanceRecord.cell == cell)))


def get_instance(s: Session, *, instance_id: str | None) -> InstanceRecord | None:
    return None if instance_id is None else s.get(InstanceRecord, instance_id)


# ---- events of runs, calibrations and validations -----------------------------------------


def events_after(s: Session, *, topic: Topic, after: int) -> list[dict[str, Any]]:
    """The topic's stored events with an id above ``after``, in order, each with its ``id``."""
    table, where = _events_of(topic)
    rows = s.execute(select(table.id, table.data).where(*where, table.id > after)
                     .order_by(table.id)).all()
    return [{**data, "id": event_id} for event_id, data in rows]


def last_event_id(s: Session, *, topic: Topic) -> int:
    """The id of the topic's newest stored event (0 for none)."""
    table, where = _events_of(topic)
    return s.scalar(select(func.max(table.id)).where(*where)) or 0


def _events_of(topic: Topic) -> tuple[type[RunEventRecord] | type[JobEventRecord], list[Any]]:
    """The table holding the topic's events and the condition selecting them."""
    if topic.kind == "run":
        return RunEventRecord, [RunEventRecord.run_id == topic.id]
    return JobEventRecord, [JobEventRecord.kind == topic.kind, JobEventRecord.job_id == topic.id]


# ---- figures for GET /metrics --------------------------------------------------------------


@dataclass(frozen=True)
class LatestCalibration:
    """The newest finished calibration of a setup, as ``GET /metrics`` reports it."""

    setup: str
    finished_at: dt.datetime
    rms_px: float | None
    cv_rms_px: float | None
    verdict: str | None


@dataclass(frozen=True)
class ServiceFigures:
    """Counts and figures over the whole database (``service.metrics``)."""

    runs: dict[tuple[str, str], int]
    stations: dict[str, int]
    calibrations: dict[str, int]
    durations_s: list[float]
    latest: list[LatestCalibration]


def service_figures(s: Session) -> ServiceFigures:
    """Runs by (state, mode), stations and calibrations by state, the durations of finished
    calibrations and the newest finished calibration per setup (result fields read in SQL)."""
    runs = {(state, mode): n for state, mode, n in s.execute(
        select(RunRecord.state, RunRecord.mode, func.count())
        .group_by(RunRecord.state, RunRecord.mode)).all()}
    stations = dict(s.execute(select(StationRecord.state, func.count())
                              .group_by(StationRecord.state)).all())
    calibrations = dict(s.execute(select(CalibrationRecord.state, func.count())
                                  .group_by(CalibrationRecord.state)).all())
    done = (CalibrationRecord.state == "done", CalibrationRecord.finished_at.is_not(None))
    durations = [(end - start).total_seconds() for start, end in s.execute(
        select(CalibrationRecord.created_at, CalibrationRecord.finished_at).where(*done)).all()]
    newest = select(RunRecord.setup, func.max(CalibrationRecord.finished_at).label("at")) \
        .join(RunRecord, RunRecord.id == CalibrationRecord.run_id).where(*done) \
        .group_by(RunRecord.setup).subquery()
    rows = s.execute(
        select(RunRecord.setup, CalibrationRecord.finished_at,
               CalibrationRecord.result[("camera", "rms_px")].as_float(),
               CalibrationRecord.result[("cross_validation", "rms_px")].as_float(),
               CalibrationRecord.result[("quality", "verdict")].as_string())
        .join(RunRecord, RunRecord.id == CalibrationRecord.run_id)
        .join(newest, (newest.c.setup == RunRecord.setup)
              & (newest.c.at == CalibrationRecord.finished_at))
        .where(*done).order_by(RunRecord.setup)).all()
    latest = {row[0]: LatestCalibration(*row) for row in rows}  # one per setup on ties
    return ServiceFigures(runs=runs, stations=stations, calibrations=calibrations,
                          durations_s=durations, latest=list(latest.values()))
