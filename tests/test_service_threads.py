"""A request hands its work to a worker thread once (service.api.routing, issue 21): the cheap
dependencies run on the event loop, the endpoint and its database session in one
worker-thread call, which also closes the session."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import anyio.to_thread
import pytest
from fastapi.testclient import TestClient

from tests.support.service import external_run, service

pytestmark = pytest.mark.usefixtures("database")


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with service(tmp_path) as c:
        yield c


@pytest.fixture
def hand_overs(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names of the functions handed to a worker thread, in order."""
    names: list[str] = []
    run_sync = anyio.to_thread.run_sync

    async def counting(func: Any, *args: Any, **kwargs: Any) -> Any:
        names.append(getattr(func, "__name__", repr(func)))
        return await run_sync(func, *args, **kwargs)

    monkeypatch.setattr(anyio.to_thread, "run_sync", counting)
    return names


@pytest.mark.parametrize("path", ["/runs?limit=50", "/runs/{run}", "/calibrations?limit=50",
                                  "/calibrations?active=true&cell=c1", "/devices"])
def test_a_read_is_one_worker_thread_call(client: TestClient, hand_overs: list[str],
                                          path: str) -> None:
    run_id = external_run(client)
    hand_overs.clear()
    r = client.get(path.format(run=run_id))
    assert r.status_code == 200, r.text
    # FastAPI alone: the settings, the key check, the session's enter and exit, the endpoint
    # and the response validation, six in all. A session the endpoint's call left open would
    # be closed in a second one (``session.close``).
    assert hand_overs == ["_call_and_close"]


def test_an_unknown_id_is_still_404_with_the_error_body(client: TestClient) -> None:
    r = client.get("/runs/" + "0" * 32)
    assert r.status_code == 404
    assert r.json()["code"] == "not_found"


def test_every_request_closes_its_session(client: TestClient,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The session is no ``yield`` dependency: the route's one worker-thread call closes it
    (a session left open would still be in its transaction, holding its connection), and a
    request refused before its endpoint ran never began one."""
    run_id = external_run(client)
    db = client.app.state.db  # type: ignore[attr-defined]
    made: list[Any] = []

    def recorded(**kwargs: Any) -> Any:
        made.append(new_session(**kwargs))
        return made[-1]

    new_session = db.new_session
    monkeypatch.setattr(db, "new_session", recorded)
    for path, status in ((f"/runs/{run_id}", 200), ("/runs?limit=50", 200),
                         ("/calibrations?limit=50", 200), ("/runs/" + "0" * 32, 404),
                         ("/runs?limit=0", 422), ("/calibrations/active?cell=none", 404)):
        made.clear()
        assert client.get(path).status_code == status, path
        assert len(made) == 1, path
        assert not made[0].in_transaction(), path
