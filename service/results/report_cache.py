"""Calibration reports for ``GET /calibrations/{id}/report``: rendered once, in a worker
process, and kept.

Rendering a 500-station report takes seconds of matplotlib. Done in the request threads, 8
requests at once took 105 s each, slowed capture from 2.27 to 0.59 stations/s and left the
service 380 MB larger (issue 22). A finished calibration's result never changes, so its page
is rendered once: in a worker process of its own at a lower priority (nice 10, so capture's
threads get most of the cores; ``service.jobs.workers.WorkerPool``), never on the event loop or
beside capture's threads; requests that arrive meanwhile wait for the same rendering, each for
at most ``report_wait_s``: then it is answered 503 ``report_rendering`` with ``Retry-After``
while the rendering goes on (on a busy host a request must not hang without bound). The page
is kept in ``<data_dir>/reports/<id>.html`` and served from there. A cache file that cannot be
written (a read-only or full data directory) only costs a new rendering next time.

Nice 19 starved the worker: with four CPU-bound processes at nice 0 on two cores it got ~1 %
of a core, and an 8-station report took minutes. At nice 10 it gets a tenth of a nice-0
process's share, which still leaves capture its speed (``tools/report-load``).
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from calib import Result
from service.errors import NotReadyError
from service.jobs.workers import WorkerPool
from service.results.identity import ReportIdentity
from service.settings import Settings

log = logging.getLogger("cellcal.service")

#: Scheduling priority of the rendering worker (0 = the service's, 19 = the lowest).
REPORT_NICE = 10
#: What a request that waited ``report_wait_s`` in vain is told to wait before asking again, s.
RETRY_AFTER_S = 5


@dataclass(frozen=True)
class ReportJob:
    """One report as the worker process receives it (pickled): the finished calibration's
    result, its stations' images (station id -> image file) and its identity."""

    result: Result
    images: dict[str, str] = field(default_factory=dict)
    identity: ReportIdentity = field(default_factory=ReportIdentity)


def render(job: ReportJob) -> str:
    """Worker entry: the report of a job (``service.results.report.render_report``)."""
    from service.results.report import render_report  # matplotlib: only in the worker

    return render_report(job.result, job.images, job.identity)


class Reports:
    """Rendered reports of finished calibrations, by calibration id."""

    def __init__(self, settings: Settings) -> None:
        self.dir = Path(settings.data_dir) / "reports"
        self.wait_s = settings.report_wait_s
        self._pool: WorkerPool | None = None
        self._lock = threading.Lock()
        self._rendering: dict[str, cf.Future[str]] = {}

    def page(self, cal_id: str, job: Callable[[], ReportJob]) -> Path | str:
        """The report of the finished calibration ``cal_id``: the cached file, or the HTML
        just rendered from ``job()``, which is called only when no page is kept and none is
        being rendered (it reads the stations and hashes their images: 8 requests at once
        for a 500-station calibration did that 8 times beside capture). ValueError (one
        line) from ``job`` for a result that is not a valid ``cellcal/result@1`` document;
        NotReadyError if the rendering takes longer than ``report_wait_s`` (it goes on, and
        a later request gets the page)."""
        path = self.cached(cal_id)
        if path.is_file():
            return path
        with self._lock:
            future = self._rendering.get(cal_id)
            new = future is None
            if future is None:
                if self._pool is None:
                    # a lower priority: capture's threads get the cores first
                    self._pool = WorkerPool(1, lambda message: None, nice=REPORT_NICE)
                future = self._pool.submit(render, job())
                self._rendering[cal_id] = future
        if new:  # outside the lock, which ``_keep`` takes (at once if it has ended already)
            future.add_done_callback(lambda f: self._keep(cal_id, f))
        try:
            return future.result(timeout=self.wait_s)
        except cf.TimeoutError:
            raise NotReadyError(
                f"The report of calibration {cal_id} is still being rendered; retry in "
                f"{RETRY_AFTER_S} s.", code="report_rendering",
                retry_after_s=RETRY_AFTER_S) from None
        except cf.process.BrokenProcessPool:  # the next request renders it in a new worker
            raise NotReadyError(
                f"The process rendering the report of calibration {cal_id} died (out of "
                f"memory, or killed); retry in {RETRY_AFTER_S} s.", code="report_worker_died",
                retry_after_s=RETRY_AFTER_S) from None

    def cached(self, cal_id: str) -> Path:
        return self.dir / f"{cal_id}.html"

    def _keep(self, cal_id: str, future: cf.Future[str]) -> None:
        """Write a rendered page to the cache (best effort), then let new requests read it."""
        try:
            if future.exception() is None:
                self.dir.mkdir(exist_ok=True)  # not a deleted data directory
                tmp = self.cached(cal_id).with_suffix(".tmp")
                tmp.write_text(future.result())
                os.replace(tmp, self.cached(cal_id))
        except (OSError, cf.CancelledError) as exc:
            log.warning("report of calibration %s not cached: %s", cal_id, exc)
        finally:
            with self._lock:
                self._rendering.pop(cal_id, None)

    def shutdown(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None
