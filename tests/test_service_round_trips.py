"""What a read costs the database (issue 21): a ``GET`` runs its statements outside a
transaction (no ``BEGIN`` before, no ``ROLLBACK`` after) and pings no pooled connection it
used a moment ago; a connection the server dropped while idle is still replaced."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, text

from service.store import db
from service.store.records import StationRecord
from tests.support.service import external_run, service

pytestmark = [pytest.mark.usefixtures("database"), pytest.mark.pg_fast]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with service(tmp_path) as c:
        yield c


@pytest.fixture
def pings(client: TestClient, monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """The connections the service's pool pinged."""
    dialect = client.app.state.db.engine.dialect
    seen: list[object] = []
    do_ping = dialect.do_ping

    def counting(dbapi_connection: Any) -> bool:
        seen.append(dbapi_connection)
        return do_ping(dbapi_connection)

    monkeypatch.setattr(dialect, "do_ping", counting)
    return seen


def in_transaction_at_statements(client: TestClient) -> list[bool]:
    """Records, for each statement the service runs from now on, whether its connection was
    inside a database transaction (PostgreSQL: the driver sent ``BEGIN``)."""
    states: list[bool] = []
    engine = client.app.state.db.engine

    @event.listens_for(engine, "before_cursor_execute")
    def record(conn: Any, *_: Any) -> None:
        dbapi = conn.connection.dbapi_connection
        states.append(not getattr(dbapi, "autocommit", True)
                      if engine.dialect.name == "postgresql" else dbapi.in_transaction)

    return states


def test_a_read_runs_no_transaction_and_no_ping(client: TestClient,
                                                pings: list[object]) -> None:
    run_id = external_run(client)
    for path in ("/runs?limit=50", f"/runs/{run_id}", "/calibrations?limit=50",
                 "/calibrations?active=true&cell=c1"):
        states = in_transaction_at_statements(client)
        for _ in range(3):
            assert client.get(path).status_code == 200
        assert states and not any(states), path
    assert pings == []  # each connection was back in the pool moments ago


def test_a_write_still_runs_in_a_transaction(client: TestClient, database: str | None) -> None:
    if database is None:
        pytest.skip("pysqlite begins a transaction at the first write, not before it")
    states = in_transaction_at_statements(client)
    external_run(client)
    assert states and all(states)  # the POST's statements ran in its transaction


def test_a_connection_dropped_while_idle_is_replaced(client: TestClient, pings: list[object],
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     database: str | None) -> None:
    if database is None:
        pytest.skip("a SQLite file has no server to drop a connection")
    run_id = external_run(client)
    assert client.get(f"/runs/{run_id}").status_code == 200
    monkeypatch.setattr(db, "IDLE_PING_S", -1.0)  # every pooled connection counts as idle
    engine = client.app.state.db.engine
    with engine.connect() as conn:  # the server ends every other connection of the service
        conn.execute(text("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                          "WHERE datname = current_database() AND pid <> pg_backend_pid()"))
        conn.commit()
    r = client.get(f"/runs/{run_id}")
    assert r.status_code == 200, r.text
    assert pings  # found dead by the ping, not by the request's statement


def test_a_run_reads_its_station_errors_only_when_it_has_some(client: TestClient) -> None:
    """``GET /runs/{id}`` and ``GET /runs`` are one statement for runs none of whose stations
    failed (the run's row counts them); a run with a failed station gets its errors from one
    more statement."""
    run_id = external_run(client)
    seen: list[str] = []
    event.listen(client.app.state.db.engine, "before_cursor_execute",
                 lambda conn, cursor, sql, *rest: seen.append(sql))
    assert client.get(f"/runs/{run_id}").json()["station_errors"] == []
    assert client.get("/runs").json()[0]["station_errors"] == []
    assert len(seen) == 2
    with client.app.state.db.session() as s:
        s.add(StationRecord(run_id=run_id, index=0, state="skipped", error="no board",
                            error_code="not_detected", attempts=1,
                            commanded_tcp_pose=[0.3, 0.0, 0.4, 3.14, 0.0, 0.0]))
        s.commit()
    seen.clear()
    errors = [{"index": 0, "code": "not_detected", "detail": "no board"}]
    assert client.get(f"/runs/{run_id}").json()["station_errors"] == errors
    assert client.get("/runs").json()[0]["station_errors"] == errors
    assert len(seen) == 4
