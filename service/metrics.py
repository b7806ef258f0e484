"""``GET /metrics``: the service's figures in the Prometheus text format.

Every figure is read from the database at scrape time (``queries.service_figures``), so the
numbers survive restarts and agree with what the REST calls answer; ``prometheus_client``
writes the exposition format.

Metrics (all prefixed ``cellcal_``):

* ``runs{state, mode}`` — runs by state and mode (gauge);
* ``stations_total{state}`` — stations stored, ``captured`` or ``skipped`` (counter);
* ``calibrations_total{state}`` — calibrations by state (counter);
* ``calibration_duration_seconds`` — summary (count, sum) of finished calibrations, from the
  request to the stored result;
* per setup, the newest finished calibration: ``last_calibration_timestamp_seconds``,
  ``last_calibration_rms_px``, ``last_calibration_cv_rms_px`` (cross-validated corner error),
  and ``last_calibration_verdict{verdict}`` = 1 for its quality verdict (pass, warn, fail).
"""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    Metric,
    SummaryMetricFamily,
)
from prometheus_client.registry import Collector

from service.store import queries
from service.store.db import Database

__all__ = ["CONTENT_TYPE_LATEST", "exposition"]


class _StoreCollector(Collector):
    """Turns ``queries.service_figures`` into metric families at each scrape."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def collect(self) -> Iterator[Metric]:
        with self.db.session() as s:
            figures = queries.service_figures(s)
        runs = GaugeMetricFamily("cellcal_runs", "Runs by state and mode.",
                                 labels=["state", "mode"])
        for (state, mode), n in sorted(figures.runs.items()):
            runs.add_metric([state, mode], n)
        yield runs
        for name, doc, counts in (
                ("cellcal_stations", "Stations stored, by state.", figures.stations),
                ("cellcal_calibrations", "Calibrations, by state.", figures.calibrations)):
            family = CounterMetricFamily(name, doc, labels=["state"])
            for state, n in sorted(counts.items()):
                family.add_metric([state], n)
            yield family
        yield SummaryMetricFamily(
            "cellcal_calibration_duration_seconds",
            "Time from the calibration request to its stored result (finished ones).",
            count_value=len(figures.durations_s), sum_value=sum(figures.durations_s))
        yield from _latest(figures.latest)


def _latest(latest: list[queries.LatestCalibration]) -> Iterator[Metric]:
    """The per-setup families of the newest finished calibration."""
    stamp = GaugeMetricFamily("cellcal_last_calibration_timestamp_seconds",
                              "When the newest finished calibration was stored (Unix time).",
                              labels=["setup"])
    rms = GaugeMetricFamily("cellcal_last_calibration_rms_px",
                            "RMS reprojection error of the newest finished calibration.",
                            labels=["setup"])
    cv = GaugeMetricFamily("cellcal_last_calibration_cv_rms_px",
                           "Cross-validated corner error of the newest finished calibration.",
                           labels=["setup"])
    verdict = GaugeMetricFamily("cellcal_last_calibration_verdict",
                                "1 for the quality verdict of the newest finished calibration.",
                                labels=["setup", "verdict"])
    for last in latest:
        stamp.add_metric([last.setup], last.finished_at.timestamp())
        for family, value in ((rms, last.rms_px), (cv, last.cv_rms_px)):
            if value is not None:
                family.add_metric([last.setup], value)
        if last.verdict is not None:
            verdict.add_metric([last.setup, last.verdict], 1.0)
    yield from (stamp, rms, cv, verdict)


def exposition(db: Database) -> bytes:
    """The metrics page in the Prometheus text exposition format (``CONTENT_TYPE_LATEST``)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_StoreCollector(db))
    return generate_latest(registry)
