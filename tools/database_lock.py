"""A 40 s database lock at the end of a calibration and of a validation (issue 22, row 4),
against ``cellcal serve --mock`` with its default database settings.

``tests/test_service_job_outage.py`` makes the same fault fast by shortening the service's
SQLite busy timeout and retry budget; this script keeps the defaults (30 s busy timeout, 60 s
retry budget) and holds the lock for the real 40 s:

1. a run of ``--stations`` planned stations is captured (no lock);
2. a calibration of it is solved without a lock, as the reference: its SSE stream tells how long
   its end (the final ``state`` event) takes after its solve begins (the first progress event
   past the board detection), the "trigger";
3. a second calibration of the same run: as its trigger arrives, the listener takes the
   database's exclusive lock (``BEGIN EXCLUSIVE`` on ``<data>/cellcal.db``, from another
   connection) and holds it ``--lock-s`` seconds;
4. the same for two re-check validations of the locked calibration (trigger: the first event);
5. a new run must start (the robot is not held by a job).

Checked, exit status 1 at the first that fails:

* unlocked, the job ended sooner after its trigger than the lock lasts: the locked job's end
  falls inside the lock;
* the database row said ``running`` while the lock was held;
* the locked job's stream ends with the ``done`` state; the database stores it ``done`` with
  the result the service answers; the locked calibration's solution is the unlocked one's
  (camera, hand-eye, target pose within 1e-9): nothing lost;
* the locked job's stream has every progress event the unlocked one's has from its trigger
  on (stage and step; at least one after the trigger), in the same order, with rising ids:
  none dropped while the database did not answer;
* no answer was a 5xx.

    .venv/bin/python tools/database_lock.py                # 40 s, 12 stations
    .venv/bin/python tools/database_lock.py --lock-s 10    # a quicker look

Result, 2026-11-26 00:25-00:31 UTC, on the shared 2-core machine at load average 9-21 (a full
``make test`` ran beside it), ``--lock-s 40``, 12 stations: exit status 0. Calibration: unlocked
its end came 8.8 s after its solve began; locked, the lock was held 40.3 s from that moment, the
row said ``running`` throughout, and the stream ended ``done`` 0.1 s after the lock, with the
unlocked solution. Re-check: its end 2.8 s after its first event unlocked; locked 40.2 s, then
``done`` 1.0 s after the lock. A new run started (201); 182 answers, no 5xx. What the lock did
cost then: the locked calibration's progress events that met the lock each waited SQLite's
30 s busy timeout inside the job, and were logged and dropped.

Since the event bus queues events and stores them from a writer thread (``service.events``),
2026-11-26 04:05-04:10 UTC, load average ~20, ``--lock-s 40``: exit status 0, every check ok;
the locked calibration's stream had the unlocked one's last 4 progress events (hand-eye, model
selection, validation, cross-validation) in order, then ``done`` 0.1 s after the lock; the
locked re-check's had stations 1-5, then ``done`` 0.3 s after the lock; 175 answers, no 5xx.
The same script against the code before (commit fd44b09) fails that check for the calibration.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sqlite3
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.serving.local import ServeOptions, local_service

KEY = "database-lock-key-0123456789"


class CheckFailedError(Exception):
    """A check of the script did not hold."""


def check(ok: bool, what: str) -> None:
    print(f"  {'ok  ' if ok else 'FAIL'} {what}")
    if not ok:
        raise CheckFailedError(what)


class Client:
    """The service's API; every answer's status is kept (none may be a 5xx)."""

    def __init__(self, url: str) -> None:
        self.http = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"},
                                 timeout=120)
        self.statuses: list[int] = []

    def call(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        r = self.http.request(method, path, **kwargs)
        self.statuses.append(r.status_code)
        return r

    def close(self) -> None:
        self.http.close()

    def until(self, path: str, done: Any, timeout: float = 600.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while not done(body := self.call("GET", path).json()):
            if time.monotonic() > deadline:
                raise CheckFailedError(f"{path} did not finish: {body}")
            time.sleep(0.5)
        return body


@dataclass(frozen=True)
class Service:
    """The service under test: its API, base URL and SQLite database file."""

    api: Client
    url: str
    database: Path


class Job:
    """One calibration or validation followed over its SSE stream; with ``lock_s``, the
    listener takes the database's exclusive lock as the job's ``trigger`` event arrives."""

    def __init__(self, service: Service, kind: str, job_id: str, lock_s: float | None) -> None:
        self.url, self.database, self.kind, self.id = (service.url, service.database, kind,
                                                      job_id)
        self.lock_s = lock_s
        self.events: list[dict[str, Any]] = []
        self.ids: list[int] = []
        self.triggered_at: float | None = None
        self.ended_at: float | None = None
        self.lock: sqlite3.Connection | None = None
        self.locked = threading.Event()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _trigger(self, event: dict[str, Any]) -> bool:
        """A calibration's solve has begun (its detection is over); a validation has begun
        (its first event)."""
        return event.get("type") != "state" and (
            self.kind == "validation" or event.get("stage") not in (None, "detecting"))

    def _read(self) -> None:
        with httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {KEY}"},
                          timeout=httpx.Timeout(30, read=None)) as http, \
                http.stream("GET", f"/{self.kind}s/{self.id}/events") as r:
            for line in r.iter_lines():
                if line.startswith("id:"):
                    self.ids.append(int(line[3:]))
                if not line.startswith("data:"):
                    continue
                event = json.loads(line[5:])
                self.events.append(event)
                if self.triggered_at is None and self._trigger(event):
                    self.triggered_at = time.time()
                    if self.lock_s is not None:
                        self.lock = sqlite3.connect(self.database, timeout=60,
                                                    isolation_level=None,
                                                    check_same_thread=False)
                        self.lock.execute("BEGIN EXCLUSIVE")
                        self.locked.set()
        self.ended_at = time.time()

    @property
    def progress(self) -> list[tuple[Any, Any]]:
        """(stage, step) of each progress event, in the stream's order."""
        return [(e.get("stage"), e.get("step")) for e in self.events
                if e.get("type") == "progress"]

    @property
    def tail_s(self) -> float:
        """Seconds from the trigger to the end of the stream (the final state)."""
        assert self.triggered_at is not None and self.ended_at is not None
        return self.ended_at - self.triggered_at


def unlocked(service: Service, kind: str, job_id: str) -> Job:
    """The job followed without a lock: how long its end takes after the trigger."""
    job = Job(service, kind, job_id, None)
    job.reader.join(600)
    body = service.api.call("GET", f"/{kind}s/{job_id}").json()
    print(f"{kind} {job_id} without a lock: {body['state']}, ended {job.tail_s:.1f} s after "
          "its trigger")
    check(body["state"] == "done", f"the unlocked {kind} is done")
    return job


def in_a_lock(service: Service, kind: str, job_id: str, lock_s: float,
              reference: Job) -> dict[str, Any]:
    """Hold the exclusive lock for ``lock_s`` from the job's trigger on; check the job."""
    api, database = service.api, service.database
    table, path = f"{kind}s", f"/{kind}s/{job_id}"
    job = Job(service, kind, job_id, lock_s)
    if not job.locked.wait(600):
        raise CheckFailedError(f"the {kind} never reached its trigger: {job.events}")
    assert job.lock is not None and job.triggered_at is not None
    rows = set()
    while time.time() < job.triggered_at + lock_s:
        api.call("GET", path)
        rows.add(job.lock.execute(f"SELECT state FROM {table} WHERE id = ?",
                                  (job_id,)).fetchone()[0])
        time.sleep(0.5)
    job.lock.execute("ROLLBACK")
    released_at = time.time()
    job.lock.close()
    print(f"{kind} {job_id}: exclusive lock held {released_at - job.triggered_at:.1f} s from "
          "its trigger")
    check(reference.tail_s < lock_s, f"unlocked, the same job ended {reference.tail_s:.1f} s "
                                     f"after its trigger: its end falls inside the lock")
    check(rows == {"running"}, f"the database row said {sorted(rows)} while locked")
    job.reader.join(600)
    check(not job.reader.is_alive(), "the listener's stream ended")
    last = job.events[-1] if job.events else {}
    check(last.get("type") == "state" and last.get("state") == "done",
          f"its last event is the done state, {job.ended_at - released_at:.1f} s after the "
          "lock ended")
    # A new listener gets the state, then what comes after it: the locked job's progress is
    # the unlocked one's from the event it was first sent, the trigger, on.
    since = reference.progress[len(reference.progress) - len(job.progress):]
    check(len(job.progress) >= 2 and job.progress == since and job.ids == sorted(set(job.ids)),
          f"every progress event from the trigger on, in order: {len(job.progress)} "
          f"locked, the unlocked job's last {len(since)} {since}; ids rise"
          + ("" if job.progress == since else f"; locked: {job.progress}"))
    body = api.call("GET", path).json()
    conn = sqlite3.connect(database)
    state, result = conn.execute(f"SELECT state, result FROM {table} WHERE id = ?",
                                 (job_id,)).fetchone()
    conn.close()
    check(state == body["state"] == "done" and json.loads(result) == body["result"],
          "stored done, with the result the service answers")
    return body


def twice(service: Service, kind: str, start: str, lock_s: float) -> tuple[Job, dict[str, Any]]:
    """Start a ``kind`` job by ``POST start`` twice: followed without a lock, then in one
    (``in_a_lock``, with the first as its reference); the first job and the locked one's body."""
    def started() -> str:
        r = service.api.call("POST", start, json={})
        check(r.status_code == 202, f"{kind} started ({r.status_code})")
        return str(r.json()["id"])

    reference = unlocked(service, kind, started())
    return reference, in_a_lock(service, kind, started(), lock_s, reference)


def same_solution(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Two calibration results agree on the camera, hand-eye and target pose (1e-9)."""
    def numbers(doc: dict[str, Any]) -> np.ndarray:
        return np.concatenate([np.ravel(doc["camera"]["K"]), np.ravel(doc["camera"]["dist"]),
                               np.ravel(doc["hand_eye"]["matrix"]),
                               np.ravel(doc["target_pose"]["matrix"])])

    return bool(np.allclose(numbers(a), numbers(b), rtol=0.0, atol=1e-9))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lock-s", type=float, default=40.0, help="lock duration, seconds")
    parser.add_argument("--stations", type=int, default=12, help="stations of the run")
    args = parser.parse_args(argv)
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLCAL_")}
    with tempfile.TemporaryDirectory(prefix="database-lock-") as tmp:
        data = Path(tmp) / "data"
        data.mkdir()
        with local_service(data, KEY, ServeOptions(env=env)) as service, \
                contextlib.closing(Client(service.url)) as api:
            try:
                run_id = api.call("POST", "/runs", json={"stations": args.stations}).json()["id"]
                run = api.until(f"/runs/{run_id}", lambda b: b["state"] != "capturing")
                check(run["state"] == "done", f"run {run_id}: {run['stations_captured']} "
                                              "stations captured without a lock")
                cell = Service(api, service.url, data / "cellcal.db")
                free, locked = twice(cell, "calibration", f"/runs/{run_id}/calibrations",
                                     args.lock_s)
                reference = api.call("GET", f"/calibrations/{free.id}").json()
                check(same_solution(locked["result"], reference["result"]),
                      "the locked calibration's result is the unlocked one's (nothing lost)")
                _, locked = twice(cell, "validation", f"/calibrations/{locked['id']}/checks",
                                  args.lock_s)
                check(locked["result"]["kind"] == "check", "the locked re-check's report is stored")
                r = api.call("POST", "/runs", json={"stations": 3})
                check(r.status_code == 201, f"a new run starts afterwards ({r.status_code})")
                check(all(s < 500 for s in api.statuses),
                      f"{len(api.statuses)} answers, none 5xx")
            except CheckFailedError:
                print(service.log.read_text()[-4000:], file=sys.stderr)
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
