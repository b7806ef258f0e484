"""Stored state (SQLAlchemy 2 ORM): capture runs, their stations, calibrations, which
calibration is active, validations.

Images live as PNG files under the data directory; rows hold their paths relative to it.
Two constraints carry the service's guarantees, so they hold across threads, processes and
restarts: a station index is stored at most once per run (``uq_stations_run_index``: a resumed
run never duplicates a station), and a cell's robot has at most one active (capturing or
paused) run (``uq_runs_one_active_per_cell_robot``, a partial unique index).

Many cell services may share one database (a plant): every run, calibration, validation and
activation names its ``cell``; each service is an ``Instance`` with a heartbeat, and work in
flight names the instance that does it, so a restarted service recovers only a dead one's.
The schema is versioned (``service.migrations``): a change here needs a revision there.
"""

from __future__ import annotations

import datetime as dt
import uuid
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from sqlalchemy import (
    JSON,
    DateTime,
    ForeignKey,
    Index,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    text,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

#: Run states in which the robot belongs to the run.
ACTIVE_RUN_STATES = ("capturing", "paused")
#: Run states after which nothing more happens to a run unless someone resumes it.
FINAL_RUN_STATES = ("done", "failed", "cancelled", "interrupted")
RUN_STATES = ("capturing", "paused", "done", "failed", "cancelled", "interrupted")
STATION_STATES = ("captured", "skipped")
CALIBRATION_STATES = ("running", "done", "failed")
#: States after which a calibration or a validation changes no more.
FINAL_JOB_STATES = ("done", "failed")

_ACTIVE_SQL = text("state IN ('capturing', 'paused')")


def new_id() -> str:
    """An opaque, unguessable identifier (32 hex digits)."""
    return uuid.uuid4().hex


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class UTCDateTime(TypeDecorator[dt.datetime]):
    """A timestamp stored in UTC and read back timezone-aware (SQLite drops the zone)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None,
                           dialect: Dialect) -> dt.datetime | None:
        return None if value is None else value.astimezone(dt.UTC).replace(tzinfo=None)

    def process_result_value(self, value: dt.datetime | None,
                             dialect: Dialect) -> dt.datetime | None:
        return None if value is None else value.replace(tzinfo=dt.UTC)


class Base(DeclarativeBase):
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        dict[str, Any]: JSON, list[Any]: JSON, dt.datetime: UTCDateTime}


class RunRecord(Base):
    """A capture run: planned TCP poses visited in order, one station per pose; or, in
    ``external`` mode, the stations a cell controller posts."""

    __tablename__ = "runs"
    __table_args__ = (
        Index("uq_runs_one_active_per_cell_robot", "cell", "robot", unique=True,
              sqlite_where=_ACTIVE_SQL, postgresql_where=_ACTIVE_SQL),
        Index("ix_runs_created", "created_at", "id"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    cell: Mapped[str] = mapped_column(String(255))
    robot: Mapped[str] = mapped_column(String(255))
    state: Mapped[str] = mapped_column(String(16))
    #: ``robot``: the service moves the robot; ``external``: a cell controller posts stations.
    mode: Mapped[str] = mapped_column(String(16), default="robot", server_default="robot")
    setup: Mapped[str] = mapped_column(String(16))
    target: Mapped[dict[str, Any]]
    poses: Mapped[list[Any]]
    #: A run planned station by station from a cold start (``service.runs.coldstart``): its
    #: station count or stop rule, start pose, progress and stop reason; None otherwise.
    cold_start: Mapped[dict[str, Any] | None]
    #: The robot's model, serial number and controller version as its driver told them when
    #: the capture started (``drivers.base.RobotIdentity``); None for external runs.
    robot_identity: Mapped[dict[str, Any] | None]
    #: Token of the capture thread that may write stations; a new one on every (re)start.
    owner: Mapped[str | None] = mapped_column(String(32))
    #: The service instance whose thread captures (or whose controller posts) the stations.
    instance_id: Mapped[str | None] = mapped_column(String(32))
    error: Mapped[str | None] = mapped_column(Text)
    error_code: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(default=utcnow, onupdate=utcnow)

    stations: Mapped[list[StationRecord]] = relationship(
        back_populates="run", order_by="StationRecord.index", cascade="all, delete-orphan")


class StationRecord(Base):
    """One visited pose: the robot reading, the image file and the detection, or why not."""

    __tablename__ = "stations"
    __table_args__ = (
        UniqueConstraint("run_id", "index", name="uq_stations_run_index"),
        # a run's counts by state from the index alone; its errors without reading the rest
        Index("ix_stations_run_state", "run_id", "state"),
        Index("ix_stations_run_errors", "run_id", "index", sqlite_where=text("error IS NOT NULL"),
              postgresql_where=text("error IS NOT NULL")))

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    index: Mapped[int]
    state: Mapped[str] = mapped_column(String(16))
    #: The TCP pose the run commanded (stored in the column first named ``target_pose``,
    #: which is the board's pose in a result).
    commanded_tcp_pose: Mapped[list[Any]] = mapped_column("target_pose")
    tcp_pose: Mapped[list[Any] | None]
    #: Joint positions (rad) at the image, when known.
    joint_positions: Mapped[list[Any] | None]
    image_path: Mapped[str | None] = mapped_column(String(512))
    image_size: Mapped[list[Any] | None]
    #: ``ok``, ``reason``, quality metrics, ``ambiguous`` and ``corners`` (N, 2) pixels.
    detection: Mapped[dict[str, Any] | None]
    error: Mapped[str | None] = mapped_column(Text)
    error_code: Mapped[str | None] = mapped_column(String(64))
    #: How the camera made sure the image was exposed after the robot settled.
    freshness: Mapped[str | None] = mapped_column(Text)
    attempts: Mapped[int] = mapped_column(default=1)
    captured_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    run: Mapped[RunRecord] = relationship(back_populates="stations")


class CalibrationRecord(Base):
    """A solve over a run's captured stations; ``result`` is the ``cellcal/result@1`` JSON."""

    __tablename__ = "calibrations"
    __table_args__ = (Index("ix_calibrations_cell_created", "cell", "created_at", "id"),
                      Index("ix_calibrations_created", "created_at", "id"))

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    cell: Mapped[str] = mapped_column(String(255))
    #: The service instance that solves it.
    instance_id: Mapped[str | None] = mapped_column(String(32))
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    state: Mapped[str] = mapped_column(String(16))
    options: Mapped[dict[str, Any]]
    result: Mapped[dict[str, Any] | None]
    error: Mapped[str | None] = mapped_column(Text)
    #: Why it failed, for programs (``storage_unavailable``, a device fault's code, ...).
    error_code: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[dt.datetime | None]


class RunEventRecord(Base):
    """An event of a run as streamed (``GET /runs/{id}/events``); the row id is the stream's
    event id, so a listener resumes after it with ``Last-Event-ID``."""

    __tablename__ = "run_events"
    #: AUTOINCREMENT: SQLite never reuses an id, so ids only grow.
    __table_args__ = {"sqlite_autoincrement": True}  # noqa: RUF012

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    type: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict[str, Any]]
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


class JobEventRecord(Base):
    """An event of a calibration or a validation as streamed (``GET /calibrations/{id}/events``,
    ``GET /validations/{id}/events``); like ``RunEvent``, the row id is the stream's event id."""

    __tablename__ = "job_events"
    __table_args__ = (Index("ix_job_events_job", "kind", "job_id", "id"),
                      {"sqlite_autoincrement": True})

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    #: ``calibration`` or ``validation``.
    kind: Mapped[str] = mapped_column(String(16))
    job_id: Mapped[str] = mapped_column(String(32))
    type: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict[str, Any]]
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


@dataclass(frozen=True)
class Topic:
    """What an event stream follows: a run, a calibration or a validation, by its id."""

    kind: Literal["run", "calibration", "validation"]
    id: str


class ActivationRecord(Base):
    """A calibration made a cell's current one for its setup at ``activated_at``; it stays
    current until the next activation of that cell and setup, so the rows are the history of
    what was active when."""

    __tablename__ = "activations"
    __table_args__ = (Index("ix_activations_robot_id", "robot", "id"),
                      Index("ix_activations_cell_setup_id", "cell", "setup", "id"))

    #: Increasing, so activations at the same instant keep the order they were made in.
    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    cell: Mapped[str] = mapped_column(String(255))
    setup: Mapped[str] = mapped_column(String(16))
    robot: Mapped[str] = mapped_column(String(255))
    calibration_id: Mapped[str] = mapped_column(
        ForeignKey("calibrations.id", ondelete="CASCADE"), index=True)
    activated_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


class ValidationRecord(Base):
    """A validation of a calibration (dot-hit run, pose prediction), with its report."""

    __tablename__ = "validations"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    cell: Mapped[str] = mapped_column(String(255))
    #: The robot it moves (dot-hit) or reads (pose prediction).
    robot: Mapped[str] = mapped_column(String(255))
    #: The service instance that runs it.
    instance_id: Mapped[str | None] = mapped_column(String(32))
    calibration_id: Mapped[str] = mapped_column(
        ForeignKey("calibrations.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16))
    result: Mapped[dict[str, Any] | None]
    error: Mapped[str | None] = mapped_column(Text)
    #: Why it failed, for programs (``storage_unavailable``, a device fault's code, ...).
    error_code: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[dt.datetime | None]


class ActiveCalibrationRecord(Base):
    """The calibration active now on a cell for a setup, and the ``Activation`` that made it
    so; one row per cell and setup, updated in the same transaction as the history row."""

    __tablename__ = "active_calibrations"

    cell: Mapped[str] = mapped_column(String(255), primary_key=True)
    setup: Mapped[str] = mapped_column(String(16), primary_key=True)
    calibration_id: Mapped[str] = mapped_column(
        ForeignKey("calibrations.id", ondelete="CASCADE"), index=True)
    activation_id: Mapped[int]


class InstanceRecord(Base):
    """A running service: where it listens and its heartbeat. Its lease lasts until
    ``heartbeat_at`` plus the lease time; work whose instance's lease ran out is recovered."""

    __tablename__ = "instances"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    cell: Mapped[str] = mapped_column(String(255))
    host: Mapped[str] = mapped_column(String(255))
    port: Mapped[int]
    pid: Mapped[int]
    started_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    heartbeat_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


class IdempotencyRecord(Base):
    """A request that started work under an ``Idempotency-Key`` (``service.api.idempotency``):
    the hash of what was asked and, once answered, the answer, so the same request repeated
    gets the first answer from any instance, also after a restart. ``status`` is None while the
    first request is being answered."""

    __tablename__ = "idempotency_keys"

    cell: Mapped[str] = mapped_column(String(255), primary_key=True)
    key: Mapped[str] = mapped_column(String(255), primary_key=True)
    #: SHA-256 (hex) of the method, the path and the body.
    request_hash: Mapped[str] = mapped_column(String(64))
    status: Mapped[int | None]
    body: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow, index=True)


class MotionClaimRecord(Base):
    """The row a job that moves a cell's robot (a capture run, a dot-hit validation) updates
    first in the transaction that stores it: the database's lock on that robot, so the check
    that it is free and the claim are one step across every service, and the last claim."""

    __tablename__ = "motion_claims"

    cell: Mapped[str] = mapped_column(String(255), primary_key=True)
    robot: Mapped[str] = mapped_column(String(255), primary_key=True)
    job: Mapped[str | None] = mapped_column(String(64))
    instance_id: Mapped[str | None] = mapped_column(String(32))
    claimed_at: Mapped[dt.datetime | None]
