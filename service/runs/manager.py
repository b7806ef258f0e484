"""Capture runs: create (plan, claim the robot, start the capture thread), pause, cancel,
resume, and the run's ``state`` event; external runs (no capture thread: a cell controller
posts the stations, ``service.runs.external``) are finished by their controller."""

from __future__ import annotations

from sqlalchemy.exc import IntegrityError

from service.cell.motion import Motion, MotionJobs
from service.errors import ConflictError
from service.events import EventBus
from service.runs.capture import Capture
from service.runs.coldstart import ColdStartCapture
from service.runs.external import ExternalStations
from service.runs.planning import (
    check_poses,
    check_station_count,
    cold_start_plan,
    informed_backend,
    plan_poses,
)
from service.schemas import RunCreate
from service.serving.logs import lifecycle
from service.store import queries, writes
from service.store.records import RunRecord, Topic, new_id
from service.store.stations import target_json


class RunManager(MotionJobs):
    """Starts and steers capture runs; the stored run row is the source of truth."""

    def __init__(self, motion: Motion, events: EventBus) -> None:
        super().__init__(motion, events)
        #: Stations posted to external runs.
        self.external = ExternalStations(motion, events)

    def create(self, body: RunCreate) -> RunRecord:
        """Validate the plan, store the run and start capturing; 409 if the robot is busy,
        503 while the data directory takes no writes."""
        self.motion.storage.check()
        target = body.target or self.settings.run_target()
        setup = self.settings.calibration_setup()
        cold_start = None
        poses: list[list[float]] = []
        if body.poses is not None:
            poses = check_poses(self.motion, body.poses)
        elif body.mode == "robot":
            self.motion.check_free()
            rule = body.stop_rule
            if rule is not None and body.max_stations is None:  # the default, within the limit
                rule.max_stations = min(rule.max_stations, self.settings.max_stations)
            check_station_count(self.motion, rule.max_stations if rule else body.stations or 0)
            if rule is None and informed_backend(self.motion):
                assert body.stations is not None
                poses = check_poses(self.motion, plan_poses(self.motion, n=body.stations,
                                                            target=target, setup=setup))
            else:
                cold_start = cold_start_plan(
                    self.motion, target=target, stations=body.stations,
                    stop_rule=None if rule is None else rule.model_dump())
        token = new_id()
        run_id = new_id()
        with self.motion.claim(f"run {run_id}") as s:
            try:
                run = writes.add_run(s, id=run_id, cell=self.settings.cell,
                                     robot=self.settings.robot, state="capturing", owner=token,
                                     instance_id=self.motion.instance_id, setup=setup,
                                     target=target_json(target), poses=poses, mode=body.mode,
                                     cold_start=cold_start)
            except IntegrityError:
                raise self.motion.busy() from None
        lifecycle("created", "run", run.id, mode=run.mode, stations_planned=len(poses) or None)
        if run.mode == "robot":
            self._start_capture(run.id, token, cold=cold_start is not None)
        return run

    def pause(self, run_id: str) -> None:
        """Stop after the station in progress; idempotent on a paused run."""
        self._transition(run_id, ("capturing",), "paused", same_ok="paused")

    def cancel(self, run_id: str) -> None:
        """Give up a run for good; the robot is stopped if this run is moving it."""
        token = self._transition(run_id, ("capturing", "paused", "interrupted", "failed"),
                                 "cancelled", same_ok="cancelled")
        if token is not None:
            self.motion.stop_if_moving(token)

    def resume(self, run_id: str) -> None:
        """Continue a paused, interrupted or failed run at its first missing station."""
        token = new_id()
        with self.motion.claim(f"run {run_id}", check=False) as s:
            run = queries.get_run(s, run_id=run_id)
            if run.state == "capturing":
                return
            if run.state not in ("paused", "interrupted", "failed"):
                raise ConflictError(f"Run {run_id} is {run.state}; only a paused, interrupted "
                                    "or failed run can be resumed.", code="invalid_state")
            if run.cell != self.settings.cell or run.robot != self.settings.robot:
                raise ConflictError(f"Run {run_id} belongs to robot {run.robot} of cell "
                                    f"{run.cell}; resume it on that cell's service.",
                                    code="other_cell")
            if queries.running_validation(s, cell=run.cell, robot=run.robot) is not None:
                raise self.motion.busy(s)
            try:
                changed = writes.move_run(s, run_id=run_id, from_state=run.state,
                                         state="capturing", owner=token, error=None,
                                         error_code=None, instance_id=self.motion.instance_id)
            except IntegrityError:
                s.rollback()
                raise self.motion.busy() from None
        if not changed:
            raise ConflictError(f"Run {run_id} changed state meanwhile; read it and retry.",
                                code="invalid_state")
        self.events.publish_state(Topic("run", run_id))
        if run.mode == "robot":
            self._start_capture(run_id, token, cold=run.cold_start is not None)

    def finish(self, run_id: str) -> None:
        """End an external run: it takes no more stations and can be calibrated; idempotent
        on a finished run. A robot run finishes by itself after its last station."""
        with self.db.session() as s:
            if queries.get_run(s, run_id=run_id).mode != "external":
                raise ConflictError(f"Run {run_id} is driven by the service; it is done after "
                                    "its last station (pause or cancel it to stop it).",
                                    code="invalid_mode")
        self._transition(run_id, ("capturing", "paused", "interrupted"), "done",
                         same_ok="done")

    def _transition(self, run_id: str, sources: tuple[str, ...], target: str, *,
                    same_ok: str) -> str | None:
        """Move a run from one of ``sources`` to ``target`` and publish its state (one
        ``EventBus.finish`` step); the old owner token."""
        owners: list[str | None] = []

        def save() -> bool:
            with self.db.session() as s:
                run = queries.get_run(s, run_id=run_id)
                if run.state == same_ok:
                    return False
                if run.state not in sources:
                    raise ConflictError(f"Run {run_id} is {run.state}; it cannot become "
                                        f"{target}.", code="invalid_state")
                owners.append(run.owner)
                changed = writes.move_run(s, run_id=run_id, from_state=run.state,
                                         state=target, owner=None)
            if not changed:
                raise ConflictError(f"Run {run_id} changed state meanwhile; read it and retry.",
                                    code="invalid_state")
            return True

        self.events.finish(Topic("run", run_id), save)
        return owners[0] if owners else None

    def _start_capture(self, run_id: str, token: str, *, cold: bool) -> None:
        kind = ColdStartCapture if cold else Capture
        capture = kind(self.motion, self.events, run_id=run_id, token=token)
        self.motion.start(token, capture.run, name=f"capture-{run_id[:8]}")
