"""A cold-start run on a cell that reveals only what a real one does (issue 17): the UR
controller emulator in its own process, spoken to through the real ``ur-rtde`` client, with a
safety box around the start (the flange and the camera), and an MJPEG network camera that
shows the board from wherever the emulated arm stands. The service knows the board, the setup
and the box, nothing else; the run ends with a stored result, and no commanded move ever
met the box."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from calib import matrix_from_ur_pose, pose_error
from drivers.errors import ProtectiveStopError
from drivers.ur import URRobot
from mocks.blindcells import random_blind_scene
from mocks.render import RenderParams, render_board
from mocks.scene import MockScene, camera_pose_for_tcp
from mocks.ur_emulator.wire import SAFETY_NORMAL
from service.app import create_app
from service.settings import Settings
from tests.mjpeg_server import MJPEGCamera
from tests.support.service import AUTH, KEY, finished, wait_calibration, wait_run
from tests.support.ur_emulator import EmulatorProcess, running_emulator


class ArmCamera:
    """Frames of the board as the camera on the emulated arm sees it: rendered from the
    emulator's pose (asked over its dashboard) whenever that pose changed, else the last."""

    def __init__(self, scene: MockScene, emulator: EmulatorProcess) -> None:
        self.scene, self.emulator = scene, emulator
        self.params = RenderParams.from_scene(scene)
        self.rng = np.random.default_rng(0)
        self.lock = threading.Lock()
        self.pose: list[float] | None = None
        self.image: np.ndarray | None = None

    def __call__(self) -> np.ndarray:
        pose = self.emulator.state()["pose"]
        with self.lock:
            if pose != self.pose or self.image is None:
                C = camera_pose_for_tcp(self.scene, matrix_from_ur_pose(np.array(pose)))
                self.image = render_board(self.params, C, rng=self.rng)
                self.pose = pose
            return self.image


@pytest.fixture
def cell() -> Iterator[tuple[MockScene, EmulatorProcess, MJPEGCamera]]:
    scene = random_blind_scene(0, "eye_in_hand")
    lo, hi = scene.workspace.lo, scene.workspace.hi
    box = ",".join(f"{v:.4f}" for v in (*lo, *hi))
    camera_point = ",".join(f"{v:.4f}" for v in scene.hand_eye_matrix[:3, 3])
    start = ",".join(f"{v:.6f}" for v in scene.start_tcp_pose)
    with running_emulator("--instant", f"--box={box}", f"--tool-point={camera_point}",
                          f"--start-pose={start}") as emulator:
        stream = MJPEGCamera(ArmCamera(scene, emulator), period=0.05)
        try:
            yield scene, emulator, stream
        finally:
            stream.stop()


@pytest.mark.slow
@pytest.mark.usefixtures("database")
@pytest.mark.timeout(600)
def test_cold_start_on_the_ur_emulator_stores_a_result_inside_the_box(cell, tmp_path):
    scene, emulator, stream = cell
    t = scene.target
    settings = Settings(
        data_dir=tmp_path / "data", api_key=KEY, robot=f"ur://{emulator.host}",
        camera=stream.url, setup="eye_in_hand",
        target={"inner_corners": list(t.inner_corners), "square_size_m": t.square_size_m},
        workspace_min=scene.workspace.lo, workspace_max=scene.workspace.hi)
    with TestClient(create_app(settings)) as client:
        client.headers.update(AUTH)
        created = client.post("/runs", json={"stations": 10})
        assert created.status_code == 201, created.text
        run = wait_run(client, created.json()["id"], finished, timeout=500)
        assert run["state"] == "done", (run["error"], run["station_errors"], run["cold_start"])
        assert run["stations_captured"] == 10, run["cold_start"]
        assert 2 <= run["cold_start"]["exploratory_moves"] <= 8
        cal_id = client.post(f"/runs/{run['id']}/calibrations", json={}).json()["id"]
        cal = wait_calibration(client, cal_id, timeout=300)
        stored = client.get("/calibrations", params={"limit": 5}).json()
        stations = client.get(f"/runs/{run['id']}/stations").json()
    state = emulator.state()
    assert state["box_stops"] == [] and state["safety_status_bits"] == SAFETY_NORMAL, state
    lo, hi = np.array(scene.workspace.lo), np.array(scene.workspace.hi)
    for station in stations:  # the stations were taken where they were commanded, in the box
        tcp = np.array(station["commanded_tcp_pose"][:3])
        assert (lo <= tcp).all() and (tcp <= hi).all()
        assert "stream" in station["freshness"] or "still" in station["freshness"], station
    assert cal["state"] == "done", cal
    rot, trans = pose_error(np.array(cal["result"]["hand_eye"]["matrix"]),
                            scene.hand_eye_matrix)
    assert np.degrees(rot) < 0.5 and trans < 0.005  # 10 stations: a sane result, not a fine one
    ids = [c["id"] for c in (stored if isinstance(stored, list) else stored["items"])]
    assert cal_id in ids


def test_the_emulator_refuses_a_move_out_of_its_box_with_a_protective_stop():
    """The box the cold-start test relies on: a move whose flange, or a tool point, would
    leave it is refused before it starts (the arm stays), counted, and is a protective stop
    through the real client; a move inside is done."""
    start = np.array([0.3, -0.3, 0.45, np.pi, 0.0, 0.0])
    box = "0.1,-0.5,0.25,0.5,-0.1,0.65"
    with running_emulator("--instant", f"--box={box}", "--tool-point=0,0,0.15",
                          f"--start-pose={','.join(map(str, start))}") as emulator:
        robot = URRobot(emulator.host, connect_timeout=10.0, settle_dwell=0.05,
                        motion_timeout=10.0)
        robot.connect()
        try:
            np.testing.assert_allclose(robot.tcp_pose()[:3], start[:3], atol=1e-6)
            inside = start + np.array([0.05, 0.0, 0.05, 0.0, 0.0, 0.0])
            robot.move_linear(inside)
            np.testing.assert_allclose(emulator.state()["pose"][:3], inside[:3], atol=1e-6)
            assert emulator.state()["box_stops"] == []
            # the flange stays in, but the tool point 15 cm below it would go under z = 0.25
            with pytest.raises(ProtectiveStopError):
                robot.move_linear(inside - np.array([0.0, 0.0, 0.12, 0.0, 0.0, 0.0]))
            state = emulator.state()
            assert len(state["box_stops"]) == 1 and "tool point 0" in state["box_stops"][0]
            assert state["safety_status_bits"] != SAFETY_NORMAL
            np.testing.assert_allclose(state["pose"][:3], inside[:3], atol=1e-6)
        finally:
            robot.close()
