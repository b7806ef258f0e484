"""Idempotent starts (issue 19 item 7): a start repeated with the same Idempotency-Key gets the
first answer (one run, one id), also after a restart; the key with another body is 422; a key
whose first request failed can be used again; a key still being answered is 409."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.idempotency import request_hash
from service.app import create_app
from service.settings import Settings
from service.store.records import IdempotencyRecord, RunRecord

pytestmark = pytest.mark.usefixtures("database")

KEY = "test-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}
EXTERNAL = {"mode": "external"}


def _client(data_dir: Path) -> TestClient:
    client = TestClient(create_app(Settings(data_dir=data_dir, api_key=KEY)))
    client.headers.update(AUTH)
    return client


def _runs(client: TestClient) -> int:
    with client.app.state.db.session() as s:  # type: ignore[attr-defined]
        return s.query(RunRecord).count()


def test_the_same_start_twice_is_one_run_also_after_a_restart(tmp_path: Path) -> None:
    with _client(tmp_path) as client:
        first = client.post("/runs", json=EXTERNAL, headers={"Idempotency-Key": "click-1"})
        assert first.status_code == 201, first.text
        again = client.post("/runs", content=b'{ "mode" : "external" }',
                            headers={"Idempotency-Key": "click-1",
                                     "Content-Type": "application/json"})
        assert again.status_code == 201 and again.json() == first.json()
        assert again.headers["idempotent-replayed"] == "true"
        assert _runs(client) == 1
        # without a key the same body starts another run: refused as the robot is busy
        assert client.post("/runs", json=EXTERNAL).status_code == 409
    with _client(tmp_path) as restarted:
        replay = restarted.post("/runs", json=EXTERNAL, headers={"Idempotency-Key": "click-1"})
        assert replay.status_code == 201 and replay.json()["id"] == first.json()["id"]
        assert _runs(restarted) == 1


def test_the_key_with_another_request_is_422(tmp_path: Path) -> None:
    with _client(tmp_path) as client:
        assert client.post("/runs", json=EXTERNAL,
                           headers={"Idempotency-Key": "k-2"}).status_code == 201
        other = client.post("/runs", json={"mode": "external", "setup": "eye_to_hand"},
                            headers={"Idempotency-Key": "k-2"})
        assert other.status_code == 422
        assert other.json()["code"] == "idempotency_key_reused"
        run_id = client.get("/runs").json()[0]["id"]
        elsewhere = client.post(f"/runs/{run_id}/calibrations", json={},
                                headers={"Idempotency-Key": "k-2"})
        assert elsewhere.json()["code"] == "idempotency_key_reused"


def test_a_failed_start_frees_its_key(tmp_path: Path) -> None:
    with _client(tmp_path) as client:
        missing = client.post(f"/runs/{'0' * 32}/calibrations", json={},
                              headers={"Idempotency-Key": "k-3"})
        assert missing.status_code == 404
        retried = client.post("/runs", json=EXTERNAL, headers={"Idempotency-Key": "k-3"})
        assert retried.status_code == 201, retried.text


def test_a_key_in_flight_is_409_and_a_bad_key_400(tmp_path: Path) -> None:
    with _client(tmp_path) as client:
        with client.app.state.db.session() as s:  # type: ignore[attr-defined]
            s.add(IdempotencyRecord(cell=client.app.state.settings.cell,  # type: ignore[attr-defined]
                                    key="k-4", request_hash=request_hash(
                                        "POST", "/runs", b'{"mode": "external"}')))
            s.commit()
        busy = client.post("/runs", json=EXTERNAL, headers={"Idempotency-Key": "k-4"})
        assert busy.status_code == 409 and busy.json()["code"] == "request_in_progress"
        assert _runs(client) == 0
        bad = client.post("/runs", json=EXTERNAL, headers={"Idempotency-Key": "two words"})
        assert bad.status_code == 400 and bad.json()["code"] == "invalid_idempotency_key"
        assert _runs(client) == 0


def test_a_body_nested_too_deep_is_422_with_a_key_too(tmp_path: Path) -> None:
    """Issue 22, a variant of its bad-input checks: the key's request hash parsed the body
    first, and a body nested 100,000 levels deep made it a 500 (without a key FastAPI's own
    parser answered 422)."""
    nested = b'{"poses": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    with _client(tmp_path) as client:
        for headers in ({}, {"Idempotency-Key": "k-5"}):
            r = client.post("/runs", content=nested,
                            headers={"Content-Type": "application/json", **headers})
            assert r.status_code == 422 and r.json()["code"] == "invalid_request", r.text
        assert _runs(client) == 0
