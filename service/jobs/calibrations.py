"""Calibrations: start a solve over a run's captured stations, compute it in a worker process,
store the outcome when it completes.

Calibrations are CPU-bound: they run in worker processes (``service.jobs.workers``: they exit with
the service, however it dies) so the API stays responsive, and the result is stored when the
future completes. At most ``Settings.max_queued_calibrations`` solves wait or run at a time;
beyond, a request is refused (429 ``queue_full``) instead of piling up work and memory.

A solve's progress (the board detected station by station, then the stages of
``calib.calibrate``) comes back from the worker as ``progress`` events of the
calibration's stream (``GET /calibrations/{id}/events``), which ends with its final ``state``;
a progress message that arrives after the outcome is stored is dropped, so none follows it.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import threading
from dataclasses import dataclass
from typing import Any

from calib import MIN_IMAGES, Result
from service.errors import ConflictError, QueueFullError, UnprocessableError
from service.events import EventBus
from service.jobs.outcomes import Outcomes
from service.jobs.solve import SolveJob, SolveProgress, solve_calibration
from service.jobs.workers import WorkerPool
from service.results.report_cache import Reports
from service.schemas import CalibrationOptions
from service.serving.logs import lifecycle
from service.settings import Settings
from service.store import queries, writes
from service.store.db import Database
from service.store.records import CalibrationRecord, Topic
from service.store.stations import captured_station_set

log = logging.getLogger("cellcal.service")


class Calibrations:
    """Queues solves in worker processes and records their results."""

    def __init__(self, settings: Settings, db: Database, events: EventBus,
                 instance_id: str, outcomes: Outcomes) -> None:
        self.settings = settings
        self.db = db
        self.events = events
        #: This service's instance: the calibrations it solves name it.
        self.instance_id = instance_id
        self.outcomes = outcomes
        #: Their reports, rendered once in a worker process and kept.
        self.reports = Reports(settings)
        self._pool: WorkerPool | None = None
        self._pool_lock = threading.Lock()
        self._pending = 0  # solves queued or running, under _pool_lock
        self._ending: dict[str, _Ending] = {}  # solves not yet stored, under _events_lock
        self._events_lock = threading.Lock()

    def start(self, run_id: str, options: CalibrationOptions) -> CalibrationRecord:
        """Queue a solve over the run's captured stations in a worker process (429 when
        ``max_queued_calibrations`` are already queued or running)."""
        self._reserve()
        try:
            cal, job = self._create(run_id, options)
            with self._events_lock:
                self._ending[cal.id] = _Ending()
            future = self._submit(job)
        except BaseException:
            self._release()
            raise
        future.add_done_callback(lambda f: self._done(cal.id, f))
        lifecycle("started", "calibration", cal.id, run_id=run_id,
                  method=options.method, stations=len(job.stations.stations))
        return cal

    def _reserve(self) -> None:
        with self._pool_lock:
            limit = self.settings.max_queued_calibrations
            if self._pending >= limit:
                raise QueueFullError(
                    f"{self._pending} calibrations are already queued or running, the limit "
                    "(CELLCAL_MAX_QUEUED_CALIBRATIONS); retry when one has finished.")
            self._pending += 1

    def _release(self) -> None:
        with self._pool_lock:
            self._pending -= 1

    def _create(self, run_id: str, options: CalibrationOptions
                ) -> tuple[CalibrationRecord, SolveJob]:
        """The calibration row (committed) and the worker's job."""
        with self.db.session() as s:
            run = queries.get_run(s, run_id=run_id)
            if run.state == "capturing":
                raise ConflictError(f"Run {run_id} is still capturing; pause it or wait until "
                                    "it is done.", code="invalid_state")
            stations = captured_station_set(s, run_id=run_id)
            if len(stations.stations) < MIN_IMAGES:
                raise UnprocessableError(
                    f"Run {run_id} has {len(stations.stations)} captured stations; a "
                    f"calibration needs at least {MIN_IMAGES}.", code="too_few_stations")
            cal = writes.add_calibration(s, run_id=run_id, cell=run.cell,
                                         instance_id=self.instance_id, state="running",
                                         options=options.model_dump())
            solver = options.solver()
            if run.cold_start is not None:
                solver = self.settings.cold_start_solver(solver,
                                                         run.cold_start.get("stop_rule"))
            job = SolveJob(cal_id=cal.id, run_id=run_id, stations=stations, options=solver)
        return cal, job

    def shutdown(self) -> None:
        """Cancel queued solves and let the worker processes go; no more progress is read,
        so a solve that still completes is stored without waiting for its last message."""
        with self._events_lock:
            for ending in self._ending.values():
                ending.progress_ended = True
        with self._pool_lock:
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None
        self.reports.shutdown()

    def _submit(self, job: SolveJob) -> cf.Future[Result]:
        with self._pool_lock:
            if self._pool is None:
                self._pool = WorkerPool(self.settings.calibration_workers,
                                             self._progress)
            return self._pool.submit(solve_calibration, job)

    def _done(self, cal_id: str, future: cf.Future[Result]) -> None:
        """The outcome of a solve: its result, or why it failed (stored by ``_settle``)."""
        self._release()
        values: dict[str, Any]
        solved = True  # the worker ran the solve to its end and sent its last message
        try:
            values = {"state": "done", "result": future.result().document()}
        except ValueError as exc:
            values = {"state": "failed", "error": str(exc), "error_code": "calibration_failed"}
        except cf.CancelledError:
            solved = False
            values = {"state": "failed", "error_code": "interrupted",
                      "error": "The service stopped during the computation; start it again."}
        except cf.process.BrokenProcessPool:
            solved = False
            with self._pool_lock:
                if self._pool is not None:
                    self._pool.shutdown()
                self._pool = None
            values = {"state": "failed", "error_code": "worker_died",
                      "error": "The calibration worker process died (out of memory?); start "
                               "it again."}
        except Exception as exc:
            solved = False  # maybe raised before the worker had the call
            log.exception("calibration %s", cal_id)
            values = {"state": "failed", "error_code": "internal_error",
                      "error": f"Internal error ({type(exc).__name__}: {exc})."}
        try:
            self._settle(cal_id, outcome=values, progress_ended=not solved)
        except Exception:  # a future's callback must not die silently: the job would hang
            log.exception("calibration %s: storing its outcome", cal_id)

    def _progress(self, message: SolveProgress) -> None:
        """A worker's progress message, or its last (``message.last``): events are published
        until the outcome is stored."""
        cal_id = message.cal_id
        if message.last:
            self._settle(cal_id, progress_ended=True)
            return
        with self._events_lock:
            if cal_id in self._ending:
                self.events.publish(Topic("calibration", cal_id), message.event())

    def _settle(self, cal_id: str, *, outcome: dict[str, Any] | None = None,
                progress_ended: bool = False) -> None:
        """Store the outcome and publish the final ``state`` once both the outcome and the
        solve's last progress message are in (they come by different pipes), so the stored
        state turns final together with the event that ends the stream, after every
        progress event (none is published once the solve has left ``_ending``). The outcome
        is stored through ``service.jobs.outcomes``: retried, spooled if the database fails."""
        with self._events_lock:
            ending = self._ending.get(cal_id)
            if ending is None:
                return
            ending.outcome = outcome or ending.outcome
            ending.progress_ended = ending.progress_ended or progress_ended
            if ending.outcome is None or not ending.progress_ended:
                return
            del self._ending[cal_id]
        self.outcomes.finish(Topic("calibration", cal_id), ending.outcome)


@dataclass
class _Ending:
    """What a solve's end waits for: its outcome (the future's) and its last progress
    message (the worker's)."""

    outcome: dict[str, Any] | None = None
    progress_ended: bool = False
