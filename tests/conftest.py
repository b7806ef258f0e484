"""Fixtures every test module may use: the database a service test runs against.

A service test module that touches the database declares
``pytestmark = pytest.mark.usefixtures("database")`` (or ``"module_database"`` when a
module-scoped fixture opens apps); each of its tests then runs twice, on SQLite (a file in the
test's data directory, the default) and on PostgreSQL (a fresh database on a throwaway server,
``tests/support/postgres.py``, named by ``CELLCAL_DATABASE_URL`` for the test, its apps and the
``cellcal`` processes it starts).

The PostgreSQL variants are in the slow suite unless the test is marked ``pg_fast``, so
``make test`` stays quick and ``make test-slow`` runs them all. Without PostgreSQL installed
they are skipped with one line; in CI (``CI=true``) a missing PostgreSQL fails them instead.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.cli.main import main
from tests.support.helpers import SHARED
from tests.support.postgres import PostgresServer, PostgresUnavailableError
from tests.support.service import service

BACKENDS = ["sqlite", "postgresql"]


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """One PostgreSQL server per test process (each xdist worker has its own)."""
    try:
        server = PostgresServer().start()
    except PostgresUnavailableError as exc:
        if in_ci():
            pytest.fail(f"{exc}; CI must run the PostgreSQL tests (.ci/run installs it)")
        pytest.skip(f"{exc}: the PostgreSQL variants of the service tests are skipped")
    try:
        yield server
    finally:
        server.stop()


def _use_backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
                 ) -> Iterator[str | None]:
    """Point ``CELLCAL_DATABASE_URL`` at a fresh PostgreSQL database, or unset it (SQLite)."""
    if request.param == "sqlite":
        monkeypatch.delenv("CELLCAL_DATABASE_URL", raising=False)
        yield None
        return
    server: PostgresServer = request.getfixturevalue("postgres_server")
    name = server.create_database()
    monkeypatch.setenv("CELLCAL_DATABASE_URL", server.url(name))
    try:
        yield server.url(name)
    finally:
        monkeypatch.undo()
        server.drop_database(name)


@pytest.fixture(params=BACKENDS)
def database(request: pytest.FixtureRequest,
             monkeypatch: pytest.MonkeyPatch) -> Iterator[str | None]:
    """The test's database: None for SQLite in the data directory, else a PostgreSQL URL."""
    yield from _use_backend(request, monkeypatch)


@pytest.fixture(scope="module", params=BACKENDS)
def module_database(request: pytest.FixtureRequest) -> Iterator[str | None]:
    """``database`` shared by a module's tests (for module-scoped service fixtures)."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        yield from _use_backend(request, monkeypatch)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """PostgreSQL variants not marked ``pg_fast`` join the slow suite; no test's timeout is
    below the suite's (``timeout`` in pyproject.toml)."""
    floor = float(config.getini("timeout") or 0)
    for item in items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        on_postgres = "postgresql" in (params.get("database"), params.get("module_database"))
        if on_postgres and item.get_closest_marker("pg_fast") is None:
            item.add_marker(pytest.mark.slow)
        _timeout_at_least(item, floor)


def _timeout_at_least(item: pytest.Item, floor: float) -> None:
    """Raise a ``timeout`` marker below ``floor`` to it. A test's timeout only catches a hang
    (the tests wait for conditions, never for time), yet the 10-40 s ones failed tests that
    were merely slow: under four CPU burners, or other sessions' load (~25 on two cores), a
    test runs 5-10x slower than alone. A floor of 120 s was not enough either: at load 26-34
    two solver tests of tests/test_pipeline.py that took 21 and 39 s at load 20-27 ran past
    it (the kernel shares the cores between sessions, and the suite's own workers, services
    and browsers share the suite's part). A hang still fails, after ``floor`` s."""
    marker = item.get_closest_marker("timeout")
    if floor and marker is not None and marker.args and float(marker.args[0]) < floor:
        item.add_marker(pytest.mark.timeout(floor, *marker.args[1:], **marker.kwargs),
                        append=False)


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    """An authorised client of a service with mock devices on the test's data directory and
    database (``tests.support.service.service``)."""
    with service(tmp_path) as c:
        yield c


#: A real UR eye-in-hand set (``../shared/data``), calibrated once per test session by
#: ``ur_result``.
UR_SET = SHARED / "data" / "ur-kinect-lowR_highT"


def _session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory every process of this test session shares: the parent of the pytest-xdist
    workers' base directories, or the base directory itself without workers."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _calibrated_ur_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The directory of ``ur_result``'s station set and result, calibrated by the first
    process of the session that asks (3-4 CPU s) and read by the others: test_report and
    test_report_escaping may run on different workers."""
    shared = _session_dir(tmp_path_factory)
    d = shared / "ur-calibrated"
    with (shared / "ur-calibrated.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released as the file closes
        if not (d / "result.json").is_file():
            d.mkdir(exist_ok=True)
            doc = json.loads((UR_SET / "stations.json").read_text())
            for s in doc["stations"]:
                shutil.copy(UR_SET / s["image"], d / s["image"])
            blank = doc["stations"][4]["image"]
            cv2.imwrite(str(d / blank), np.full((720, 1280), 128, np.uint8))
            (d / "stations.json").write_text(json.dumps(doc))
            out = d / "result.part.json"
            assert main(["calibrate", str(d), "--out", str(out)]) in (0, 3)
            out.rename(d / "result.json")
    return d


@pytest.fixture(scope="module")
def ur_result(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """``cellcal calibrate`` on the real UR set, with one station's image replaced by a blank
    frame (a station the pipeline must reject with its reason): a copy of the session's one
    calibration, in a directory of the module's own."""
    d = tmp_path_factory.mktemp("ur")
    shutil.copytree(_calibrated_ur_set(tmp_path_factory), d, dirs_exist_ok=True)
    out = d / "result.json"
    return out, json.loads(out.read_text())
