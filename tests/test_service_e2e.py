"""End to end over real HTTP: the service in a uvicorn subprocess on 127.0.0.1 with the mock
cell, driven with ``httpx``; a hard kill mid-run, then a restart and a resume.
"""

from __future__ import annotations

import contextlib
import json
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from calib.geometry import ur_pose_from_matrix
from mocks.scene import default_scene, sample_station_poses
from service.serving.local import local_service
from tests.support.service import finished, wait_calibration, wait_run

pytestmark = pytest.mark.usefixtures("database")

REPO = Path(__file__).resolve().parents[1]
KEY = "e2e-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}
Server = Callable[[], tuple[str, Any]]


@pytest.fixture
def start_server(tmp_path: Path) -> Iterator[Server]:
    """Start ``cellcal serve --mock`` on a free port over ``tmp_path``; every one is reaped."""
    with contextlib.ExitStack() as stack:
        def start() -> tuple[str, Any]:
            service = stack.enter_context(local_service(tmp_path / "data", KEY))
            return service.url, service.proc

        yield start


def _poses(n: int) -> list[list[float]]:
    T = sample_station_poses(default_scene(), n, np.random.default_rng(11))
    return ur_pose_from_matrix(T).tolist()


def _events(client: httpx.Client, run_id: str) -> list[tuple[str, dict[str, Any]]]:
    """Read the run's server-sent events until the service ends the stream."""
    events = []
    with client.stream("GET", f"/runs/{run_id}/events") as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        kind = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line.removeprefix("event: ")
            elif line.startswith("data: "):
                events.append((kind, json.loads(line.removeprefix("data: "))))
    return events


@pytest.mark.timeout(240)
def test_capture_watch_and_calibrate_over_http(start_server: Callable[[], Any]) -> None:
    url, _ = start_server()
    with httpx.Client(base_url=url, headers=AUTH, timeout=30) as client:
        assert httpx.get(f"{url}/runs").status_code == 401
        r = client.post("/runs", json={"poses": _poses(8)})
        assert r.status_code == 201
        run_id = r.json()["id"]
        events = _events(client, run_id)
        first, last = events[0][1], events[-1][1]
        stations = [e for kind, e in events if kind == "station"]
        assert events[0][0] == events[-1][0] == "state"
        assert first["stations_captured"] + len(stations) == 8
        assert [e["index"] for e in stations] == list(range(8 - len(stations), 8))
        assert (last["state"], last["stations_captured"]) == ("done", 8)

        r = client.post(f"/runs/{run_id}/calibrations", json={"options": {}})
        assert r.status_code == 202
        cal = wait_calibration(client, r.json()["id"], timeout=180)
        assert cal["state"] == "done", cal["error"]
        assert cal["result"]["target"]["kappa"] == pytest.approx(1.005, abs=3e-3)


@pytest.mark.timeout(240)
def test_service_killed_mid_run_resumes_after_restart(start_server: Callable[[], Any]) -> None:
    url, proc = start_server()
    with httpx.Client(base_url=url, headers=AUTH, timeout=30) as client:
        run_id = client.post("/runs", json={"poses": _poses(10)}).json()["id"]
        wait_run(client, run_id, lambda r: r["stations_captured"] >= 3, 90)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)

    url, _ = start_server()
    with httpx.Client(base_url=url, headers=AUTH, timeout=30) as client:
        run = client.get(f"/runs/{run_id}").json()
        assert run["state"] == "interrupted"
        assert 3 <= run["stations_captured"] < 10
        assert client.post(f"/runs/{run_id}/resume").json()["state"] == "capturing"
        run = wait_run(client, run_id, finished, 90)
        assert (run["state"], run["stations_captured"]) == ("done", 10)
        indices = [s["index"] for s in client.get(f"/runs/{run_id}/stations").json()]
        assert indices == list(range(10))
