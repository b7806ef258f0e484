"""The service's log on stderr: uvicorn's access lines and cellcal's own records from INFO on,
among them the lifecycle of every run, calibration and re-check (created or started, each
state it enters, with the error code when it fails), as plain text or as one JSON object per
line (``cellcal serve --log-format json``) for a log collector.

A lifecycle record carries its facts as fields (``lifecycle``): ``event``, ``kind``, ``id``,
``state``, ``code``; JSON lines hold them as keys next to ``time``, ``level``, ``logger`` and
``message``.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import sys
from typing import Any

LOG_FORMATS = ("text", "json")
#: The logger of the service's lifecycle records.
LIFECYCLE = logging.getLogger("cellcal.lifecycle")
#: Attributes every ``LogRecord`` has: the rest came as ``extra`` fields.
_STANDARD = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message",
                                                                                 "asctime"}
_TEXT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class JSONLines(logging.Formatter):
    """One JSON object per record: time (UTC, ISO 8601), level, logger, message and the
    record's extra fields; a traceback as ``exception``."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "time": dt.datetime.fromtimestamp(record.created, dt.UTC).isoformat(
                timespec="milliseconds"),
            "level": record.levelname, "logger": record.name, "message": record.getMessage()}
        doc |= {k: v for k, v in vars(record).items() if k not in _STANDARD}
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


def configure_logging(log_format: str) -> None:
    """Send cellcal's records from INFO on to stderr in ``log_format`` (``LOG_FORMATS``),
    and uvicorn's too for ``json`` (call after uvicorn has set up its loggers)."""
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format {log_format!r}: use {' or '.join(LOG_FORMATS)}")
    formatter = JSONLines() if log_format == "json" else logging.Formatter(_TEXT)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(formatter)
    cellcal = logging.getLogger("cellcal")
    cellcal.handlers = [handler]
    cellcal.setLevel(logging.INFO)
    cellcal.propagate = False
    if log_format == "json":
        for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
            for uvicorn_handler in logging.getLogger(name).handlers:
                uvicorn_handler.setFormatter(formatter)


def lifecycle(event: str, kind: str, job_id: str, **fields: Any) -> None:
    """Log that ``kind`` (run, calibration, validation) ``job_id`` had ``event`` (created,
    started, or the state it entered), with ``fields`` (state, code, ...)."""
    said = " ".join(f"{k}={v}" for k, v in fields.items() if v is not None)
    LIFECYCLE.info("%s %s %s%s", kind, job_id, event, f" ({said})" if said else "",
                   extra={"event": event, "kind": kind, "id": job_id, **fields})


def log_state_event(kind: str, job_id: str, event: dict[str, Any]) -> None:
    """``lifecycle`` for a published ``state`` event of a run or job."""
    error = event.get("error")
    code = error.get("code") if isinstance(error, dict) else None
    lifecycle(event["state"], kind, job_id, state=event["state"], code=code,
              error=error.get("detail") if isinstance(error, dict) else error,
              stations_captured=event.get("stations_captured"))
