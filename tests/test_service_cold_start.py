"""Cold-start runs through the service against the blind mock (issue 17): a 20-station run
with no guess, the same with a wrong guess configured, a tolerance run, and never a move
outside the box."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from calib import COVERAGE_90, SolverOptions, pose_error, ur_pose_from_matrix
from mocks.blindcells import random_blind_scene
from service.app import create_app
from service.settings import Settings
from tests.support.service import finished, wait_calibration, wait_run

pytestmark = pytest.mark.usefixtures("database")

KEY = "cold-start-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}


def _settings(tmp_path, scene, **extra) -> Settings:
    path = tmp_path / "scene.json"
    path.write_text(scene.model_dump_json())
    return Settings(data_dir=tmp_path / "data", api_key=KEY, scene=path,
                    workspace_min=scene.workspace.lo, workspace_max=scene.workspace.hi, **extra)


def _finished(client: TestClient, run_id: str) -> dict:
    return wait_run(client, run_id, finished, 900)


def _calibrated_error(client: TestClient, run_id: str, scene) -> tuple[float, float, dict]:
    cal_id = client.post(f"/runs/{run_id}/calibrations", json={}).json()["id"]
    cal = wait_calibration(client, cal_id, 600)
    assert cal["state"] == "done", cal
    result = cal["result"]
    X = np.array(result["hand_eye"]["matrix"])
    rot, trans = pose_error(X, scene.hand_eye_matrix)
    return float(np.degrees(rot)), float(trans * 1e3), result


def _run(tmp_path, scene, body, **settings):
    with TestClient(create_app(_settings(tmp_path, scene, **settings))) as client:
        client.headers.update(AUTH)
        created = client.post("/runs", json=body)
        assert created.status_code == 201, created.text
        run = _finished(client, created.json()["id"])
        robot = client.app.state.devices.get()[0]
        assert robot.refused_moves == 0  # no commanded pose left the box
        errors = _calibrated_error(client, run["id"], scene) if run["state"] == "done" else None
        return run, errors


@pytest.mark.slow
def test_twenty_stations_from_a_cold_start_land_within_a_millimetre(tmp_path):
    scene = random_blind_scene(2, "eye_in_hand")
    run, (rot_deg, trans_mm, _) = _run(tmp_path, scene, {"stations": 20})
    assert run["state"] == "done" and run["stations_captured"] == 20
    assert run["cold_start"]["stop_reason"] == "max_stations"
    assert run["cold_start"]["exploratory_moves"] <= 8
    assert rot_deg <= 0.1 and trans_mm <= 1.0


@pytest.mark.slow
def test_a_wrong_guess_is_logged_and_ignored(tmp_path):
    scene = random_blind_scene(2, "eye_in_hand")
    flipped = scene.hand_eye_matrix.copy()
    flipped[:3, :3] = flipped[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # rotated 180°
    run, (rot_deg, trans_mm, _) = _run(
        tmp_path, scene, {"stations": 20},
        hand_eye_guess=tuple(ur_pose_from_matrix(flipped)),
        focal_px_guess=2.0 * scene.camera.k_matrix[0, 0])
    assert run["state"] == "done"
    assert any("guess" in note and "ignored" in note for note in run["cold_start"]["notes"])
    assert rot_deg <= 0.1 and trans_mm <= 1.0


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_a_tolerance_run_stops_when_the_90_percent_bound_meets_it(tmp_path):
    scene = random_blind_scene(3, "eye_to_hand")
    body = {"tolerance_mm": 1.0, "tolerance_deg": 0.1, "max_stations": 30}
    run, (rot_deg, trans_mm, result) = _run(tmp_path, scene, body)
    cold = run["cold_start"]
    assert run["state"] == "done" and cold["stop_reason"] == "tolerance_met", run
    rule = cold["stop_rule"]
    assert {k: rule[k] for k in ("tolerance_mm", "tolerance_deg", "max_stations")} == {
        "tolerance_mm": 1.0, "tolerance_deg": 0.1, "max_stations": 30}
    assert rule["coverage_factor"] == COVERAGE_90 and "90 % bound" in rule["rule"]
    assert run["stations_planned"] == 30 and run["stations_captured"] < 30
    last = cold["sigma_history"][-1]
    assert last["kind"] == "honest" and last["stations"] == run["stations_captured"]
    assert last["bound_rot_deg"] <= 0.1 and last["bound_trans_mm"] <= 1.0
    assert last["bound_trans_mm"] == pytest.approx(COVERAGE_90 * last["trans_mm"])
    # before the stop the bound was not yet within the tolerance
    assert not any(p["kind"] == "honest" and p["bound_rot_deg"] <= 0.1
                   and p["bound_trans_mm"] <= 1.0 for p in cold["sigma_history"][:-1])
    # the last σ of the history is the σ the calibration of the same stations reports
    sigma = result["uncertainty"]
    assert last["rot_deg"] == pytest.approx(
        np.degrees(np.linalg.norm(sigma["hand_eye_rot_rad"])), rel=0.02)
    assert last["trans_mm"] == pytest.approx(
        1e3 * np.linalg.norm(sigma["hand_eye_trans_m"]), rel=0.02)
    assert rot_deg <= 2 * 0.1 and trans_mm <= 2 * 1.0


def test_a_tolerance_needs_both_figures_and_excludes_stations(tmp_path):
    scene = random_blind_scene(3, "eye_to_hand")
    with TestClient(create_app(_settings(tmp_path, scene))) as client:
        client.headers.update(AUTH)
        for body in ({"tolerance_mm": 0.5}, {"tolerance_mm": 0.5, "tolerance_deg": 0.05,
                                              "stations": 10},
                     {"stations": 10, "max_stations": 20}, {"tolerance_mm": -1,
                                                            "tolerance_deg": 0.05}):
            answer = client.post("/runs", json=body)
            assert answer.status_code == 422, (body, answer.text)
            assert answer.json()["code"]


def test_a_short_cold_start_run_explores_then_plans_inside_the_box(tmp_path):
    scene = random_blind_scene(4, "eye_to_hand")
    with TestClient(create_app(_settings(tmp_path, scene))) as client:
        client.headers.update(AUTH)
        run = _finished(client, client.post("/runs", json={"stations": 8}).json()["id"])
        assert client.app.state.devices.get()[0].refused_moves == 0
        events = client.get(f"/runs/{run['id']}/events").text
    assert run["state"] == "done" and run["stations_captured"] == 8, run
    cold = run["cold_start"]
    assert cold["stop_reason"] == "max_stations" and cold["stop_rule"] is None
    assert 2 <= cold["exploratory_moves"] <= 8
    assert run["stations_planned"] == 8
    assert '"stop_reason": "max_stations"' in events


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_an_interrupted_cold_start_run_resumes_where_it_was(tmp_path):
    """A service stopped mid-run (as by SIGTERM) leaves the run interrupted with its stations;
    a new service resumes it: the stored stations are replayed into the planner, so planning
    goes on from them, with no exploration repeated, no station lost or taken twice."""
    scene = random_blind_scene(4, "eye_to_hand")
    settings = _settings(tmp_path, scene)
    with TestClient(create_app(settings)) as client:
        client.headers.update(AUTH)
        run_id = client.post("/runs", json={"stations": 10}).json()["id"]
        wait_run(client, run_id, lambda r: r["stations_captured"]
                 >= r["cold_start"]["exploratory_moves"] + 3, 600)
    with TestClient(create_app(settings)) as client:  # the old service has stopped
        client.headers.update(AUTH)
        before = client.get(f"/runs/{run_id}").json()
        kept = client.get(f"/runs/{run_id}/stations").json()
        assert before["state"] == "interrupted" and 0 < before["stations_captured"] < 10
        assert client.post(f"/runs/{run_id}/resume").status_code == 200
        run = _finished(client, run_id)
        stations = client.get(f"/runs/{run_id}/stations").json()
        assert client.app.state.devices.get()[0].refused_moves == 0
    assert run["state"] == "done" and run["stations_captured"] == 10, run
    assert [s["index"] for s in stations] == list(range(len(stations)))
    assert [s["commanded_tcp_pose"] for s in stations[:len(kept)]] == \
        [s["commanded_tcp_pose"] for s in kept]  # nothing captured before was lost
    explored = before["cold_start"]["exploratory_moves"]
    assert run["cold_start"]["exploratory_moves"] == explored  # no exploration again
    new = np.array([s["commanded_tcp_pose"] for s in stations[len(kept):]])
    old = np.array([s["commanded_tcp_pose"] for s in kept])
    # each new station is a new pose, none a replay of an earlier one (the start included)
    assert len(new) and np.min(np.linalg.norm(new[:, None] - old[None], axis=2)) > 1e-3


def test_a_cold_start_calibration_keeps_the_users_options_and_adds_box_and_tolerance(
        tmp_path):
    """The stop rule's σ and the run's calibrations are solved with the same box
    (``Settings.cold_start_solver``); a user's options are kept; a tolerance run's tolerance
    goes to the verdict in radians and metres."""
    scene = random_blind_scene(3, "eye_to_hand")
    settings = _settings(tmp_path, scene)
    plain = settings.cold_start_solver()
    assert plain.workspace == settings.workspace() and plain.tolerance is None
    mine = settings.cold_start_solver(SolverOptions(method="refine", outlier_sigma=4.0),
                                      {"tolerance_mm": 0.5, "tolerance_deg": 0.05,
                                       "max_stations": 40})
    assert (mine.method, mine.outlier_sigma) == ("refine", 4.0)
    assert mine.workspace == (scene.workspace.lo, scene.workspace.hi)
    assert mine.tolerance == pytest.approx((np.deg2rad(0.05), 5e-4))
