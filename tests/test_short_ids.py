"""Short ids (issue 19 item 6): any unique prefix of an id names the record in every path; an
ambiguous prefix is 409 with the candidates; unknown prefixes stay 404."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service.store.records import RunRecord

pytestmark = pytest.mark.usefixtures("database")

KEY = "test-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(create_app(Settings(data_dir=tmp_path, api_key=KEY))) as c:
        c.headers.update(AUTH)
        yield c


def _external_run(client: TestClient) -> str:
    r = client.post("/runs", json={"mode": "external"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _add_runs(client: TestClient, ids: list[str]) -> None:
    """Finished runs with chosen ids, written straight into the app's database."""
    with client.app.state.db.session() as s:  # type: ignore[attr-defined]
        for run_id in ids:
            s.add(RunRecord(id=run_id, cell="c", robot="mock://", state="done", setup="eye_in_hand",
                            target={"type": "checkerboard", "inner_corners": [11, 8],
                                    "square_size_m": 0.03}, poses=[]))
        s.commit()


def test_a_unique_prefix_names_the_run_everywhere(client: TestClient) -> None:
    run_id = _external_run(client)
    short = run_id[:8]
    assert client.get(f"/runs/{short}").json()["id"] == run_id
    assert client.get(f"/runs/{short}/stations").json() == []
    with client.stream("GET", f"/runs/{short}/events") as events:  # streams take it too
        assert events.status_code == 200
        assert next(line for line in events.iter_lines() if line.startswith("data:"))
    cancelled = client.post(f"/runs/{short}/cancel")
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    assert client.get(f"/runs/{run_id}").json()["state"] == "cancelled"


def test_an_ambiguous_prefix_is_409_with_the_candidates(client: TestClient) -> None:
    ids = ["abcd" + "0" * 28, "abcd" + "1" * 28]
    _add_runs(client, ids)
    r = client.get("/runs/abcd")
    assert r.status_code == 409
    body = r.json()
    assert body["code"] == "ambiguous_id" and all(i in body["detail"] for i in ids)
    assert client.get("/runs/abcd1").json()["id"] == ids[1]  # one more digit settles it


@pytest.mark.parametrize("path", ["/runs/ffff", "/calibrations/ffff", "/validations/ffff/events",
                                  "/runs/abc"])
def test_prefixes_of_nothing_stay_404(client: TestClient, path: str) -> None:
    r = client.get(path)
    assert r.status_code == 404 and r.json()["code"] == "not_found"


def test_a_prefix_reveals_nothing_without_the_key(client: TestClient) -> None:
    _add_runs(client, ["abcd" + "0" * 28, "abcd" + "1" * 28])
    r = client.get("/runs/abcd", headers={"Authorization": "Bearer wrong-key-0123456789"})
    assert r.status_code == 401 and "abcd0" not in r.text
