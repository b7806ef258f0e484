"""Every write the service makes, in one place: the rows it adds (runs, stations,
calibrations, validations, events, activations, its own instance row), the conditional
updates the capture threads and the jobs rely on, and what it deletes.

Functions take the session first and everything else by keyword. Each commits, except the
claims (``claim_robot``, ``claim_run``), which lock a row for the caller's transaction. No
other module adds, merges or deletes a row (``service.store.queries`` reads).
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import delete, update
from sqlalchemy.dialects.postgresql import insert as postgresql_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.store.records import (
    ActivationRecord,
    ActiveCalibrationRecord,
    Base,
    CalibrationRecord,
    IdempotencyRecord,
    InstanceRecord,
    JobEventRecord,
    MotionClaimRecord,
    RunEventRecord,
    RunRecord,
    StationRecord,
    Topic,
    ValidationRecord,
    utcnow,
)

#: Why a run stopped when the service did (at shutdown, or found so at the next start).
INTERRUPTED = ("The service stopped while this run was capturing; resume it to continue from "
               "the next station.")


# ---- which calibration is active ----------------------------------------------------------------


def activate(s: Session, *, cal_id: str, cell: str, setup: str, robot: str) -> bool:
    """Make the calibration the cell's current one for ``setup``: the ``active_calibrations``
    row changes and a history row is added, in one transaction, unless it is current already.
    True if it changed.

    The row is written before anything is read (an insert that does nothing if the row
    exists, then an update conditional on another calibration being current), so of two
    services activating at once the second waits for the first and then sees its outcome:
    exactly one current calibration, and no history row for an activation that changed
    nothing.
    """
    created = _insert_if_absent(s, ActiveCalibrationRecord, cell=cell, setup=setup,
                                calibration_id=cal_id, activation_id=0)
    if not created and not s.execute(
            update(ActiveCalibrationRecord)
            .where(ActiveCalibrationRecord.cell == cell, ActiveCalibrationRecord.setup == setup,
                   ActiveCalibrationRecord.calibration_id != cal_id)
            .values(calibration_id=cal_id)).rowcount:
        s.commit()
        return False
    return _record_activation(s, cal_id=cal_id, cell=cell, setup=setup, robot=robot)


def _insert_if_absent(s: Session, model: type[Base], **values: Any) -> bool:
    """``INSERT ... ON CONFLICT DO NOTHING`` (SQLite and PostgreSQL); True if inserted. A
    conflicting row another transaction is inserting is waited for."""
    dialect = s.get_bind().dialect.name
    insert = postgresql_insert if dialect == "postgresql" else sqlite_insert
    key = next(iter(model.__table__.primary_key.columns))
    return s.execute(insert(model).values(**values).on_conflict_do_nothing()
                     .returning(key)).first() is not None


def _record_activation(s: Session, *, cal_id: str, cell: str, setup: str, robot: str) -> bool:
    """The history row of an activation the caller's transaction made; commits."""
    row = ActivationRecord(cell=cell, setup=setup, robot=robot, calibration_id=cal_id)
    s.add(row)
    s.flush()
    s.execute(update(ActiveCalibrationRecord).where(ActiveCalibrationRecord.cell == cell,
                                              ActiveCalibrationRecord.setup == setup)
              .values(activation_id=row.id))
    s.commit()
    return True


# ---- claims and conditional updates -------------------------------------------------------------


def claim_robot(s: Session, *, cell: str, robot: str, job: str, instance_id: str) -> None:
    """Write the cell's robot's ``motion_claims`` row first in the caller's transaction: its
    write lock keeps every other service's claim of that robot waiting until the caller
    commits, so the checks that follow and the claiming row are one step. Does not commit."""
    values = {"job": job, "instance_id": instance_id, "claimed_at": utcnow()}
    if not _insert_if_absent(s, MotionClaimRecord, cell=cell, robot=robot, **values):
        s.execute(update(MotionClaimRecord).where(MotionClaimRecord.cell == cell,
                                            MotionClaimRecord.robot == robot).values(**values))


def claim_run(s: Session, *, run_id: str, token: str) -> bool:
    """Lock the run row for this transaction if thread ``token`` owns the capturing run.

    An update, not a read: it takes the row's write lock (the whole database on SQLite), so a
    cancel, pause or takeover either commits before it (and the claim fails) or waits until
    the caller's transaction has committed. Does not commit.
    """
    return bool(s.execute(
        update(RunRecord).where(RunRecord.id == run_id, RunRecord.owner == token,
                                RunRecord.state == "capturing")
        .values(owner=token)).rowcount)


def move_run(s: Session, *, run_id: str, from_state: str, **values: Any) -> bool:
    """Set ``values`` on the run if it is still in ``from_state``; True if it changed."""
    changed = s.execute(update(RunRecord)
                        .where(RunRecord.id == run_id, RunRecord.state == from_state)
                        .values(**values)).rowcount
    s.commit()
    return bool(changed)


def finish_run(s: Session, *, run_id: str, token: str, **values: Any) -> bool:
    """End the run (``state``, ``error``, ``error_code``) if thread ``token`` still owns it;
    True if it did."""
    changed = s.execute(
        update(RunRecord).where(RunRecord.id == run_id, RunRecord.owner == token,
                                RunRecord.state == "capturing")
        .values(owner=None, **values)).rowcount
    s.commit()
    return bool(changed)


def finish_calibration(s: Session, *, cal_id: str, **values: Any) -> None:
    """Store a calibration's outcome (``state``, ``result`` or ``error`` and ``error_code``;
    ``finished_at`` defaults to now) if it is still running: one that a restart found failed
    stays failed."""
    s.execute(update(CalibrationRecord).where(CalibrationRecord.id == cal_id,
                                        CalibrationRecord.state == "running")
              .values(**{"finished_at": utcnow(), **values}))
    s.commit()


def finish_validation(s: Session, *, val_id: str, **values: Any) -> None:
    """Store a validation's outcome (``state``, ``result`` or ``error`` and ``error_code``;
    ``finished_at`` defaults to now) if it is still running."""
    s.execute(update(ValidationRecord)
              .where(ValidationRecord.id == val_id, ValidationRecord.state == "running")
              .values(**{"finished_at": utcnow(), **values}))
    s.commit()


def recover(s: Session, *, cell: str, live: set[str]) -> tuple[int, int, int]:
    """The cell's work whose service is not among the ``live`` instances: capturing runs
    become interrupted, running calibrations and validations failed; how many of each.
    Another cell's work and a live service's are not touched."""
    def orphaned(model: type[RunRecord] | type[CalibrationRecord] | type[ValidationRecord]) -> Any:
        return (model.cell == cell) & (model.instance_id.is_(None)
                                       | model.instance_id.not_in(live))

    runs = s.execute(
        update(RunRecord).where(RunRecord.state == "capturing", orphaned(RunRecord))
        .values(state="interrupted", owner=None, error_code="interrupted",
                error=INTERRUPTED)).rowcount
    cals = s.execute(
        update(CalibrationRecord)
        .where(CalibrationRecord.state == "running", orphaned(CalibrationRecord))
        .values(state="failed", finished_at=utcnow(), error_code="interrupted",
                error="The service stopped during the computation; start it again.")).rowcount
    vals = s.execute(
        update(ValidationRecord)
        .where(ValidationRecord.state == "running", orphaned(ValidationRecord))
        .values(state="failed", finished_at=utcnow(), error_code="interrupted",
                error="The service stopped during the validation; start it again.")).rowcount
    s.commit()
    return runs, cals, vals


# ---- service instances --------------------------------------------------------------------------


def renew_instance(s: Session, *, instance_id: str) -> bool:
    """Renew the instance's lease; False if its row is gone (taken for dead)."""
    changed = s.execute(update(InstanceRecord).where(InstanceRecord.id == instance_id)
                        .values(heartbeat_at=utcnow())).rowcount
    s.commit()
    return bool(changed)


def forget_instances(s: Session, *, cell: str, live: set[str],
                     only: set[str] | None = None) -> None:
    """Remove the cell's instance rows not in ``live`` (only those in ``only``, if given)."""
    query = delete(InstanceRecord).where(InstanceRecord.cell == cell,
                                         InstanceRecord.id.not_in(live))
    s.execute(query if only is None else query.where(InstanceRecord.id.in_(only)))
    s.commit()


# ---- events of runs, calibrations and validations -----------------------------------------------


def add_event(s: Session, *, topic: Topic, event: dict[str, Any]) -> int:
    """Store an event of ``topic``; its id, which increases along the topic's stream."""
    row: RunEventRecord | JobEventRecord = (
        RunEventRecord(run_id=topic.id, type=event["type"], data=event) if topic.kind == "run"
        else JobEventRecord(kind=topic.kind, job_id=topic.id, type=event["type"], data=event))
    s.add(row)
    s.commit()
    return row.id


# ---- new rows ------------------------------------------------------------------------------


def add_run(s: Session, **values: Any) -> RunRecord:
    """Store a new run (``RunRecord`` columns); IntegrityError if the robot has an active run
    already (the one-active-run index), after a rollback."""
    return _insert(s, RunRecord(**values))


def add_calibration(s: Session, **values: Any) -> CalibrationRecord:
    """Store a new calibration (``CalibrationRecord`` columns)."""
    return _insert(s, CalibrationRecord(**values))


def add_validation(s: Session, **values: Any) -> ValidationRecord:
    """Store a new validation (``ValidationRecord`` columns)."""
    return _insert(s, ValidationRecord(**values))


def add_station(s: Session, **values: Any) -> bool:
    """Store a station (``StationRecord`` columns) in the caller's transaction and commit;
    False if another capture thread stored that index first."""
    s.add(StationRecord(**values))
    try:
        s.commit()
    except IntegrityError:
        s.rollback()
        return False
    return True


def add_instance(s: Session, row: InstanceRecord) -> None:
    """Register this service's instance row."""
    _insert(s, row)


def restore_instance(s: Session, row: InstanceRecord) -> None:
    """Register this service's instance row again, with its id, after another service took it
    for dead and removed it."""
    s.merge(row)
    s.commit()


def reserve_idempotency_key(s: Session, row: IdempotencyRecord, *, keep: dt.timedelta,
                            abandoned: dt.timedelta) -> bool:
    """Reserve an Idempotency-Key for a request with ``row`` (``service.api.idempotency``):
    True when it is this request's now, False when another row holds it. Rows older than
    ``keep`` go first, and this key's reservation when its request never finished within
    ``abandoned``."""
    now = utcnow()
    s.execute(delete(IdempotencyRecord).where(IdempotencyRecord.created_at < now - keep))
    s.execute(delete(IdempotencyRecord).where(
        IdempotencyRecord.cell == row.cell, IdempotencyRecord.key == row.key,
        IdempotencyRecord.status.is_(None), IdempotencyRecord.created_at < now - abandoned))
    row.created_at = now
    try:
        _insert(s, row)
    except IntegrityError:
        return False
    return True


def settle_idempotency_key(s: Session, *, cell: str, key: str, status: int, body: str) -> None:
    """Keep a 2xx answer with its key; free the key after any other answer."""
    row = s.get(IdempotencyRecord, (cell, key))
    if row is None:
        return
    if 200 <= status < 300:
        row.status, row.body = status, body
    else:
        s.delete(row)
    s.commit()


def _insert(s: Session, row: Any) -> Any:
    s.add(row)
    try:
        s.commit()
    except IntegrityError:
        s.rollback()
        raise
    return row
