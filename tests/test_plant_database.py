"""Many cell services on one database (a plant), on SQLite and PostgreSQL: cells never block
each other, concurrent activations leave one current calibration per cell and setup and no
duplicate history, and a service recovers only the work of its own cell's dead services."""

from __future__ import annotations

import datetime as dt
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service.app import create_app
from service.store.records import (
    ActivationRecord,
    ActiveCalibrationRecord,
    CalibrationRecord,
    InstanceRecord,
    RunRecord,
    utcnow,
)
from tests.support.results import full_result
from tests.support.service import (
    AUTH,
    finished,
    gated_opener,
    poses,
    read_events,
    service,
    settings,
    start_run,
    wait_run,
)

pytestmark = [pytest.mark.usefixtures("database"), pytest.mark.pg_fast,
              pytest.mark.timeout(120)]

BOARD = {"inner_corners": [11, 8], "square_size_m": 0.03}


@contextmanager
def services(tmp_path: Path, *cells: str) -> Iterator[list[TestClient]]:
    """One service per cell name on one database (each with its own images directory)."""
    with ExitStack() as stack:
        clients = []
        for k, cell in enumerate(cells):
            app = create_app(settings(tmp_path / f"s{k}", cell=cell,
                                      database_url=_shared_url(tmp_path)))
            client = stack.enter_context(TestClient(app))
            client.headers.update(AUTH)
            clients.append(client)
        yield clients


def _shared_url(tmp_path: Path) -> str:
    """The test's PostgreSQL database, or one SQLite file for all services."""
    return settings(tmp_path).database_url or f"sqlite:///{tmp_path / 'plant.db'}"


def test_runs_in_different_cells_never_block_each_other(tmp_path: Path) -> None:
    with services(tmp_path, "press-1", "press-2") as (one, two):
        first, second = (c.post("/runs", json={"poses": poses(3)}) for c in (one, two))
        assert (first.status_code, second.status_code) == (201, 201), second.text
        for client, r in ((one, first), (two, second)):
            run = wait_run(client, r.json()["id"], finished)
            assert (run["robot"], run["state"], run["stations_captured"]) == (
                "mock://", "done", 3)


def add_calibrations(client: TestClient, cell: str, n: int) -> list[str]:
    """``n`` finished calibrations of one run of ``cell``; their ids."""
    with client.app.state.db.session() as s:
        run = RunRecord(cell=cell, robot="mock://", state="done", setup="eye_in_hand",
                        target=BOARD, poses=[])
        s.add(run)
        s.flush()
        cals = [CalibrationRecord(cell=cell, run_id=run.id, state="done", options={},
                                  result=full_result()) for _ in range(n)]
        s.add_all(cals)
        s.commit()
        return [cal.id for cal in cals]


def test_concurrent_activations_leave_one_current_and_no_duplicate_history(
        tmp_path: Path) -> None:
    """Two services activate three calibrations of one cell from 8 threads at once, 120
    times: one current calibration, and a history row only where the current one changed."""
    with services(tmp_path, "press-1", "press-1") as clients:
        cal_ids = add_calibrations(clients[0], "press-1", 3)
        start = threading.Barrier(8)

        def activate(k: int) -> int:
            if k < 8:
                start.wait()
            return clients[k % 2].post(f"/calibrations/{cal_ids[k % 3]}/activate").status_code

        with ThreadPoolExecutor(8) as pool:
            codes = list(pool.map(activate, range(120)))
        assert codes == [200] * 120
        with clients[0].app.state.db.session() as s:
            current = s.scalars(select(ActiveCalibrationRecord)).all()
            history = s.scalars(select(ActivationRecord).order_by(ActivationRecord.id)).all()
    assert len(current) == 1
    assert current[0].calibration_id == history[-1].calibration_id
    assert current[0].activation_id == history[-1].id
    repeats = [a.id for a, b in pairwise(history) if a.calibration_id == b.calibration_id]
    assert repeats == []


def test_the_same_activation_from_many_requests_is_one_history_row(tmp_path: Path) -> None:
    with services(tmp_path, "press-1", "press-1") as clients:
        (cal_id,) = add_calibrations(clients[0], "press-1", 1)
        with ThreadPoolExecutor(8) as pool:
            codes = list(pool.map(
                lambda k: clients[k % 2].post(f"/calibrations/{cal_id}/activate").status_code,
                range(40)))
        assert codes == [200] * 40
        with clients[0].app.state.db.session() as s:
            assert s.scalar(select(func.count()).select_from(ActivationRecord)) == 1


def test_a_restart_recovers_only_its_cells_dead_work(tmp_path: Path) -> None:
    """A run of cell A whose service's lease ran out is interrupted when a service of cell A
    starts, not when one of cell B does; a live service's run is never touched."""
    with services(tmp_path, "press-a") as (a,):
        with a.app.state.db.session() as s:
            dead = InstanceRecord(cell="press-a", host="elsewhere", port=8000, pid=1,
                                  heartbeat_at=utcnow() - dt.timedelta(minutes=5))
            s.add(dead)
            s.flush()
            orphan = RunRecord(cell="press-a", robot="mock://9", state="capturing", owner="x",
                               instance_id=dead.id, setup="eye_in_hand", target=BOARD,
                               poses=poses(2))
            s.add(orphan)
            s.commit()
        live = a.post("/runs", json={"mode": "external"}).json()["id"]
        with services(tmp_path, "press-b") as (b,):
            assert b.get(f"/runs/{orphan.id}").json()["state"] == "capturing"
        with services(tmp_path, "press-a") as (again,):
            assert again.get(f"/runs/{orphan.id}").json()["state"] == "interrupted"
            assert again.get(f"/runs/{live}").json()["state"] == "capturing"
        with a.app.state.db.session() as s:
            assert s.get(InstanceRecord, dead.id) is None


def test_a_runs_events_can_be_followed_on_another_service(tmp_path: Path,
                                                         database: str | None) -> None:
    """On PostgreSQL a client follows a run on a service that does not drive it: the events
    come over LISTEN/NOTIFY as they happen, the same ones, ending with the final state."""
    if database is None:
        pytest.skip("SQLite has no relay: the service that drives a run serves its events")
    gate = threading.Event()
    with services(tmp_path, "press-1") as (other,), \
            service(tmp_path / "driver", gated_opener(tmp_path / "driver", 1, gate)) as driver:
        run_id = start_run(driver, 4)
        wait_run(driver, run_id, lambda r: r["stations_captured"] == 1)
        subscribed = threading.Event()

        def first_event_read(events: list[Any]) -> bool:
            subscribed.set()  # the stream listens before it sends its first event
            return False

        with ThreadPoolExecutor(1) as pool:
            followed = pool.submit(read_events, other, run_id, until=first_event_read)
            assert subscribed.wait(60)
            gate.set()
            remote = followed.result(timeout=60)
        local = read_events(driver, run_id, last_event_id="0")
    assert remote[0][1] == "state" and remote[0][2]["stations_captured"] == 1
    assert remote[1:] == [e for e in local if e[0] > remote[0][0]]
    assert [kind for _, kind, _ in remote[1:]] == ["station"] * 3 + ["state"]
    assert remote[-1][2]["state"] == "done"
