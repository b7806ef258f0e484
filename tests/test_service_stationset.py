"""A service run as a station set (``GET /runs/{id}/stationset``): ``cellcal calibrate`` on it
gives the service's calibration (issue 9), and the download refuses what it cannot give."""

from __future__ import annotations

import io
import json
import re
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from calib import CheckerboardTarget, Station, Stations
from service.cli.main import main
from service.cli.report import station_images, station_set_identity
from service.stationsets.format import load_station_set, write_station_set
from tests.support.service import (
    assert_same_calibration,
    finished,
    gated_opener,
    get_report,
    service,
    start_run,
    wait_calibration,
    wait_run,
)

pytestmark = pytest.mark.usefixtures("database")




# only a hang guard: under four CPU burners the nice-10 report rendering gets a few % of a core
@pytest.mark.timeout(600)
def test_cellcal_calibrate_on_an_exported_run_gives_the_service_result(
        client: TestClient, tmp_path: Path) -> None:
    run_id = start_run(client, 10)
    assert wait_run(client, run_id, finished)["state"] == "done"
    r = client.post(f"/runs/{run_id}/calibrations", json={})
    assert r.status_code == 202, r.text
    cal = wait_calibration(client, r.json()["id"], timeout=240.0)
    assert cal["state"] == "done", cal["error"]
    served = cal["result"]

    r = client.get(f"/runs/{run_id}/stationset")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/zip"
    station_dir = tmp_path / "set"
    with zipfile.ZipFile(io.BytesIO(r.content)) as archive:
        archive.extractall(station_dir)
    doc = json.loads((station_dir / "stations.json").read_text())
    stored = client.get(f"/runs/{run_id}/stations").json()
    assert doc["format"] == "cellcal/stations@1"
    assert [s["id"] for s in doc["stations"]] == [f"{s['index']:03d}" for s in stored]
    assert [s["tcp_pose"] for s in doc["stations"]] == [s["tcp_pose"] for s in stored]
    assert [s["freshness"] for s in doc["stations"]] == [s["freshness"] for s in stored]
    assert all(s["freshness"].startswith("mock: rendered at the grab") for s in stored)
    for s, st in zip(doc["stations"], stored, strict=True):  # the stored PNGs, byte for byte
        image = client.get(f"/runs/{run_id}/stations/{st['index']}/image").content
        assert (station_dir / s["image"]).read_bytes() == image

    out = tmp_path / "cli.json"
    assert main(["calibrate", str(station_dir), "--out", str(out)]) in (0, 3)
    cli = json.loads(out.read_text())
    assert [s["id"] for s in cli["stations"]] == [s["id"] for s in served["stations"]]
    assert (cli["method"], cli["setup"], cli["options"]) == (
        served["method"], served["setup"], served["options"])
    assert_same_calibration(served, cli)
    assert cli["quality"]["verdict"] == served["quality"]["verdict"]

    # The service's report and `cellcal report --stations` on the download name the same input.
    page = get_report(client, cal["id"]).text
    stations = load_station_set(station_dir)
    local = station_set_identity(station_dir, stations,
                                 station_images(station_dir, stations)).input_sha256
    assert re.findall(r"\b[0-9a-f]{64}\b", page) == [local]


def test_station_set_keeps_how_freshness_was_ensured(tmp_path: Path) -> None:
    image = np.zeros((8, 8), np.uint8)
    fresh = "stream: 3 frames skipped, then two consecutive frames agree"
    stations = Stations(setup="eye_in_hand", target=CheckerboardTarget(
        inner_corners=(9, 6), square_size_m=0.03), stations=(
        Station("000", T_base_tcp=np.array([0.3, 0, 0.4, 0, 3.1, 0]), image=image,
                freshness=fresh),
        Station("001", T_base_tcp=np.array([0.3, 0, 0.5, 0, 3.1, 0]), image=image)))
    write_station_set(tmp_path, stations)
    read = load_station_set(tmp_path).model().stations
    assert [s.freshness for s in read] == [fresh, None]


@pytest.mark.timeout(60)
def test_station_set_of_a_run_being_captured_unknown_or_empty(tmp_path: Path) -> None:
    gate = threading.Event()
    with service(tmp_path, gated_opener(tmp_path, 1, gate)) as c:
        run_id = start_run(c, 3)  # held at its second grab until the gate opens
        wait_run(c, run_id, lambda run: run["stations_captured"] == 1)
        r = c.get(f"/runs/{run_id}/stationset")
        assert (r.status_code, r.json()["code"]) == (409, "invalid_state")
        gate.set()
        assert wait_run(c, run_id, finished)["state"] == "done"
        r = c.get("/runs/nope/stationset")
        assert (r.status_code, r.json()["code"]) == (404, "not_found")
        r = c.post("/runs", json={"mode": "external"})
        assert r.status_code == 201, r.text
        empty = r.json()["id"]
        c.post(f"/runs/{empty}/finish")
        r = c.get(f"/runs/{empty}/stationset")
        assert (r.status_code, r.json()["code"]) == (404, "not_found")
        assert "no captured station" in r.json()["detail"]
