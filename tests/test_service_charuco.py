"""A ChArUco cell through the whole service (issue 9): ``cellcal serve --mock`` with a ChArUco
scene captures stations that cut the board at the image border, calibrates, gives a verdict,
exports, and its station set reproduces the calibration offline; a planned ChArUco run is
validated by dot-hit and re-check on the in-process app.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from calib import Charuco, CheckerboardTarget, board_from_target, ur_pose_from_matrix
from mocks.scene import StationSpread, charuco_scene, sample_station_poses
from service.app import create_app
from service.cli.main import main
from service.serving.local import ServeOptions, local_service
from tests.support.service import (
    AUTH,
    assert_same_calibration,
    finished,
    settings,
    wait_calibration,
    wait_doc,
    wait_run,
)

SCENE = charuco_scene()
BOARD = board_from_target(SCENE.nominal_target())
KEY = "charuco-key-0123456789abcdef"
#: Stations of the run; every third one cuts the board at the image border.
N_STATIONS, CUT_FRACTION = 12, 1 / 3


def _poses() -> list[list[float]]:
    T = sample_station_poses(SCENE, N_STATIONS, np.random.default_rng(5),
                             StationSpread(cut_fraction=CUT_FRACTION))
    return ur_pose_from_matrix(T).tolist()


def test_the_board_comes_from_the_scene_or_the_target_setting(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    scene_file = tmp_path / "scene.json"
    scene_file.write_text(SCENE.model_dump_json())
    assert settings(tmp_path, scene=scene_file).run_target() == SCENE.nominal_target()
    assert isinstance(BOARD, Charuco) and BOARD.squares == (12, 9)

    charuco = SCENE.nominal_target().model_dump_json()
    monkeypatch.setenv("CELLCAL_TARGET", charuco)  # over the default (checkerboard) scene
    assert settings(tmp_path).run_target() == SCENE.nominal_target()
    monkeypatch.setenv("CELLCAL_TARGET", '{"inner_corners": [9, 6], "square_size_m": 0.025}')
    assert settings(tmp_path).run_target() == CheckerboardTarget(inner_corners=(9, 6),
                                                                  square_size_m=0.025)
    monkeypatch.delenv("CELLCAL_TARGET")
    monkeypatch.setenv("CELLCAL_TARGET_INNER_CORNERS", "[9, 6]")  # the older spelling
    monkeypatch.setenv("CELLCAL_TARGET_SQUARE_SIZE_M", "0.025")
    assert settings(tmp_path).run_target() == CheckerboardTarget(inner_corners=(9, 6),
                                                                  square_size_m=0.025)
    monkeypatch.setenv("CELLCAL_TARGET", charuco)
    with pytest.raises(ValidationError, match="not a mix"):
        settings(tmp_path)
    monkeypatch.delenv("CELLCAL_TARGET_INNER_CORNERS")
    monkeypatch.delenv("CELLCAL_TARGET_SQUARE_SIZE_M")
    monkeypatch.setenv("CELLCAL_TARGET", '{"type": "charuco", "squares": [12, 9]}')
    with pytest.raises(ValidationError, match="square_size_m"):
        settings(tmp_path)


@pytest.mark.timeout(600)
def test_charuco_run_over_http_calibrates_exports_and_reproduces(tmp_path: Path) -> None:
    scene_file = tmp_path / "scene.json"
    scene_file.write_text(SCENE.model_dump_json())
    with (local_service(tmp_path / "data", KEY, ServeOptions(scene=scene_file)) as service,
          httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {KEY}"},
                       timeout=60) as client):
        r = client.post("/runs", json={"poses": _poses()})
        assert r.status_code == 201, r.text
        run_id = r.json()["id"]
        run = wait_run(client, run_id, finished, 180)
        assert run["state"] == "done" and run["stations_captured"] == N_STATIONS, run
        assert run["target"] == SCENE.nominal_target().model_dump(mode="json")

        seen = [client.get(f"/runs/{run_id}/stations/{k}").json()["detection"]
                for k in range(N_STATIONS)]
        n_ids = [len(d["ids"]) for d in seen]
        assert all(len(d["corners"]) == len(d["ids"]) for d in seen)
        cut = [n for n in n_ids if n < len(BOARD.point_ids)]
        assert len(cut) >= N_STATIONS * CUT_FRACTION, n_ids  # partial views, kept by id

        r = client.post(f"/runs/{run_id}/calibrations", json={})
        assert r.status_code == 202, r.text
        cal = wait_calibration(client, r.json()["id"], timeout=480.0)
        assert cal["state"] == "done", cal["error"]
        served = cal["result"]
        assert served["quality"]["verdict"] in ("pass", "warn", "fail")
        assert len(served["stations"]) == N_STATIONS
        assert sorted(len(s["point_ids"]) for s in served["stations"]) == sorted(n_ids)
        assert served["target"]["kappa"] == pytest.approx(SCENE.target.kappa, abs=3e-3)
        np.testing.assert_allclose(np.asarray(served["hand_eye"]["matrix"])[:3, 3],
                                   SCENE.hand_eye_matrix[:3, 3], atol=3e-3)

        r = client.get(f"/calibrations/{cal['id']}/export", params={"format": "opencv-yaml"})
        assert r.status_code == 200, r.text
        assert "camera_matrix" in r.text

        r = client.get(f"/runs/{run_id}/stationset")
        assert r.status_code == 200, r.text
    station_dir = tmp_path / "set"
    with zipfile.ZipFile(io.BytesIO(r.content)) as archive:
        archive.extractall(station_dir)
    doc = json.loads((station_dir / "stations.json").read_text())
    assert doc["target"] == SCENE.nominal_target().model_dump(mode="json")
    out = tmp_path / "cli.json"
    assert main(["calibrate", str(station_dir), "--out", str(out)]) in (0, 3)
    cli = json.loads(out.read_text())
    assert [s["point_ids"] for s in cli["stations"]] == [s["point_ids"]
                                                         for s in served["stations"]]
    assert_same_calibration(served, cli)


@pytest.mark.timeout(600)
def test_planned_charuco_run_is_validated_by_dot_hit_and_recheck(tmp_path: Path) -> None:
    scene_file = tmp_path / "scene.json"
    scene_file.write_text(SCENE.model_dump_json())
    with TestClient(create_app(settings(tmp_path, scene=scene_file))) as c:
        c.headers.update(AUTH)
        r = c.post("/runs", json={"stations": 8})
        assert r.status_code == 201, r.text
        run_id = r.json()["id"]
        assert wait_run(c, run_id, finished, 180)["state"] == "done"
        cal_id = c.post(f"/runs/{run_id}/calibrations", json={}).json()["id"]
        cal = wait_calibration(c, cal_id, timeout=480.0)
        assert cal["state"] == "done", cal["error"]

        r = c.post(f"/calibrations/{cal_id}/checks", json={"stations": 3})
        assert r.status_code == 202, r.text
        check = wait_doc(c, f"/validations/{r.json()['id']}", timeout=180)
        assert check["state"] == "done", check["error"]
        assert check["result"]["state"] == "ok"
        assert all(s["state"] == "ok" for s in check["result"]["stations"])

        # the dot-hit needs a current view: back to where the camera sees the board
        r = c.post(f"/calibrations/{cal_id}/validations", json={})
        assert r.status_code == 202, r.text
        dot = wait_doc(c, f"/validations/{r.json()['id']}", timeout=180)
        assert dot["state"] == "done", dot["error"]
        ids = [p["id"] for p in dot["result"]["points"]]
        assert ids == ["corner_0_0", "corner_10_0", "corner_0_7", "corner_10_7", "centre"]
        assert dot["result"]["error_m"]["max"] < 1e-3
        Y = SCENE.target_pose_matrix  # ChArUco corner id 0 at the target origin, x along cols
        truth = SCENE.true_board_points()[[0, 10, 77, 87]] @ Y[:3, :3].T + Y[:3, 3]
        for p, true_point in zip(dot["result"]["points"][:4], truth, strict=True):
            assert np.linalg.norm(np.subtract(p["commanded"], true_point)) < 1e-3
