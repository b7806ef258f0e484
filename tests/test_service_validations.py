"""Dot-hit validations (``POST /calibrations/{id}/validations``) on the mock cell.

One real capture and calibration is made per module; each test then opens its own app on
that database (fresh mock devices, the robot at the scene's start pose, where the camera sees
the board) with the settings it needs.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation
from sqlalchemy import select

from calib import make_transform
from drivers.base import Camera, Robot
from mocks.scene import default_scene
from service.app import create_app
from service.cell.devices import settings_opener
from service.store.records import CalibrationRecord, RunRecord, ValidationRecord
from tests.support.results import full_result
from tests.support.service import (
    AUTH,
    CELL,
    Event,
    GatedCamera,
    finished,
    poses,
    read_events,
    settings,
    wait_calibration,
    wait_doc,
    wait_run,
)

pytestmark = pytest.mark.usefixtures("module_database")

SCENE = default_scene()
POINTS = ["corner_0_0", "corner_10_0", "corner_0_7", "corner_10_7", "centre"]

Client = Callable[..., TestClient]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory,
               module_database: str | None) -> tuple[Path, str, str]:
    """(data dir, run id, calibration id) of a planned 8-station run, calibrated, in the
    module's database (asked for here, so each database gets its own: a module fixture that
    did not ask was made once, on SQLite, and the PostgreSQL variants found no calibration)."""
    data = tmp_path_factory.mktemp("validations")
    with TestClient(create_app(settings(data))) as c:
        c.headers.update(AUTH)
        r = c.post("/runs", json={"stations": 8})
        assert r.status_code == 201, r.text
        run_id = r.json()["id"]
        assert wait_run(c, run_id, finished)["state"] == "done"
        # default options: 'auto' must see the mock board's 0.5 % oversize on 8 stations
        cal_id = c.post(f"/runs/{run_id}/calibrations", json={}).json()["id"]
        cal = wait_calibration(c, cal_id, timeout=180)
        assert cal["state"] == "done", cal["error"]
    return data, run_id, cal_id


@pytest.fixture
def app_on(calibrated: tuple[Path, str, str]) -> Iterator[Client]:
    """Open an app on the calibrated database: ``app_on(**settings)``; all are closed."""
    clients: list[TestClient] = []

    def make(open_devices: Callable[[], tuple[Robot, Camera]] | None = None,
             **overrides: Any) -> TestClient:
        c = TestClient(create_app(settings(calibrated[0], **overrides),
                                  open_devices=open_devices))
        c.__enter__()
        clients.append(c)
        c.headers.update(AUTH)
        return c

    yield make
    for c in reversed(clients):
        c.__exit__(None, None, None)


def validate(client: TestClient, cal_id: str, body: dict[str, Any] | None = None
             ) -> dict[str, Any]:
    r = client.post(f"/calibrations/{cal_id}/validations", json=body or {})
    assert r.status_code == 202, r.text
    return wait_doc(client, f"/validations/{r.json()['id']}")


def true_pose(client: TestClient) -> np.ndarray:
    return client.app.state.devices.get()[0].true_pose


@pytest.mark.timeout(300)  # includes the module fixture's capture and solve
def test_dot_hit_touches_the_true_points_within_a_millimetre(
        app_on: Client, calibrated: tuple[Path, str, str]) -> None:
    client = app_on()
    cal_id = calibrated[2]
    start = true_pose(client)
    val = validate(client, cal_id)
    assert (val["state"], val["kind"], val["error"]) == ("done", "dot_hit", None)
    report = val["result"]
    assert [p["id"] for p in report["points"]] == POINTS
    assert report["probe"] == [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]
    assert report["ground_truth"] == "mock scene"
    assert report["observation"]["rms_px"] < 0.5
    errors = np.array([p["error_m"] for p in report["points"]])
    assert errors.max() < 1e-3, errors
    assert report["error_m"] == pytest.approx({"mean": errors.mean(), "max": errors.max()})
    Y = SCENE.target_pose_matrix
    truth = dict(zip(POINTS[:4], SCENE.true_board_points()[[0, 10, 77, 87]] @ Y[:3, :3].T
                     + Y[:3, 3], strict=True))
    for p in report["points"][:4]:  # commanded and reached near the true corner
        assert np.linalg.norm(np.subtract(p["commanded"], truth[p["id"]])) < 1e-3
        assert np.linalg.norm(np.subtract(p["reached"], truth[p["id"]])) < 1.5e-3
    assert np.allclose(true_pose(client)[:3, 3], start[:3, 3], atol=2e-3)  # back at the start
    listed = client.get(f"/calibrations/{cal_id}/validations").json()
    assert val["id"] in [v["id"] for v in listed]


@pytest.mark.timeout(30)
def test_chosen_points_with_another_probe(app_on: Client,
                                          calibrated: tuple[Path, str, str]) -> None:
    probe = [0.01, 0.0, 0.15, 0.0, 0.0, 0.5]
    val = validate(app_on(), calibrated[2], {"probe": probe, "points": ["centre", "corner_0_0"]})
    assert val["state"] == "done", val["error"]
    assert [p["id"] for p in val["result"]["points"]] == ["centre", "corner_0_0"]
    assert np.allclose(val["result"]["probe"], probe)
    assert val["result"]["error_m"]["max"] < 1e-3


@pytest.mark.timeout(30)
def test_outside_the_workspace_is_refused_before_moving(
        app_on: Client, calibrated: tuple[Path, str, str]) -> None:
    client = app_on(workspace_min=(-1.5, -1.5, 0.15))  # the TCP cannot go below 15 cm
    start = true_pose(client)
    val = validate(client, calibrated[2])
    assert val["state"] == "failed" and val["result"] is None
    assert "outside the workspace limits" in val["error"]
    assert val["error_code"] == "outside_workspace"
    assert val["error"].endswith("the robot was not moved.")
    np.testing.assert_array_equal(true_pose(client), start)


@pytest.mark.timeout(30)
def test_board_out_of_view_fails_the_validation(app_on: Client,
                                                calibrated: tuple[Path, str, str]) -> None:
    client = app_on()
    client.app.state.devices.get()[1].grab = lambda **_: np.full((1024, 1280), 128, np.uint8)
    val = validate(client, calibrated[2])
    assert val["state"] == "failed"
    assert val["error"].startswith("The board is not in view at the robot's current pose")
    assert val["error_code"] == "board_not_visible"


@pytest.mark.timeout(30)
def test_the_robot_does_one_motion_job_at_a_time(app_on: Client,
                                                 calibrated: tuple[Path, str, str]) -> None:
    gate = threading.Event()
    mocks = settings_opener(settings(calibrated[0]))

    def hanging() -> tuple[Robot, Camera]:
        robot, camera = mocks()
        return robot, GatedCamera(camera, 0, gate)  # type: ignore[return-value]

    client = app_on(open_devices=hanging)
    cal_id = calibrated[2]
    interrupted = RunRecord(cell=CELL, robot="mock://", state="interrupted", setup="eye_in_hand",
                            target={"inner_corners": [11, 8], "square_size_m": 0.03},
                            poses=poses(2))
    with client.app.state.db.session() as s:
        s.add(interrupted)
        s.commit()
    r = client.post(f"/calibrations/{cal_id}/validations", json={})
    assert r.status_code == 202
    val_id = r.json()["id"]
    holder = client.app.state.runtime.instance.describe()
    for path, body in [(f"/calibrations/{cal_id}/validations", {}), ("/runs", {"stations": 5}),
                       ("/runs", {"poses": poses(2)}), (f"/runs/{interrupted.id}/resume", None)]:
        r = client.post(path, json=body)
        assert r.status_code == 409, (path, r.text)
        assert r.json() == {"detail": f"The robot mock:// of cell {CELL} is running validation "
                                      f"{val_id}, held by {holder}; let it finish first.",
                            "code": "robot_busy"}
    gate.set()
    assert wait_doc(client, f"/validations/{val_id}")["state"] == "done"
    assert client.get(f"/runs/{interrupted.id}").json()["state"] == "interrupted"
    client.post(f"/runs/{interrupted.id}/cancel")


@pytest.mark.timeout(240)
def test_two_services_never_move_one_robot_at_once(app_on: Client,
                                                   calibrated: tuple[Path, str, str]) -> None:
    """Two services of one cell and robot start a dot-hit validation at the same moment, 20
    times: the database's motion claim lets one move at a time (the other gets 409)."""
    services = [app_on(), app_on()]
    start = threading.Barrier(2)

    def validate_now(client: TestClient) -> Any:
        start.wait()
        return client.post(f"/calibrations/{calibrated[2]}/validations",
                           json={"points": ["centre"]})

    accepted: list[str] = []
    refused = 0
    for _ in range(20):
        with ThreadPoolExecutor(2) as pool:
            answers = list(pool.map(validate_now, services))
        codes = sorted(r.status_code for r in answers)
        assert codes in ([202, 409], [202, 202]), [r.text for r in answers]
        for r in answers:
            if r.status_code == 202:
                accepted.append(r.json()["id"])
                assert wait_doc(services[0], f"/validations/{r.json()['id']}")["state"] == "done"
            else:
                assert r.json()["code"] == "robot_busy"
                refused += 1
    assert refused > 0  # the tries did meet (else they prove nothing)
    with services[0].app.state.db.session() as s:
        spans = sorted((v.created_at, v.finished_at) for v in s.scalars(
            select(ValidationRecord).where(ValidationRecord.id.in_(accepted))))
    assert len(spans) == len(accepted) >= 20
    assert all(end <= next_start for (_, end), (next_start, _) in pairwise(spans))


@pytest.mark.timeout(30)
def test_an_active_run_holds_the_robot(app_on: Client,
                                       calibrated: tuple[Path, str, str]) -> None:
    client = app_on()
    run_id = client.post("/runs", json={"stations": 5}).json()["id"]
    client.post(f"/runs/{run_id}/pause")
    r = client.post(f"/calibrations/{calibrated[2]}/validations", json={})
    assert r.status_code == 409
    assert r.json()["code"] == "robot_busy" and run_id in r.json()["detail"]
    client.post(f"/runs/{run_id}/cancel")


@pytest.mark.timeout(20)
@pytest.mark.parametrize("method, path", [
    ("POST", "/calibrations/nope/validations"), ("GET", "/calibrations/nope/validations"),
    ("GET", "/validations/nope")])
def test_unknown_ids_are_404(app_on: Client, method: str, path: str) -> None:
    r = app_on().request(method, path, json={})
    assert r.status_code == 404
    assert r.json()["code"] == "not_found"


@pytest.mark.timeout(20)
@pytest.mark.parametrize("state", ["running", "failed"])
def test_unfinished_calibration_is_409(app_on: Client, calibrated: tuple[Path, str, str],
                                       state: str) -> None:
    client = app_on()
    cal_id = add_calibration(client, calibrated[1], state=state)
    r = client.post(f"/calibrations/{cal_id}/validations", json={})
    assert r.status_code == 409
    assert r.json()["code"] == "invalid_state"


@pytest.mark.timeout(20)
@pytest.mark.parametrize("body, code, match", [
    ({"points": ["corner_3_3"]}, "unknown_point", "unknown id 'corner_3_3'; choose from "
                                                  "corner_0_0, corner_10_0"),
    ({"points": []}, "invalid_request", "body.points"),
    ({"probe": [0.0, 0.0, 1.5, 0.0, 0.0, 0.0]}, "invalid_probe", "1.5 m from the TCP"),
    ({"probe": [0.0, 0.0, 100.0, 0.0, 0.0, 0.0]}, "invalid_probe", "millimetres"),
    ({"probe": [0.0, 0.0, 0.1]}, "invalid_request", "body.probe"),
    ({"speed": 1}, "invalid_request", "speed"),
])
def test_bad_request_is_422(app_on: Client, calibrated: tuple[Path, str, str],
                            body: dict[str, Any], code: str, match: str) -> None:
    r = app_on().post(f"/calibrations/{calibrated[2]}/validations", json=body)
    assert r.status_code == 422
    assert r.json()["code"] == code
    assert match in r.json()["detail"]


@pytest.mark.timeout(20)
def test_eye_to_hand_is_422(app_on: Client, calibrated: tuple[Path, str, str]) -> None:
    client = app_on()
    cal_id = add_calibration(client, calibrated[1], result=full_result("eye_to_hand"))
    r = client.post(f"/calibrations/{cal_id}/validations", json={})
    assert r.status_code == 422
    assert r.json()["code"] == "unsupported_setup"


@pytest.mark.timeout(20)
def test_a_validation_cut_by_a_restart_is_failed(app_on: Client,
                                                 calibrated: tuple[Path, str, str]) -> None:
    client = app_on()
    with client.app.state.db.session() as s:  # a validation of a service that died
        val = ValidationRecord(cell=CELL, robot="mock://", calibration_id=calibrated[2],
                               kind="dot_hit", state="running")
        s.add(val)
        s.commit()
    after = app_on().get(f"/validations/{val.id}").json()
    assert after["state"] == "failed"
    assert "stopped during the validation" in after["error"]
    assert after["error_code"] == "interrupted"


def add_calibration(client: TestClient, run_id: str, state: str = "done",
                    result: dict[str, Any] | None = None) -> str:
    with client.app.state.db.session() as s:
        cal = CalibrationRecord(cell=CELL, run_id=run_id, state=state, options={}, result=result)
        s.add(cal)
        s.commit()
    return cal.id


# ---- re-checks (POST /calibrations/{id}/checks) ----------------------------------------------

def recheck(client: TestClient, cal_id: str, body: dict[str, Any] | None = None
            ) -> tuple[dict[str, Any], list[Event]]:
    """The check's report and its events, read from its stream until the stream ends."""
    r = client.post(f"/calibrations/{cal_id}/checks", json=body or {})
    assert r.status_code == 202, r.text
    val_id = r.json()["id"]
    events = read_events(client, val_id, last_event_id="0", path="/validations/{}/events")
    check = client.get(f"/validations/{val_id}").json()
    assert (check["kind"], check["state"]) == ("check", "done"), check
    assert events[-1][1:] == ("state", {"type": "state", "validation_id": val_id,
                                        "state": "done", "error": None,
                                        "error_code": None})
    return check["result"], events


@pytest.mark.timeout(240)
def test_recheck_of_an_unchanged_cell_is_ok(app_on: Client,
                                            calibrated: tuple[Path, str, str]) -> None:
    report, events = recheck(app_on(), calibrated[2])
    assert report["state"] == "ok", report
    assert [s["station"] for s in report["stations"]] == [0, 2, 4, 5, 7]  # spread over 8
    progress = [data for _, kind, data in events if kind == "progress"]
    assert [(p["step"], p["of"], p["station"], p["state"]) for p in progress] == [
        (k, 5, s["station"], s["state"]) for k, s in enumerate(report["stations"], 1)]
    assert progress[1]["message"] == "station 2 of 5 checked: ok"
    assert all(s["state"] == "ok" for s in report["stations"]), report["stations"]
    assert report["offset"]["rot_deg"] < report["limits"]["rot_deg"]
    assert report["offset"]["trans_mm"] < report["limits"]["trans_mm"]


@pytest.mark.timeout(240)
def test_recheck_flags_a_camera_mount_moved_by_2_mm_and_0_2_degrees(
        app_on: Client, calibrated: tuple[Path, str, str]) -> None:
    client = app_on()
    rotation = Rotation.from_rotvec(np.deg2rad(0.2) * np.array([0.6, -0.8, 0.0])).as_matrix()
    shift = make_transform(rotation, 2e-3 * np.array([0.0, 0.6, 0.8]))
    client.app.state.devices.get()[1].shift_mount(shift)
    report, _ = recheck(client, calibrated[2], {"stations": 4})
    assert report["state"] == "degraded", report
    assert len(report["stations"]) == 4
    # the mean offset is the shift itself, within the noise of four stations
    assert report["offset"]["rot_deg"] == pytest.approx(0.2, abs=0.05)
    assert report["offset"]["trans_mm"] == pytest.approx(2.0, abs=0.5)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(("body", "status", "code"), [
    ({"stations": 2, "poses": [[0.5, 0, 0.5, 3.1, 0, 0]]}, 422, "invalid_request"),
    ({"stations": 9}, 422, "too_few_stations"),
    ({"poses": [[0.5, 0.0, -0.5, 3.1, 0.0, 0.0]]}, 422, "outside_workspace"),
    ({"poses": [[0.5, 0.0, 0.5, 180.0, 0.0, 0.0]]}, 422, "invalid_pose"),
])
def test_recheck_requests_are_checked_before_the_robot_moves(
        app_on: Client, calibrated: tuple[Path, str, str], body: dict[str, Any], status: int,
        code: str) -> None:
    client = app_on()
    robot = client.app.state.devices.get()[0]
    before = robot.true_pose.copy()
    r = client.post(f"/calibrations/{calibrated[2]}/checks", json=body)
    assert (r.status_code, r.json()["code"]) == (status, code), r.text
    assert np.array_equal(robot.true_pose, before)
    assert client.post("/calibrations/nope/checks", json={}).status_code == 404
