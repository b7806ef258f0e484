"""The service's log (issue 19): runs and calibrations say their lifecycle at INFO, and with
``--log-format json`` every line, access lines included, is one JSON object."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.serving.local import ServeOptions, local_service
from service.serving.logs import JSONLines, lifecycle
from tests.support.service import KEY


def _wait_final(url: str, headers: dict[str, str], path: str) -> dict[str, Any]:
    deadline = time.monotonic() + 240
    while (doc := httpx.get(url + path, headers=headers).json())["state"] in ("capturing",
                                                                            "running"):
        assert time.monotonic() < deadline, doc
        time.sleep(0.2)
    return doc


@pytest.mark.timeout(300)
def test_json_log_tells_the_lifecycle_of_a_run_and_its_calibration(tmp_path: Path) -> None:
    log = tmp_path / "serve.log"
    options = ServeOptions(log=log, args=("--log-format", "json"))
    with local_service(tmp_path / "data", KEY, options) as service:
        headers = {"Authorization": f"Bearer {KEY}"}
        run = httpx.post(f"{service.url}/runs", json={"stations": 4}, headers=headers).json()
        assert _wait_final(service.url, headers, f"/runs/{run['id']}")["state"] == "done"
        cal = httpx.post(f"{service.url}/runs/{run['id']}/calibrations", json={},
                         headers=headers).json()
        final = _wait_final(service.url, headers, f"/calibrations/{cal['id']}")["state"]
    lines = [line for line in log.read_text().splitlines() if line.startswith("{")]
    records = [json.loads(line) for line in lines]
    events = [(r["kind"], r["id"], r["event"]) for r in records if r.get("logger") ==
              "cellcal.lifecycle"]
    assert events == [("run", run["id"], "created"), ("run", run["id"], "done"),
                      ("calibration", cal["id"], "started"),
                      ("calibration", cal["id"], final)]
    done = next(r for r in records if r.get("event") == "done" and r.get("kind") == "run")
    assert done["level"] == "INFO" and done["stations_captured"] == 4
    assert any(r["logger"] == "uvicorn.access" for r in records)  # access lines too
    assert all(line.startswith("{") for line in log.read_text().splitlines()
               if "uvicorn" in line or "cellcal" in line)


def test_a_lifecycle_record_as_text_and_json(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("INFO", logger="cellcal.lifecycle"):
        lifecycle("failed", "run", "abc", state="failed", code="board_mismatch")
    record = caplog.records[-1]
    assert record.getMessage() == "run abc failed (state=failed code=board_mismatch)"
    doc = json.loads(JSONLines().format(record))
    assert {k: doc[k] for k in ("level", "event", "kind", "id", "state", "code")} == {
        "level": "INFO", "event": "failed", "kind": "run", "id": "abc", "state": "failed",
        "code": "board_mismatch"}
