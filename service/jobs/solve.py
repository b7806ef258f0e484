"""What a calibration's worker process runs: the solve of one job (``solve_calibration``)
and the progress messages it sends back to the service (``SolveProgress``).

A module of its own so that a spawned worker imports only what the solve needs (calib and
the result's writer): the worker unpickles ``solve_calibration`` by importing its module, and
``service.jobs.calibrations`` brings the database, alembic and the event bus with it, which
cost each new worker about 0.8 CPU s before its first solve.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from calib import Result, SolverOptions, Stations, calibrate
from service.jobs.workers import report_progress


@dataclass(frozen=True)
class SolveJob:
    """One solve as a worker process receives it (pickled): the calibration and its run, the
    run's captured stations (stored detections and robot poses) and the solver's options."""

    cal_id: str
    run_id: str
    stations: Stations
    options: SolverOptions


def solve_calibration(job: SolveJob) -> Result:
    """Worker-process entry: a solve's job -> its typed result (the service stores its
    document).

    Top level (picklable) and self-contained: it imports the document writer in the worker.
    """
    from service.results.document import result_of

    progress = ProgressSender(job.cal_id, len(job.stations.stations))
    try:
        result = calibrate(job.stations, job.options, progress=progress.detecting,
                           on_stage=progress.stage)
        return result_of(result, command=f"POST /runs/{job.run_id}/calibrations")
    finally:
        progress.end()


@dataclass(frozen=True)
class SolveProgress:
    """One progress message of a solve as its worker sends it (pickled): a stage begins, or
    the board detection reaches station ``step`` of ``of``; ``last``: the solve sends no
    more (no event)."""

    cal_id: str
    stage: str = ""
    message: str = ""
    step: int | None = None
    of: int | None = None
    last: bool = False

    def event(self) -> dict[str, Any]:
        """The ``progress`` event of the calibration's stream."""
        count = {} if self.step is None else {"step": self.step, "of": self.of}
        return {"type": "progress", "calibration_id": self.cal_id, "stage": self.stage,
                **count, "message": self.message}


class ProgressSender:
    """In a worker: a solve's progress messages, sent to the service process
    (``service.jobs.workers.report_progress``)."""

    def __init__(self, cal_id: str, n_stations: int) -> None:
        self.cal_id = cal_id
        self.n_stations = n_stations

    def detecting(self, observations: Iterable[Any]) -> Iterator[Any]:
        """``observations`` unchanged and still one at a time, one event as the board
        detection reaches each."""
        n = self.n_stations
        for k, item in enumerate(observations, 1):
            report_progress(SolveProgress(self.cal_id, "detecting",
                                          f"detecting the board: station {k} of {n}",
                                          step=k, of=n))
            yield item

    def end(self) -> None:
        """The solve's last message: no progress event follows."""
        report_progress(SolveProgress(self.cal_id, last=True))

    def stage(self, name: str) -> None:
        """A stage of ``calib.calibrate`` begins."""
        report_progress(SolveProgress(self.cal_id, name, name))
