"""REST service (``service.app``) through ``TestClient`` with the ``mock://`` devices.

Each test gets its own data directory and SQLite database. Restarts are simulated by a second
app on the same database while the first one's capture thread is held mid-station.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from calib.result import parse_result
from drivers.base import Camera, Robot
from drivers.errors import CameraError, RobotConnectionError
from mocks.scene import default_scene
from service.app import create_app
from service.cell.devices import settings_opener
from service.settings import Settings
from tests.support.helpers import undeclared_fields, wait_for
from tests.support.service import (
    AUTH,
    KEY,
    finished,
    gated_opener,
    poses,
    service,
    settings,
    start_run,
    wait_calibration,
    wait_run,
)

pytestmark = pytest.mark.usefixtures("database")



















def station_indices(client: TestClient, run_id: str) -> list[int]:
    return [s["index"] for s in client.get(f"/runs/{run_id}/stations").json()]






# ---- auth, health, validation, not found -----------------------------------------------------

@pytest.mark.timeout(20)
def test_health_needs_no_key(client: TestClient) -> None:
    r = client.get("/health", headers={"Authorization": ""})
    assert r.status_code == 200
    assert r.json()["status"] == "ok"


@pytest.mark.timeout(20)
@pytest.mark.parametrize("headers, code", [
    ({}, "unauthorized"),
    ({"Authorization": "Bearer wrong-key-0123456789"}, "invalid_api_key"),
    ({"Authorization": f"Basic {KEY}"}, "unauthorized"),
])
@pytest.mark.parametrize("method, path", [
    ("GET", "/runs"), ("POST", "/runs"), ("GET", "/runs/x/stations"),
    ("GET", "/calibrations/x"), ("GET", "/devices"), ("GET", "/runs/x/events")])
def test_calls_without_the_key_get_401(tmp_path: Path, headers: dict[str, str], code: str,
                                       method: str, path: str) -> None:
    with TestClient(create_app(settings(tmp_path))) as c:
        r = c.request(method, path, headers=headers, json={"poses": poses(3)})
    assert r.status_code == 401
    assert r.json()["code"] == code
    assert r.headers["www-authenticate"] == "Bearer"


@pytest.mark.timeout(20)
def test_without_a_configured_key_every_call_is_refused(tmp_path: Path) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path))) as c:
        r = c.get("/runs", headers={"Authorization": "Bearer anything-at-all-here"})
    assert r.status_code == 401
    assert r.json()["code"] == "no_api_key"


def test_settings_refuse_a_public_host_without_key(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not loopback"):
        Settings(data_dir=tmp_path, host="0.0.0.0")
    assert Settings(data_dir=tmp_path, host="0.0.0.0", api_key=KEY).host == "0.0.0.0"


@pytest.mark.parametrize("overrides, match", [
    ({"robot": "ftp://x"}, "unknown robot address"),
    ({"workspace_min": (0, 0, 2)}, "must be below"),
    ({"scene": "/no/such/scene.json"}, "No such file"),
    ({"robot": "ur://10.0.0.2"}, "mock:// camera renders what the mock robot sees"),
    ({"robot": "ur://10.0.0.2", "camera": "v4l2:///dev/video0"}, "needs the checkerboard"),
])
def test_settings_fail_fast(tmp_path: Path, overrides: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        settings(tmp_path, **overrides)


@pytest.mark.timeout(20)
@pytest.mark.parametrize("body, code, match", [
    ({}, "invalid_request", "exactly one of 'stations'"),
    ({"stations": 5, "poses": poses(3)}, "invalid_request", "exactly one of 'stations'"),
    ({"poses": [[0.1, 0.2, 0.3]]}, "invalid_request", r"body\.poses\[0\]"),
    ({"poses": [[0.1, 0.2, 0.3, 0, 0, "x"]]}, "invalid_request", r"body\.poses\[0\]\[5\]"),
    ({"poses": poses(3), "speed": 9}, "invalid_request", "speed"),
    ({"stations": 2}, "invalid_request", r"body\.stations"),
    ({"poses": [*poses(2), [0.4, 0.1, -0.2, 0.0, 3.1, 0.0]]}, "outside_workspace",
     r"poses\[2\].*outside the workspace"),
    ({"poses": [poses(2)[0], [0.4, 0.1, 0.3, 0.0, 177.6, 0.0]]}, "invalid_pose",
     r"poses\[1\] rotation vector has norm 178, more than π rad: .*were degrees given\?"),
])
def test_malformed_or_unsafe_run_is_422(client: TestClient, body: dict[str, Any], code: str,
                                        match: str) -> None:
    r = client.post("/runs", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["code"] == code
    assert re.search(match, r.json()["detail"]), r.json()["detail"]
    assert client.get("/runs").json() == []


@pytest.mark.timeout(20)
def test_body_that_is_not_json_is_422(client: TestClient) -> None:
    r = client.post("/runs", content=b"{poses:", headers={"Content-Type": "application/json"})
    assert r.status_code == 422
    assert r.json()["code"] == "invalid_request"


@pytest.mark.timeout(20)
@pytest.mark.parametrize("method, path", [
    ("GET", "/runs/nope"), ("POST", "/runs/nope/pause"), ("POST", "/runs/nope/resume"),
    ("POST", "/runs/nope/cancel"), ("GET", "/runs/nope/stations"),
    ("GET", "/runs/nope/stations/0"), ("GET", "/runs/nope/stations/0/image"),
    ("GET", "/runs/nope/events"), ("POST", "/runs/nope/calibrations"),
    ("GET", "/calibrations/nope"), ("GET", "/no/such/route")])
def test_unknown_ids_are_404(client: TestClient, method: str, path: str) -> None:
    r = client.request(method, path)
    assert r.status_code == 404
    assert r.json()["code"] == "not_found"


# ---- capture runs ------------------------------------------------------------------------

@pytest.mark.pg_fast
@pytest.mark.timeout(30)
def test_run_captures_every_station(client: TestClient, tmp_path: Path) -> None:
    run_id = start_run(client, 4)
    run = wait_run(client, run_id, finished)
    assert run["state"] == "done"
    assert (run["stations_captured"], run["stations_planned"], run["error"]) == (4, 4, None)
    stations = client.get(f"/runs/{run_id}/stations").json()
    assert [s["index"] for s in stations] == [0, 1, 2, 3]
    assert all(s["detection"]["ok"] and s["detection"]["corners"] is None for s in stations)
    one = client.get(f"/runs/{run_id}/stations/2").json()
    assert len(one["detection"]["corners"]) == 11 * 8
    assert np.allclose(one["tcp_pose"], poses(4)[2], atol=2e-3)
    image = client.get(one["image_url"])
    assert image.headers["content-type"] == "image/png"
    assert image.content.startswith(b"\x89PNG")
    assert len(list((tmp_path / "runs" / run_id).glob("*.png"))) == 4
    assert [r["id"] for r in client.get("/runs").json()] == [run_id]


@pytest.mark.timeout(30)
def test_run_with_planned_stations(client: TestClient) -> None:
    r = client.post("/runs", json={"stations": 5})
    assert r.status_code == 201, r.text
    run = wait_run(client, r.json()["id"], finished)
    assert (run["state"], run["stations_planned"], run["stations_captured"]) == ("done", 5, 5)


@pytest.mark.timeout(20)
def test_planning_without_the_board_in_view_is_422(client: TestClient) -> None:
    camera = client.app.state.devices.get()[1]
    camera.grab = lambda **_: np.full((1024, 1280), 128, np.uint8)  # lens cap on
    r = client.post("/runs", json={"stations": 5})
    assert r.status_code == 422
    assert r.json()["code"] == "planning_failed"
    assert "not in view" in r.json()["detail"]


@pytest.mark.pg_fast
@pytest.mark.timeout(30)
def test_second_run_on_the_robot_is_409(client: TestClient) -> None:
    first = start_run(client, 6)
    r = client.post("/runs", json={"poses": poses(3)})
    assert r.status_code == 409
    assert r.json()["code"] == "robot_busy"
    assert first in r.json()["detail"]
    client.post(f"/runs/{first}/pause")
    assert client.post("/runs", json={"poses": poses(3)}).status_code == 409  # paused holds it
    client.post(f"/runs/{first}/cancel")
    wait_run(client, start_run(client, 3), finished)


@pytest.mark.timeout(120)
def test_pause_then_resume_captures_each_station_once(client: TestClient) -> None:
    run_id = start_run(client, 10)
    wait_run(client, run_id, lambda r: r["stations_captured"] >= 1)
    r = client.post(f"/runs/{run_id}/pause")
    assert r.status_code == 200 and r.json()["state"] == "paused"
    wait_for("the capture thread to end", client.app.state.runtime.motion.idle)
    held = client.get(f"/runs/{run_id}").json()  # the station in progress ended or dropped
    assert held["state"] == "paused" and held["stations_captured"] < 10
    assert client.post(f"/runs/{run_id}/pause").json()["state"] == "paused"  # idempotent
    assert client.post(f"/runs/{run_id}/resume").json()["state"] == "capturing"
    run = wait_run(client, run_id, finished)
    assert (run["state"], run["stations_captured"]) == ("done", 10)
    assert station_indices(client, run_id) == list(range(10))
    assert client.post(f"/runs/{run_id}/resume").status_code == 409
    assert client.post(f"/runs/{run_id}/cancel").status_code == 409


@pytest.mark.timeout(30)
def test_cancel_stops_the_run_for_good(client: TestClient) -> None:
    run_id = start_run(client, 10)
    wait_run(client, run_id, lambda r: r["stations_captured"] >= 1)
    assert client.post(f"/runs/{run_id}/cancel").json()["state"] == "cancelled"
    wait_for("the capture thread to end", client.app.state.runtime.motion.idle)
    run = client.get(f"/runs/{run_id}").json()
    assert run["state"] == "cancelled" and run["stations_captured"] < 10
    assert client.post(f"/runs/{run_id}/cancel").status_code == 200  # idempotent
    r = client.post(f"/runs/{run_id}/resume")
    assert r.status_code == 409 and r.json()["code"] == "invalid_state"


class RefusingRobot:
    """A mock robot whose first ``refusals`` moves are refused (its ``unreachable`` fault:
    code ``motion_failed``, the robot stays put)."""

    def __init__(self, robot: Robot, refusals: int) -> None:
        self.robot, self.refusals = robot, refusals

    def move_linear(self, *args: Any, **kwargs: Any) -> None:
        if self.refusals > 0:
            self.refusals -= 1
            self.robot.inject_fault("unreachable")  # type: ignore[attr-defined]
        self.robot.move_linear(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.robot, name)


@pytest.mark.timeout(30)
def test_failed_station_is_retried_once_then_skipped(tmp_path: Path) -> None:
    mocks = settings_opener(settings(tmp_path))

    def refusing() -> tuple[Robot, Camera]:
        robot, camera = mocks()
        return RefusingRobot(robot, 2), camera  # type: ignore[return-value]

    with TestClient(create_app(settings(tmp_path), open_devices=refusing)) as c:
        c.headers.update(AUTH)
        # Station 0: both tries are refused; the next move goes.
        run = wait_run(c, start_run(c, 4), finished)
        assert (run["state"], run["stations_captured"], run["stations_skipped"]) == \
            ("done", 3, 1)
        assert run["station_errors"][0]["index"] == 0
        assert run["station_errors"][0]["code"] == "motion_failed"
        stations = c.get(f"/runs/{run['id']}/stations").json()
        assert [(s["state"], s["attempts"]) for s in stations] == \
            [("skipped", 2), ("captured", 1), ("captured", 1), ("captured", 1)]


@pytest.mark.timeout(20)
def test_unreachable_robot_fails_the_run(tmp_path: Path) -> None:
    def unreachable() -> tuple[Robot, Camera]:
        raise RobotConnectionError("Cannot reach the robot controller at 10.0.0.2 "
                                   "(connection refused).")

    with service(tmp_path, unreachable) as c:
        run = wait_run(c, start_run(c, 3), finished)
        devices = c.get("/devices").json()
    assert run["state"] == "failed"
    assert run["error"] == {"code": "robot_unreachable",
                            "detail": "Cannot reach the robot controller at 10.0.0.2 "
                                      "(connection refused)."}
    assert run["stations_captured"] == 0
    assert devices["robot"]["connected"] is False
    assert devices["robot"]["error"]["code"] == "robot_unreachable"
    # the camera, opened after the robot, was not tried: the robot's error is not its own
    assert devices["camera"] == {"url": "mock://", "opened": False, "resolution": None,
                                 "error": None}


@pytest.mark.timeout(20)
def test_missing_camera_is_the_camera_error_alone(tmp_path: Path) -> None:
    def no_camera() -> tuple[Robot, Camera]:
        raise CameraError("No camera at /dev/video0.", code="camera_not_found")

    with service(tmp_path, no_camera) as c:
        devices = c.get("/devices").json()
    assert devices["camera"]["error"] == {"code": "camera_not_found",
                                          "detail": "No camera at /dev/video0."}
    assert devices["robot"]["error"] is None and devices["robot"]["connected"] is False


@pytest.mark.timeout(30)
def test_connection_lost_mid_run_fails_it_and_resume_finishes(client: TestClient) -> None:
    robot = client.app.state.devices.get()[0]
    robot.inject_fault("disconnect")
    run_id = start_run(client, 3)
    run = wait_run(client, run_id, finished)
    assert run["state"] == "failed"
    assert run["error"]["code"] == "robot_unreachable"
    assert "Lost the connection" in run["error"]["detail"]
    assert client.post(f"/runs/{run_id}/resume").status_code == 200  # reconnects
    run = wait_run(client, run_id, finished)
    assert (run["state"], run["stations_captured"], run["error"]) == ("done", 3, None)


@pytest.mark.pg_fast
@pytest.mark.timeout(40)
def test_restart_mid_run_then_resume_loses_and_duplicates_nothing(tmp_path: Path) -> None:
    gate = threading.Event()
    with service(tmp_path, gated_opener(tmp_path, 2, gate)) as old:
        run_id = start_run(old, 6)
        wait_run(old, run_id, lambda r: r["stations_captured"] == 2)
        # The old service hangs at station 2 and is taken for dead (no heartbeat); a new one
        # starts on the same database.
        old.app.state.runtime.instance.close()
        with service(tmp_path) as new:
            run = new.get(f"/runs/{run_id}").json()
            assert (run["state"], run["stations_captured"]) == ("interrupted", 2)
            assert run["error"]["code"] == "interrupted"
            # An interrupted run does not hold the robot.
            wait_run(new, start_run(new, 3), finished)
            assert new.post(f"/runs/{run_id}/resume").json()["state"] == "capturing"
            run = wait_run(new, run_id, finished)
            assert (run["state"], run["stations_captured"]) == ("done", 6)
            gate.set()  # the old thread wakes up: its station must not be stored
            wait_for("the old service's capture thread to end",
                     old.app.state.runtime.motion.idle)
            assert station_indices(new, run_id) == list(range(6))
            assert new.get(f"/runs/{run_id}").json()["state"] == "done"
    assert len(list((tmp_path / "runs" / run_id).glob("*.png"))) == 6


@pytest.mark.pg_fast
@pytest.mark.timeout(40)
def test_a_second_service_leaves_a_live_services_run_alone(tmp_path: Path) -> None:
    """Two services of one cell and robot on one database: the second one's start-up touches
    nothing of the first one's, and its run is refused naming the instance that holds the
    robot."""
    gate = threading.Event()
    with service(tmp_path, gated_opener(tmp_path, 2, gate)) as first:
        run_id = start_run(first, 4)
        wait_run(first, run_id, lambda r: r["stations_captured"] == 2)
        with service(tmp_path) as second:
            assert second.get(f"/runs/{run_id}").json()["state"] == "capturing"
            r = second.post("/runs", json={"poses": poses(3)})
            assert r.status_code == 409
            holder = first.app.state.runtime.instance
            assert r.json()["code"] == "robot_busy"
            assert f"{run_id}, held by instance {holder.id} (" in r.json()["detail"]
            gate.set()
            run = wait_run(second, run_id, finished)
        assert (run["state"], run["stations_captured"], run["error"]) == ("done", 4, None)
        assert station_indices(first, run_id) == [0, 1, 2, 3]


# ---- events and calibrations ---------------------------------------------------------------

@pytest.mark.timeout(30)
def test_events_of_a_finished_run_end_with_its_state(client: TestClient) -> None:
    run_id = start_run(client, 3)
    wait_run(client, run_id, finished)
    with client.stream("GET", f"/runs/{run_id}/events") as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        text = r.read().decode()
    # the run's state as of its newest stored event: 3 stations, then the final state
    assert text.startswith("id: 4\nevent: state\ndata: {")
    assert '"state": "done"' in text and '"stations_captured": 3' in text


@pytest.mark.timeout(240)
def test_calibration_of_a_run(client: TestClient) -> None:
    run_id = start_run(client, 8)
    r = client.post(f"/runs/{run_id}/calibrations", json={})
    assert r.status_code == 409  # still capturing
    wait_run(client, run_id, finished)
    r = client.post(f"/runs/{run_id}/calibrations",
                    json={"options": {"method": "joint", "robot_noise_rot_deg": 0.02,
                                      "robot_noise_trans_mm": 0.1}})
    assert r.status_code == 202, r.text
    cal_id = r.json()["id"]
    cal = wait_calibration(client, cal_id, timeout=180)
    assert cal["state"] == "done", cal["error"]
    result = cal["result"]
    assert result["format"] == "cellcal/result@1"
    assert undeclared_fields(parse_result(result)) == []
    scene = default_scene()
    assert result["target"]["kappa"] == pytest.approx(scene.target.kappa, abs=3e-3)
    assert np.allclose(result["hand_eye"]["matrix"], scene.hand_eye, atol=3e-3)
    assert [c["id"] for c in client.get(f"/runs/{run_id}/calibrations").json()] == [cal_id]


@pytest.mark.timeout(30)
@pytest.mark.parametrize("body, code", [
    ({"options": {"method": "magic"}}, "invalid_request"),
    ({"options": {"robot_noise_rot_deg": -1}}, "invalid_request"),
    # Method #2 needs the joint solver: refused on arrival, not by the worker later
    ({"options": {"nu_method": "extrinsics", "method": "sm"}}, "invalid_request"),
    ({"options": {"nu_method": "extrinsics", "estimate_nu": False}}, "invalid_request"),
    ({}, "too_few_stations"),
])
def test_bad_calibration_request_is_422(client: TestClient, body: dict[str, Any],
                                        code: str) -> None:
    run_id = start_run(client, 2)
    wait_run(client, run_id, finished)
    r = client.post(f"/runs/{run_id}/calibrations", json=body)
    assert r.status_code == 422
    assert r.json()["code"] == code
    if "nu_method" in body.get("options", {}):
        assert "Method #2" in r.json()["detail"]
        assert client.get(f"/runs/{run_id}/calibrations").json() == []  # nothing was queued
