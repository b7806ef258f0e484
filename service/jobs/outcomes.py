"""The final outcome of a calibration or a validation: stored whatever the database does.

A job's end is one write (its state, result or error) and one event (the final ``state``,
which ends its stream). When that write failed (a lock held for 40 s, a full disk), the job
stayed ``running`` for good, a validation held the robot (409 ``robot_busy`` for every new
run), the result was lost and listeners hung (issue 22). Now :meth:`Outcomes.finish`

* retries the write like a capture's (``service.store.db.retry_transient``, for
  ``Settings.database_retry_s``);
* if the database still fails, spools the outcome to ``<data_dir>/spool/`` (one JSON file per
  job, written atomically) and a drain thread stores it, then publishes the final state, as
  soon as the database answers again; a spooled outcome left by a service that stopped is
  stored at the next start (:meth:`Outcomes.recover`, before running jobs are marked failed);
* from the moment the job's worker ends until its outcome is stored, every row of the job
  read from the database shows that outcome (a SQLAlchemy ``load`` listener), so a job whose
  worker has ended is never shown ``running`` and its validation does not hold the robot.

A job that computed its result while the data directory was deleted (or the database file
went) used to end ``done``, stored in a database file without a name, and a restart lost it
without a word (issue 22, row 5). A ``done`` outcome is therefore stored only while
``Storage.gone`` finds the directory and the database file where they were; otherwise the
job ends ``failed`` with the ``storage_unavailable`` reason (``error_code``).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Callable
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

from sqlalchemy import event
from sqlalchemy.orm.attributes import set_committed_value

from service.events import EventBus
from service.settings import Settings
from service.store import writes
from service.store.db import Database, DatabaseUnavailableError, retry_transient
from service.store.records import CalibrationRecord, Topic, ValidationRecord, utcnow
from service.store.storage import Storage

log = logging.getLogger("cellcal.service")

#: Pause between two attempts of the drain thread, seconds.
DRAIN_INTERVAL_S = 1.0
_ROWS: dict[str, type[CalibrationRecord] | type[ValidationRecord]] = {
    "calibration": CalibrationRecord, "validation": ValidationRecord}


class Outcomes:
    """Stores jobs' final outcomes, through database outages (see the module doc)."""

    def __init__(self, settings: Settings, db: Database, events: EventBus,
                 storage: Storage) -> None:
        self.settings = settings
        self.db = db
        self.events = events
        self.storage = storage
        self.dir = Path(settings.data_dir) / "spool"
        self._pending: dict[Topic, dict[str, Any]] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._drainer: threading.Thread | None = None
        for row in _ROWS.values():
            event.listen(row, "load", self._overlay)

    # ---- a job ends ------------------------------------------------------------------------

    def finish(self, topic: Topic, values: dict[str, Any]) -> None:
        """Store the outcome ``values`` (``state``, and ``result`` or ``error`` and
        ``error_code``) of the job ``topic`` and publish its final state; spooled if the
        database does not answer. ``done`` becomes ``failed`` when the data directory or the
        database file is gone."""
        if values.get("state") == "done" and (gone := self.storage.gone()) is not None:
            log.error("%s %s: %s", topic.kind, topic.id, gone)
            values = {"state": "failed", "error": str(gone), "error_code": gone.code}
        values = {**values, "finished_at": utcnow()}
        with self._lock:  # shown from now on, while the write is tried
            self._pending[topic] = values

        def save() -> bool:
            try:
                retry_transient(lambda: self._store(topic, values),
                                budget_s=self.settings.database_retry_s,
                                what=f"storing the outcome of {topic.kind} {topic.id}")
            except Exception as exc:  # DatabaseUnavailableError, or a fault of the disk
                log.error("%s %s: %s; the outcome is spooled and stored once the database "
                          "answers", topic.kind, topic.id, exc)
                self._spool(topic, values)
                return False
            with self._lock:
                self._pending.pop(topic, None)
            return True

        def retry(read: Callable[[], dict[str, Any]]) -> dict[str, Any]:
            return retry_transient(read, budget_s=self.settings.database_retry_s,
                                   what=f"publishing the end of {topic.kind} {topic.id}")

        try:  # one step: the final state is never stored without its event on the way
            self.events.finish(topic, save, retry=retry)
        except DatabaseUnavailableError as exc:  # stored; the drain thread publishes it
            log.error("%s %s: %s", topic.kind, topic.id, exc)
            self._spool(topic, None)

    def _store(self, topic: Topic, values: dict[str, Any] | None) -> bool:
        """Store ``values`` (nothing when they are None or empty: stored already); True."""
        if values:
            with self.db.session() as s:
                if topic.kind == "calibration":
                    writes.finish_calibration(s, cal_id=topic.id, **values)
                else:
                    writes.finish_validation(s, val_id=topic.id, **values)
        return True

    # ---- the spool -------------------------------------------------------------------------

    def _spool(self, topic: Topic, values: dict[str, Any] | None) -> None:
        """Keep ``values`` (None: stored, only the event is missing) until the drain thread
        has stored them, in memory and in a file that the next start reads."""
        with self._lock:
            self._pending[topic] = values or {}
            if self._drainer is None or not self._drainer.is_alive():
                self._drainer = threading.Thread(target=self._drain, name="outcome-spool",
                                                 daemon=True)
                self._drainer.start()
        if values is not None:
            try:
                _write_atomically(self._file(topic), json.dumps(
                    {"kind": topic.kind, "id": topic.id, "values": _jsonable(values)}))
            except OSError as exc:
                log.error("%s %s: cannot spool the outcome to %s (%s); it is kept in memory "
                          "until the database answers", topic.kind, topic.id, self.dir, exc)
        self._wake.set()

    def _file(self, topic: Topic) -> Path:
        return self.dir / f"{topic.kind}-{topic.id}.json"

    def _drain(self) -> None:
        """Store the spooled outcomes, then publish their final states, as soon as the
        database takes them."""
        while not self._closed.is_set():
            self._wake.wait(DRAIN_INTERVAL_S)
            self._wake.clear()
            with self._lock:
                pending = list(self._pending.items())
            for topic, values in pending:
                try:
                    self.events.finish(topic, partial(self._store, topic, values))
                except Exception as exc:  # still unavailable: the next round tries again
                    log.debug("%s %s still spooled: %s", topic.kind, topic.id, exc)
                    continue
                with self._lock:
                    self._pending.pop(topic, None)
                _forget(self._file(topic))
                log.warning("%s %s: the spooled outcome is stored", topic.kind, topic.id)

    def _overlay(self, row: CalibrationRecord | ValidationRecord, _context: Any) -> None:
        """A job row just read shows its spooled outcome."""
        kind = "calibration" if isinstance(row, CalibrationRecord) else "validation"
        values = self._pending.get(Topic(kind, row.id))
        for key, value in (values or {}).items():
            set_committed_value(row, key, value)

    # ---- start and stop --------------------------------------------------------------------

    def recover(self) -> int:
        """Store the outcomes a previous service spooled (their events too); how many."""
        stored = 0
        for path in sorted(self.dir.glob("*.json")) if self.dir.is_dir() else []:
            try:
                doc = json.loads(path.read_text())
                topic, values = Topic(doc["kind"], doc["id"]), _from_json(doc["values"])
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.error("spooled outcome %s cannot be read (%s); left in place", path, exc)
                continue
            self.events.finish(topic, partial(self._store, topic, values))
            _forget(path)
            stored += 1
        return stored

    def close(self) -> None:
        """Stop the drain thread (what is still spooled is stored at the next start)."""
        self._closed.set()
        self._wake.set()
        if self._drainer is not None:
            self._drainer.join(5.0)
        for row in _ROWS.values():
            event.remove(row, "load", self._overlay)


def _jsonable(values: dict[str, Any]) -> dict[str, Any]:
    return {k: v.isoformat() if isinstance(v, datetime) else v for k, v in values.items()}


def _from_json(values: dict[str, Any]) -> dict[str, Any]:
    finished = values.get("finished_at")
    return {**values, "finished_at": None if finished is None
            else datetime.fromisoformat(finished)}


def _forget(path: Path) -> None:
    """Remove the spool file of an outcome now stored. A directory that takes no change
    (read-only) keeps it; the next start stores it again, where a job no longer running is
    left as it is. The drain thread must not die of it and leave later outcomes unstored."""
    try:
        path.unlink(missing_ok=True)
    except OSError as exc:
        log.error("the stored outcome's spool file %s cannot be removed (%s); the next start "
                  "finds it stored already", path, exc.strerror or exc)


def _write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file, synced, then renamed."""
    path.parent.mkdir(exist_ok=True)  # not a deleted data directory
    tmp = path.with_suffix(".tmp")
    with tmp.open("w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
