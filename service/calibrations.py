"""Calibrations: start a solve over a run's captured stations, compute it in a worker process,
store the outcome when it completes.

Calibrations are CPU-bound: they run in worker processes (``service.workers``: they exit with
the service, however it dies) so the API stays responsive, and the result is stored when the
future completes. At most ``Settings.max_queued_calibrations`` solves wait or run at a time;
beyond, a request is refused (429 ``queue_full``) instead of piling up work and memory.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import threading
from typing import Any

import numpy as np

from calib import (
    MIN_IMAGES,
    PipelineOptions,
    RobotNoise,
    board_from_target,
    calibrate_stations,
)
from service import store
from service.db import Database
from service.errors import ConflictError, QueueFullError, UnprocessableError
from service.models import Calibration
from service.schemas import CalibrationOptions
from service.settings import Settings
from service.station_rows import captured_station_set
from service.workers import CalibrationPool

log = logging.getLogger("cellcal.service")


class Calibrations:
    """Queues solves in worker processes and records their results."""

    def __init__(self, settings: Settings, db: Database) -> None:
        self.settings = settings
        self.db = db
        self._pool: CalibrationPool | None = None
        self._pool_lock = threading.Lock()
        self._pending = 0  # solves queued or running, under _pool_lock

    def start(self, run_id: str, options: CalibrationOptions) -> Calibration:
        """Queue a solve over the run's captured stations in a worker process (429 when
        ``max_queued_calibrations`` are already queued or running)."""
        self._reserve()
        try:
            cal, payload = self._create(run_id, options)
            future = self._submit(payload)
        except BaseException:
            self._release()
            raise
        future.add_done_callback(lambda f: self._done(cal.id, f))
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
                ) -> tuple[Calibration, dict[str, Any]]:
        """The calibration row (committed) and the worker's payload."""
        with self.db.session() as s:
            run = store.get_run(s, run_id=run_id)
            if run.state == "capturing":
                raise ConflictError(f"Run {run_id} is still capturing; pause it or wait until "
                                    "it is done.", code="invalid_state")
            stations = captured_station_set(s, run_id=run_id)
            if len(stations.stations) < MIN_IMAGES:
                raise UnprocessableError(
                    f"Run {run_id} has {len(stations.stations)} captured stations; a "
                    f"calibration needs at least {MIN_IMAGES}.", code="too_few_stations")
            payload = {"run_id": run_id, "stations": stations, "options": options.model_dump()}
            cal = Calibration(run_id=run_id, state="running", options=options.model_dump())
            s.add(cal)
            s.commit()
        return cal, payload

    def shutdown(self) -> None:
        """Cancel queued solves and let the worker processes go."""
        with self._pool_lock:
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None

    def _submit(self, payload: dict[str, Any]) -> cf.Future[dict[str, Any]]:
        with self._pool_lock:
            if self._pool is None:
                self._pool = CalibrationPool(self.settings.calibration_workers)
            return self._pool.submit(solve_calibration, payload)

    def _done(self, cal_id: str, future: cf.Future[dict[str, Any]]) -> None:
        """Store the outcome of a solve: its result, or why it failed."""
        self._release()
        values: dict[str, Any]
        try:
            values = {"state": "done", "result": future.result()}
        except cf.CancelledError:
            values = {"state": "failed", "error": "The service stopped during the "
                                                  "computation; start it again."}
        except ValueError as exc:
            values = {"state": "failed", "error": str(exc)}
        except cf.process.BrokenProcessPool:
            with self._pool_lock:
                if self._pool is not None:
                    self._pool.shutdown()
                self._pool = None
            values = {"state": "failed", "error": "The calibration worker process died (out "
                                                  "of memory?); start it again."}
        except Exception as exc:
            log.error("calibration %s: %s: %s", cal_id, type(exc).__name__, exc)
            values = {"state": "failed",
                      "error": f"Internal error ({type(exc).__name__}: {exc})."}
        with self.db.session() as s:
            store.finish_calibration(s, cal_id=cal_id, **values)


def solve_calibration(payload: dict[str, Any]) -> dict[str, Any]:
    """Worker-process entry: the run's captured stations (``calib.Stations``: stored detections
    and robot poses) and the options -> result JSON document.

    Top level (picklable) and self-contained: it imports the pipeline in the worker.
    """
    from service.results import calibration_result_json

    opts, stations = payload["options"], payload["stations"]
    default = RobotNoise()
    noise = RobotNoise(
        default.rot_rad if opts["robot_noise_rot_deg"] is None
        else float(np.deg2rad(opts["robot_noise_rot_deg"])),
        default.trans_m if opts["robot_noise_trans_mm"] is None
        else opts["robot_noise_trans_mm"] * 1e-3)
    assert stations.target is not None  # a run always has its board
    result = calibrate_stations(
        stations.inputs(), board_from_target(stations.target),
        PipelineOptions(setup=stations.setup, method=opts["method"],
                        estimate_nu=opts["estimate_nu"], estimate_kappa=opts["estimate_kappa"],
                        kappa=opts.get("kappa", "auto"), nu_method=opts["nu_method"],
                        noise=noise))
    return calibration_result_json(
        result, command=f"POST /runs/{payload['run_id']}/calibrations")
