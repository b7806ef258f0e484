"""The service's log (issue 19): runs and calibrations say their lifecycle at INFO, and with
``--log-format json`` every line, access lines included, is one JSON object."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from service.serving.local import ServeOptions, local_service
from service.serving.logs import JSONLines, lifecycle
from tests.support.service import AUTH, KEY, finished, wait_calibration, wait_run


@pytest.mark.timeout(300)
def test_json_log_tells_the_lifecycle_of_a_run_and_its_calibration(tmp_path: Path) -> None:
    log = tmp_path / "serve.log"
    options = ServeOptions(log=log, args=("--log-format", "json"))
    with (local_service(tmp_path / "data", KEY, options) as service,
          httpx.Client(base_url=service.url, headers=AUTH, timeout=30) as client):
        run = client.post("/runs", json={"stations": 4}).json()
        assert wait_run(client, run["id"], finished, 240)["state"] == "done"
        cal = client.post(f"/runs/{run['id']}/calibrations", json={}).json()
        final = wait_calibration(client, cal["id"], 240)["state"]
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
