"""History mode of the service benchmark: API latency over a plant's history, on SQLite and on
PostgreSQL (``python -m benchmarks.service --history``).

Acceptance target (issue 21): with 10,000 calibrations and 200,000 stations stored, 20
concurrent clients and 5 server-sent-event listeners, the p99 of every common GET under 50 ms
on both databases, and the p99 at 10,000 calibrations at most 1.2x the p99 at 1,000.

For each database (a SQLite file; a throwaway PostgreSQL server, ``tests/support/postgres``)
the history is seeded straight into the tables (a run of 20 stations with real-sized
detections, 88 corners each, and one finished calibration with a full result per run, over
20 cells, every 10th calibration of a cell activated; on PostgreSQL then ``VACUUM ANALYZE``),
then ``cellcal serve --mock`` runs on it in a subprocess. The load: 20 clients each send a
GET from the mix below and pause 0.2 s (a dashboard polling); 5 listeners follow the event
stream of the newest run to its end, then the next run's; one client opens an external run
(``POST /runs``) and finishes it every 0.5 s. Latency is measured at the client, request sent
to body read.

Both history sizes are measured alike and by turns: each has its own database, seeded alike,
and its own service, both running; each service gets a warm-up (not measured), then
``--rounds`` rounds of a ``--seconds`` block on each, in A B B A order, so a change of the
shared machine's load during the run falls on both sizes.
Four rounds of 40 s give each request kind about 2,000 requests per size, so its p99 is not a
handful of samples; the report gives the pooled figures and their spread over the rounds
(``benchmarks.history_report``).

Two load generators, each in turn on the same servers (``--client``): ``threads``, the load
above as 26 ``httpx`` threads in this process, and ``light``, the same load from a separate
asyncio process (``benchmarks.history_client``). On 2 cores the threaded client's own CPU and
GIL are part of its figures; a plant's dashboards run on other computers. Both are reported,
with the server's and the client's CPU per request.

    python -m benchmarks.service --history           # 1,000 and 10,000 calibrations
    python -m benchmarks.service --history --quick   # 200 and 2,000, 5 stations per run
    python -m benchmarks.service --history --backend postgresql --client threads --rounds 1

Prints a table and writes benchmarks/results/service_history.png. Requests go only to
127.0.0.1, bounded in time; servers and temporary directories are removed on every exit.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import random
import secrets
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from sqlalchemy import create_engine, insert

from benchmarks.history_client import CELLS, POST_EVERY_S, THINK_S, get_mix
from service.serving.local import LocalService, ServeOptions, local_service
from service.store.db import Database
from service.store.pages import Cursor
from service.store.records import (
    ActivationRecord,
    ActiveCalibrationRecord,
    CalibrationRecord,
    RunRecord,
    StationRecord,
    new_id,
)

TARGET_P99_MS = 50.0
TARGET_GROWTH = 1.2
CLIENTS, LISTENERS = 20, 5
T0 = dt.datetime(2025, 1, 1, tzinfo=dt.UTC)


@dataclass
class Latencies:
    """Seconds per request kind, and the answers that were not 2xx."""

    by_kind: dict[str, list[float]] = field(default_factory=dict)
    errors: dict[str, int] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, kind: str, seconds: float, status: int) -> None:
        with self.lock:
            self.by_kind.setdefault(kind, []).append(seconds)
            if status >= 300:
                self.errors[kind] = self.errors.get(kind, 0) + 1


# ---- seeding -------------------------------------------------------------------------------

def _result() -> dict[str, Any]:
    from tests.test_exports import full_result  # a complete cellcal/result@1 document

    return full_result()


def seed(url: str, *, first: int, count: int, stations: int) -> list[str]:
    """Calibrations ``first`` .. ``first + count - 1``, each with its run of ``stations``
    stations, one a minute from T0; activations every 10th; their ids."""
    rng = np.random.default_rng(first)
    result = _result()
    engine = create_engine(url)
    cal_ids = []
    with engine.begin() as conn:
        for start in range(first, first + count, 500):
            runs, rows, cals, acts = [], [], [], []
            for k in range(start, min(start + 500, first + count)):
                at = T0 + dt.timedelta(minutes=k)
                cell = f"cell-{k % CELLS:02d}"
                run_id, cal_id = new_id(), new_id()
                runs.append(dict(id=run_id, cell=cell, robot="mock://", state="done",
                                 mode="robot", setup="eye_in_hand", poses=[[0.3] * 6] * stations,
                                 target={"inner_corners": [11, 8], "square_size_m": 0.03},
                                 created_at=at, updated_at=at))
                corners = np.round(rng.uniform(0, 1280, (stations, 88, 2)), 2).tolist()
                rows += [dict(run_id=run_id, index=i, state="captured", target_pose=[0.3] * 6,
                              tcp_pose=[0.3] * 6, image_path=f"runs/{run_id}/{i:04d}.png",
                              image_size=[1280, 1024], attempts=1, captured_at=at,
                              detection={"ok": True, "corners": corners[i], "sharpness": 1.0})
                         for i in range(stations)]
                cals.append(dict(id=cal_id, cell=cell, run_id=run_id, state="done",
                                 options={"method": "joint"}, result=result, created_at=at,
                                 finished_at=at))
                if (k // CELLS) % 10 == 0:  # each cell: every 10th calibration
                    acts.append(dict(cell=cell, setup="eye_in_hand", robot="mock://",
                                     calibration_id=cal_id, activated_at=at))
                cal_ids.append(cal_id)
            for table, values in ((RunRecord, runs), (StationRecord, rows),
                                  (CalibrationRecord, cals), (ActivationRecord, acts)):
                if values:
                    conn.execute(insert(table.__table__), values)
    _set_active(engine)
    engine.dispose()
    _settle(url)
    return cal_ids


def _settle(url: str) -> None:
    """After the bulk insert, PostgreSQL's ``VACUUM ANALYZE`` (its manual's advice after a bulk
    load): otherwise autovacuum does it during the measured load (seen: the 9,000 calibrations
    inserted between the levels were vacuumed and analysed 1-18 s into it, and the all-GET p99
    was 303 ms against 72-95 ms after a settled seed). A history that grew over a year has had
    that done long ago."""
    if not url.startswith("postgresql"):
        return
    engine = create_engine(url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.exec_driver_sql("VACUUM ANALYZE")
    engine.dispose()


def _set_active(engine: Any) -> None:
    """``active_calibrations`` from the newest activation per cell (as activating does)."""
    from sqlalchemy import delete, func, select

    with engine.begin() as conn:
        conn.execute(delete(ActiveCalibrationRecord.__table__))
        newest = select(func.max(ActivationRecord.id)).group_by(ActivationRecord.cell)
        for row in conn.execute(select(ActivationRecord.__table__)
                                .where(ActivationRecord.id.in_(newest))):
            conn.execute(insert(ActiveCalibrationRecord.__table__).values(
                cell=row.cell, setup=row.setup, calibration_id=row.calibration_id,
                activation_id=row.id))


# ---- load ----------------------------------------------------------------------------------

@dataclass
class Load:
    """What the load threads share: the service, the measurements, the newest run."""

    url: str
    headers: dict[str, str]
    out: Latencies = field(default_factory=Latencies)
    stop: threading.Event = field(default_factory=threading.Event)
    newest_run: list[str] = field(default_factory=list)

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=self.headers, timeout=30.0)


def dashboard(ld: Load, mix: list[Any], seed_: int) -> None:
    """One client: a GET from the mix, then a pause of about ``THINK_S``."""
    rng = random.Random(seed_)
    with ld.client() as c:
        while not ld.stop.wait(THINK_S * rng.uniform(0.5, 1.5)):
            kind, path = rng.choice(mix)
            t0 = time.perf_counter()
            r = c.get(path(rng))
            ld.out.add(kind, time.perf_counter() - t0, r.status_code)


def run_opener(ld: Load) -> None:
    """Opens an external run and finishes it, every ``POST_EVERY_S``."""
    with ld.client() as c:
        while not ld.stop.wait(POST_EVERY_S):
            t0 = time.perf_counter()
            r = c.post("/runs", json={"mode": "external"})
            ld.out.add("POST /runs", time.perf_counter() - t0, r.status_code)
            if r.status_code == 201:
                ld.newest_run[:] = [r.json()["id"]]
                c.post(f"/runs/{r.json()['id']}/finish")


def listener(ld: Load) -> None:
    """Follows the newest run's event stream to its end, then the next newer run's (a page
    showing the newest run). It does not reconnect to a run whose stream has ended: that
    answers its final state at once, so a listener doing it asks ~15 times a second."""
    followed = None
    with ld.client() as c:
        while not ld.stop.is_set():
            newest = ld.newest_run[0] if ld.newest_run else None
            if newest is None or newest == followed:
                ld.stop.wait(0.05)  # no request: waits for the opener's next run
                continue
            followed = newest
            with c.stream("GET", f"/runs/{newest}/events") as r:
                for _ in r.iter_lines():
                    if ld.stop.is_set():
                        break


def load(url: str, key: str, mix: list[Any], seconds: float) -> Latencies:
    """The clients, listeners and run opener against ``url`` for ``seconds``."""
    ld = Load(url, {"Authorization": f"Bearer {key}"})
    threads = [threading.Thread(target=dashboard, args=(ld, mix, k)) for k in range(CLIENTS)]
    threads += [threading.Thread(target=listener, args=(ld,)) for _ in range(LISTENERS)]
    threads.append(threading.Thread(target=run_opener, args=(ld,)))
    for t in threads:
        t.start()
    ld.stop.wait(seconds)
    ld.stop.set()
    for t in threads:
        t.join(60.0)
    return ld.out


def load_light(url: str, key: str, spec: dict[str, Any],
               seconds: float) -> tuple[Latencies, float]:
    """The same load from a separate light client process (``benchmarks.history_client``);
    the latencies and the CPU seconds the client process used during the load."""
    import json
    import subprocess
    import sys

    spec = {**spec, "url": url, "key": key, "seconds": seconds, "clients": CLIENTS,
            "listeners": LISTENERS}
    done = subprocess.run([sys.executable, "-m", "benchmarks.history_client"], check=True,
                          input=json.dumps(spec).encode(), capture_output=True,
                          timeout=seconds + 120.0)
    got = json.loads(done.stdout)
    return Latencies(by_kind=got["by_kind"], errors=got["errors"]), got["cpu_s"]


#: The two load generators: ``threads``, 26 ``httpx`` threads in this process (what the
#: benchmark always did), and ``light``, one asyncio process (``benchmarks.history_client``).
CLIENT_KINDS = ("threads", "light")


def cpu_seconds(pid: int) -> float:
    """CPU time (user + system) a process and its threads used so far, seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def loaded(client: str, svc: LocalService, mix: list[Any], spec: dict[str, Any],
           seconds: float) -> tuple[Latencies, float, float]:
    """The load from ``client``; its latencies and the server's and the client's CPU seconds
    meanwhile."""
    server0, mine0 = cpu_seconds(svc.proc.pid), time.process_time()
    if client == "threads":
        got = load(svc.url, svc.key, mix, seconds)
        own = time.process_time() - mine0
    else:
        got, own = load_light(svc.url, svc.key, spec, seconds)
    return got, cpu_seconds(svc.proc.pid) - server0, own


# ---- the two databases, each at both sizes ----------------------------------------------

@contextlib.contextmanager
def databases(kind: str, tmp: Path, count: int) -> Iterator[list[str]]:
    """``count`` new empty databases of ``kind`` at the newest schema; their URLs."""
    if kind == "sqlite":
        urls = [f"sqlite:///{tmp / f'history-{k}.db'}" for k in range(count)]
        for url in urls:
            Database(url).close()
        yield urls
        return
    from tests.support.postgres import PostgresServer

    server = PostgresServer().start()
    try:
        urls = [server.url(server.create_database(f"history{k}_")) for k in range(count)]
        for url in urls:
            Database(url).close()
        yield urls
    finally:
        server.stop()


@dataclass(frozen=True)
class Level:
    """One measured block: a database of ``calibrations`` loaded by ``client`` for one
    round."""

    backend: str
    calibrations: int
    stations: int
    #: Which load generator (``CLIENT_KINDS``).
    client: str
    #: Which round of the paired small / large blocks.
    round: int
    latencies: Latencies
    #: The machine's 1-minute load average at the end of the block (2 cores: above 2, the
    #: service waited for CPU).
    load_average: float
    #: CPU seconds per request of the server process and of the load generator.
    server_cpu_ms: float
    client_cpu_ms: float


@dataclass(frozen=True)
class Plan:
    """How long the load runs: a warm-up of ``warmup_s`` on each service (not measured),
    then ``rounds`` rounds, each a block of ``block_s`` on the small history and one on the
    large, in A B B A order (so a drift of the machine's load falls on both alike)."""

    levels: tuple[int, int]
    stations: int
    block_s: float
    rounds: int
    warmup_s: float


@dataclass(frozen=True)
class Served:
    """One service over one seeded history, with what its load's requests need."""

    calibrations: int
    svc: LocalService
    mix: list[Any]
    spec: dict[str, Any]


def measure(kind: str, plan: Plan, clients: tuple[str, ...]) -> list[Level]:
    """Seed one database per history size, serve each, and load them by turns, with each
    of ``clients``: both sizes are measured alike, the same client, warm-up and concurrency,
    interleaved in time."""
    found: list[Level] = []
    with tempfile.TemporaryDirectory(prefix="cellcal-history-") as tmp_dir, \
            databases(kind, Path(tmp_dir), len(plan.levels)) as urls, \
            contextlib.ExitStack() as stack:
        served = [stack.enter_context(_served(kind, url, level, plan.stations,
                                              Path(tmp_dir) / f"data-{level}"))
                  for url, level in zip(urls, plan.levels, strict=True)]
        for client in clients:
            for one in served:
                loaded(client, one.svc, one.mix, one.spec, plan.warmup_s)
            for r in range(plan.rounds):
                for one in served if r % 2 == 0 else served[::-1]:
                    got, server_cpu, client_cpu = loaded(client, one.svc, one.mix, one.spec,
                                                         plan.block_s)
                    n = max(1, sum(len(v) for v in got.by_kind.values()))
                    found.append(Level(kind, one.calibrations, one.calibrations * plan.stations,
                                       client, r, got, os.getloadavg()[0],
                                       1e3 * server_cpu / n, 1e3 * client_cpu / n))
            print(f"  {kind}: {client} client measured (load average "
                  f"{os.getloadavg()[0]:.1f})", flush=True)
    return found


@contextlib.contextmanager
def _served(kind: str, url: str, level: int, stations: int,
            data_dir: Path) -> Iterator[Served]:
    """``url`` seeded with ``level`` calibrations and served by ``cellcal serve --mock``."""
    key = secrets.token_urlsafe(24)
    t0 = time.perf_counter()
    cal_ids = seed(url, first=0, count=level, stations=stations)
    print(f"  {kind}: {level:,} calibrations seeded ({time.perf_counter() - t0:.0f} s)",
          flush=True)
    env = {**_env(), "CELLCAL_DATABASE_URL": url, "CELLCAL_CELL": "cell-00"}
    with local_service(data_dir, key, ServeOptions(env=env, startup_timeout=60.0)) as svc:
        run_ids = [run["id"] for run in httpx.get(
            f"{svc.url}/runs?limit=500", headers={"Authorization": f"Bearer {key}"},
            timeout=30).json()]
        deep = _deep_cursor(url, cal_ids)
        yield Served(level, svc, get_mix(cal_ids, run_ids, deep),
                     {"cal_ids": cal_ids, "run_ids": run_ids, "deep": deep})


def _deep_cursor(url: str, cal_ids: list[str]) -> str:
    """A cursor near the oldest end of the history (the page a deep scroll reads)."""
    from sqlalchemy.orm import Session

    engine = create_engine(url)
    with Session(engine) as s:
        cal = s.get(CalibrationRecord, cal_ids[len(cal_ids) // 20])
        cursor = Cursor.of(cal).encode()
    engine.dispose()
    return cursor


def _env() -> dict[str, str]:
    from benchmarks.service_loop import clean_env

    return clean_env()


#: The two databases (``--backend``).
BACKENDS = ("sqlite", "postgresql")


def run_history(*, quick: bool, seconds: float | None, rounds: int | None = None,
                clients: tuple[str, ...] = CLIENT_KINDS,
                backends: tuple[str, ...] = BACKENDS) -> int:
    """The ``backends`` (default both databases), then the report; 0 if every target is met,
    else 1."""
    from benchmarks.history_report import report

    plan = (Plan((200, 2000), 5, seconds or 4.0, rounds or 2, 1.0) if quick else
            Plan((1000, 10000), 20, seconds or 40.0, rounds or 4, 5.0))
    found: list[Level] = []
    for kind in backends:
        found += measure(kind, plan, clients)
    return 0 if report(found) else 1
