"""A database that fails as a calibration or a validation ends (issue 22, row 4).

The job's last write used to fail once: the validation stayed ``running`` for good, every new
run got 409 ``robot_busy``, the calibration's result was lost and its listeners hung. Here
another connection holds the SQLite write lock from just after the job starts until its
outcome has gone to the spool (``service.jobs.outcomes``), so the ends of both jobs meet a
database that does not answer for longer than the service retries (``database_retry_s``,
shortened by configuration, as in ``test_service_database_outage``). Meanwhile the job shows
its outcome and holds no robot; once the lock is gone the outcome is stored, the listener gets
every progress event, in order, then the final state, and nothing is lost (progress events
used to wait the busy timeout inside the job and be dropped). ``tools/database_lock.py`` holds
the real 40 s lock against ``cellcal serve`` with the default settings (its docstring has the
result).
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.jobs import outcomes as outcomes_module
from service.jobs.outcomes import Outcomes
from service.store.db import DatabaseUnavailableError
from service.store.records import Topic
from tests.support.helpers import wait_for
from tests.support.service import (
    AUTH,
    Event,
    finished,
    poses,
    read_events,
    settings,
    start_run,
    wait_run,
)

#: The service's SQLite busy timeout and write retry budget in this test, seconds.
BUSY_S, RETRY_S = 0.5, 2.0


@contextmanager
def locked(database: Path) -> Iterator[sqlite3.Connection]:
    """The database's write lock, held by another program while the block runs."""
    lock = sqlite3.connect(database, timeout=30, isolation_level=None)
    try:
        lock.execute("BEGIN IMMEDIATE")
        yield lock
    finally:
        lock.execute("ROLLBACK")
        lock.close()


@contextmanager
def listening(client: TestClient, path: str) -> Iterator[list[Event]]:
    """The events of the stream at ``path``, read in a thread until it ends (joined at the
    end of the block)."""
    events: list[Event] = []
    failed: list[BaseException] = []

    def read() -> None:
        try:
            events.extend(read_events(client, "", path=path))
        except BaseException as exc:
            failed.append(exc)
            raise

    reader = threading.Thread(target=read)
    reader.start()
    wait_for("the listener", lambda: client.app.state.runtime.events._listeners)
    yield events
    reader.join(120)
    assert not reader.is_alive(), "the stream did not end"
    assert not failed, failed


def steps(events: list[Event], stage: str) -> int:
    """How many steps the stream's ``stage`` progress events count, after checking that the
    ids rise and that every step from 1 to that count came, once each and in order."""
    ids = [event_id for event_id, _, _ in events]
    assert ids == sorted(set(ids)), ids
    seen = [(data["step"], data["of"]) for _, kind, data in events
            if kind == "progress" and data["stage"] == stage]
    n = seen[0][1] if seen else 0
    assert seen == [(k, n) for k in range(1, n + 1)], seen
    return n


def row_state(db: sqlite3.Connection | Path, table: str, job_id: str) -> tuple[Any, ...]:
    conn = db if isinstance(db, sqlite3.Connection) else sqlite3.connect(db)
    return conn.execute(f"SELECT state, result, error FROM {table} WHERE id = ?",
                        (job_id,)).fetchone()


def end_in_a_lock(client: TestClient, data: Path, kind: str, job_id: str) -> dict[str, Any]:
    """Hold the lock from now until the job's outcome is spooled; check what the service
    shows meanwhile; the job as answered then."""
    table, spooled = f"{kind}s", data / "spool" / f"{kind}-{job_id}.json"
    with locked(data / "cellcal.db") as lock:
        assert row_state(lock, table, job_id)[0] == "running", "the job ended before the lock"
        wait_for(f"the {kind}'s outcome to be spooled", spooled.exists, 300)
        shown = client.get(f"/{table}/{job_id}").json()
        assert shown["state"] != "running"  # its worker has ended: so says the service
        assert row_state(lock, table, job_id)[0] == "running"  # though the database has not
        if kind == "validation":  # a new run is refused for the database, not the robot
            r = client.post("/runs", json={"poses": poses(3)})
            assert r.status_code == 503 and r.json()["code"] == "database_unavailable"
    wait_for("the spooled outcome to be stored", lambda: not spooled.exists(), 60)
    state, result, error = row_state(data / "cellcal.db", table, job_id)
    assert (state, error) == (shown["state"], shown["error"])
    assert json.loads(result) == shown["result"]  # nothing lost
    return shown


@pytest.mark.timeout(600)
def test_jobs_ending_in_a_database_lock_end_done(tmp_path: Path) -> None:
    app = create_app(settings(tmp_path, database_busy_timeout_s=BUSY_S,
                              database_retry_s=RETRY_S))
    with TestClient(app) as client:
        client.headers.update(AUTH)
        run_id = start_run(client, 12)
        assert wait_run(client, run_id, finished, 300)["state"] == "done"

        r = client.post(f"/runs/{run_id}/calibrations")
        assert r.status_code == 202, r.text
        cal_id = r.json()["id"]
        with listening(client, f"/calibrations/{cal_id}/events") as events:
            cal = end_in_a_lock(client, tmp_path, "calibration", cal_id)
        assert cal["state"] == "done" and cal["result"]["format"] == "cellcal/result@1"
        assert events[-1][1:] == ("state", {"type": "state", "calibration_id": cal_id,
                                            "state": "done", "error": None,
                                            "error_code": None})
        assert steps(events, "detecting") == 12  # each station's, in order

        r = client.post(f"/calibrations/{cal_id}/checks", json={})
        assert r.status_code == 202, r.text
        val_id = r.json()["id"]
        with listening(client, f"/validations/{val_id}/events") as events:
            val = end_in_a_lock(client, tmp_path, "validation", val_id)
        assert val["state"] == "done" and val["result"]["kind"] == "check"
        assert events[-1][2]["state"] == "done"
        assert steps(events, "station") > 0
        # the robot is free: a new run starts
        assert client.post("/runs", json={"poses": poses(3)}).status_code == 201


JOBS = ("first", "second")


class _Database:
    """A database stand-in that fails while ``down`` is set and stores nothing otherwise."""

    def __init__(self) -> None:
        self.down = threading.Event()
        self.stored: list[str] = []

    @contextmanager
    def session(self) -> Iterator[Any]:
        if self.down.is_set():
            raise DatabaseUnavailableError("the database is down")
        yield _Session(self.stored)


class _Session:
    """Records the job ids of the updates it is given."""

    def __init__(self, stored: list[str]) -> None:
        self.stored = stored

    def execute(self, statement: Any) -> None:
        self.stored += [v for v in statement.compile().params.values() if v in JOBS]

    def commit(self) -> None:
        pass


class _Events:
    """An event bus stand-in: the final state is the outcome's write, nothing published."""

    def finish(self, topic: Topic, save: Any, retry: Any = None) -> bool:
        return save()


class _Storage:
    def gone(self) -> None:
        return None


@pytest.mark.timeout(60)
def test_a_spool_file_that_cannot_be_removed_does_not_stop_the_drain(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An outcome spooled in a database outage is stored when the database returns, and its
    spool file removed; a data directory that refused that removal (read-only by then) ended
    the drain thread with an uncaught OSError, so every outcome spooled later stayed unstored
    (the job ``running`` in the database) until a restart."""
    monkeypatch.setattr(outcomes_module, "DRAIN_INTERVAL_S", 0.05)  # retried sooner
    db = _Database()
    outcomes = Outcomes(settings(tmp_path, database_retry_s=0.0), db,  # type: ignore[arg-type]
                        _Events(), _Storage())  # type: ignore[arg-type]
    unlink = Path.unlink

    def refused(path: Path, missing_ok: bool = False) -> None:
        if path.parent == outcomes.dir:
            raise PermissionError(13, "Read-only file system", str(path))
        unlink(path, missing_ok=missing_ok)

    try:
        for job in JOBS:
            db.down.set()
            outcomes.finish(Topic("calibration", job), {"state": "done", "result": {}})
            assert (outcomes.dir / f"calibration-{job}.json").is_file()
            monkeypatch.setattr(Path, "unlink", refused)
            db.down.clear()
            wait_for(f"the {job} outcome stored", lambda: not outcomes._pending, timeout=20)
        assert db.stored == list(JOBS)
    finally:
        monkeypatch.undo()
        outcomes.close()
