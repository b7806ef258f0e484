"""The plant test (issue 21): many ``cellcal serve --mock`` services of different cells on one
PostgreSQL, all capturing, solving, activating and re-checking at once; then one host's
services killed with SIGKILL mid-run, restarted, their runs resumed; counted after each part.

A service drives one cell, so "3 hosts with 6 cells each" is 3 groups of 6 services (18
cells). Counts, from the database and the answers: stations lost (a finished run's indices not
0..n-1) or duplicated, runs/calibrations/validations left stuck (in flight with no live
service), active calibrations per cell and setup (exactly 1 each), and 5xx answers.

    python tools/plant_test.py                 # 3 x 6 cells, 8 stations per run
    python tools/plant_test.py --groups 2 --cells 2 --stations 6

Exit status 0 when every target holds. Uses a throwaway PostgreSQL server
(tests/support/postgres.py) and temporary directories, removed at the end; requests go only
to 127.0.0.1.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import secrets
import signal
import sys
import tempfile
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import create_engine, text

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.serving.local import LocalService, ServeOptions, local_service
from tests.support.postgres import PostgresServer

TIMEOUT_S = 900.0


class Plant:
    """The services, their answers and how many were 5xx."""

    def __init__(self, url: str, root: Path, stations: int) -> None:
        self.url, self.root, self.stations = url, root, stations
        self.key = secrets.token_urlsafe(24)
        self.services: dict[str, LocalService] = {}
        self.stacks: dict[str, contextlib.ExitStack] = {}
        self.status = Counter[int]()
        self.lock = threading.Lock()

    def start(self, cell: str) -> None:
        stack = contextlib.ExitStack()
        env = {k: v for k, v in os.environ.items() if not k.startswith("CELLCAL_")}
        env.update(CELLCAL_DATABASE_URL=self.url, CELLCAL_CELL=cell, CELLCAL_LEASE_S="5")
        self.services[cell] = stack.enter_context(local_service(
            self.root / cell, self.key, ServeOptions(env=env, startup_timeout=120.0,
                                                     log=self.root / f"{cell}.log")))
        self.stacks[cell] = stack

    def kill(self, cell: str) -> None:
        """SIGKILL the service and its calibration workers (its process group)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.services[cell].proc.pid, signal.SIGKILL)
        self.services[cell].proc.wait()
        self.stacks.pop(cell).close()

    def call(self, cell: str, method: str, path: str, **kw: Any) -> httpx.Response:
        svc = self.services[cell]
        r = httpx.request(method, svc.url + path, timeout=120.0,
                          headers={"Authorization": f"Bearer {svc.key}"}, **kw)
        with self.lock:
            self.status[r.status_code] += 1
        return r

    def wait(self, cell: str, path: str, done: Any) -> dict[str, Any]:
        deadline = time.monotonic() + TIMEOUT_S
        while not done(doc := self.call(cell, "GET", path).json()):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{cell} {path}: {doc}")
            time.sleep(0.5)
        return doc

    def close(self) -> None:
        for stack in self.stacks.values():
            stack.close()


def capture(plant: Plant, cell: str) -> str:
    r = plant.call(cell, "POST", "/runs", json={"stations": plant.stations})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def finish(plant: Plant, cell: str, run_id: str) -> None:
    """Capture to the end, solve, activate, re-check."""
    run = plant.wait(cell, f"/runs/{run_id}", lambda d: d["state"] != "capturing")
    assert run["state"] == "done", run
    cal = plant.call(cell, "POST", f"/runs/{run_id}/calibrations", json={}).json()
    cal = plant.wait(cell, f"/calibrations/{cal['id']}", lambda d: d["state"] != "running")
    assert cal["state"] == "done", cal.get("error")
    assert plant.call(cell, "POST", f"/calibrations/{cal['id']}/activate").status_code == 200
    check = plant.call(cell, "POST", f"/calibrations/{cal['id']}/checks", json={}).json()
    plant.wait(cell, f"/validations/{check['id']}", lambda d: d["state"] != "running")


def kill_mid_run(plant: Plant, cell: str, run_id: str) -> None:
    """SIGKILL the cell's service once its run has 2 stations or more."""
    plant.wait(cell, f"/runs/{run_id}",
               lambda d: d["stations_captured"] + d["stations_skipped"] >= 2)
    plant.kill(cell)


def counts(url: str) -> dict[str, int]:
    """What the targets count, from the database."""
    engine = create_engine(url)
    q = {
        "stations duplicated": "SELECT count(*) FROM (SELECT run_id, index FROM stations "
                               "GROUP BY run_id, index HAVING count(*) > 1) d",
        "stations lost": "SELECT count(*) FROM runs r WHERE r.state = 'done' AND "
                         "(SELECT count(*) FROM stations s WHERE s.run_id = r.id) <> "
                         "json_array_length(r.poses::json) OR (SELECT max(index) FROM "
                         "stations s WHERE s.run_id = r.id) <> json_array_length(r.poses::json)"
                         " - 1",
        "runs stuck": "SELECT count(*) FROM runs WHERE state IN ('capturing', 'paused')",
        "calibrations stuck": "SELECT count(*) FROM calibrations WHERE state = 'running'",
        "validations stuck": "SELECT count(*) FROM validations WHERE state = 'running'",
        "cells with != 1 active": "SELECT count(*) FROM (SELECT cell FROM runs GROUP BY cell) c"
                                  " WHERE (SELECT count(*) FROM active_calibrations a WHERE "
                                  "a.cell = c.cell AND a.setup = 'eye_in_hand') <> 1",
        "runs done": "SELECT count(*) FROM runs WHERE state = 'done'",
        "stations": "SELECT count(*) FROM stations",
    }
    with engine.connect() as conn:
        found = {name: int(conn.execute(text(sql)).scalar() or 0) for name, sql in q.items()}
    engine.dispose()
    return found


def report(title: str, found: dict[str, int], status: Counter[int]) -> bool:
    fivexx = sum(n for code, n in status.items() if code >= 500)
    print(f"\n{title}")
    for name, n in {**found, "5xx answers": fivexx}.items():
        print(f"  {name:26} {n:>6}")
    return fivexx == 0 and all(found[k] == 0 for k in (
        "stations duplicated", "stations lost", "runs stuck", "calibrations stuck",
        "validations stuck", "cells with != 1 active"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--groups", type=int, default=3, help="hosts (groups of services)")
    parser.add_argument("--cells", type=int, default=6, help="cells (services) per group")
    parser.add_argument("--stations", type=int, default=8, help="stations per run")
    args = parser.parse_args()
    cells = [f"h{g}-cell{c}" for g in range(args.groups) for c in range(args.cells)]
    victims = cells[:args.cells]  # the first host's services
    server = PostgresServer().start()
    url = server.url(server.create_database("plant"))
    ok = True
    with tempfile.TemporaryDirectory(prefix="cellcal-plant-") as tmp:
        plant = Plant(url, Path(tmp), args.stations)
        try:
            t0 = time.monotonic()
            for cell in cells:  # from this thread: a service gets SIGTERM when its starter ends
                plant.start(cell)
            print(f"{len(cells)} services up in {time.monotonic() - t0:.0f} s", flush=True)
            with ThreadPoolExecutor(len(cells)) as pool:
                runs = dict(zip(cells, pool.map(lambda c: capture(plant, c), cells),
                                strict=True))
                # part 1: everyone captures, solves, activates and re-checks at once
                list(pool.map(lambda c: finish(plant, c, runs[c]), cells))
            ok &= report("all cells once", counts(url), plant.status)
            # part 2: a second round; the first host dies mid-run and comes back
            with ThreadPoolExecutor(len(cells)) as pool:
                runs = dict(zip(cells, pool.map(lambda c: capture(plant, c), cells),
                                strict=True))
                # each victim is killed as soon as its run is 2 stations in (waiting for all
                # of them first let a fast one finish its run before the kill, seen at load 30)
                list(pool.map(lambda c: kill_mid_run(plant, c, runs[c]), victims))
                print(f"killed -9: {', '.join(victims)}", flush=True)
                for cell in victims:
                    plant.start(cell)
                for cell in victims:
                    state = plant.call(cell, "GET", f"/runs/{runs[cell]}").json()["state"]
                    assert state == "interrupted", (cell, state)
                    assert plant.call(cell, "POST", f"/runs/{runs[cell]}/resume").status_code \
                        == 200
                list(pool.map(lambda c: finish(plant, c, runs[c]), cells))
            ok &= report("after kill -9 of one host's services and a restart", counts(url),
                         plant.status)
            print(f"\nwall time {time.monotonic() - t0:.0f} s; answers by status: "
                  f"{dict(sorted(plant.status.items()))}")
        finally:
            plant.close()
            server.stop()
    print("targets met" if ok else "targets NOT met")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
