"""A board configured with the wrong size (issue 19 item 2) is told from the first image,
naming the grid that was seen: a pose-list run fails at its first station, a planned run is
refused, a posted image says so; the check never refuses the configured board."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from calib.boards import Checkerboard, detect_checkerboard
from calib.boards.checkerboard import grid_mismatch
from calib.geometry import pose_error
from calib.pipeline import StationInputs
from mocks.scene import default_scene
from tests.support.service import external_run, finished, poses, post, robot_pose, wait_run
from tests.support.stations import BOARD, SIZE, SQUARE, calibrate_set, rendered_stations

SCENE_BOARD = tuple(default_scene().target.inner_corners)
WRONG = {"type": "checkerboard", "inner_corners": [SCENE_BOARD[0] + 1, SCENE_BOARD[1] + 1],
         "square_size_m": 0.03}
SEEN = (f"found an {SCENE_BOARD[0]}x{SCENE_BOARD[1]} grid of inner corners, you configured "
        f"{SCENE_BOARD[0] + 1}x{SCENE_BOARD[1] + 1}")


def test_the_configured_board_either_way_round_is_no_mismatch() -> None:
    image = rendered_stations()[0][0]
    cols, rows = BOARD
    assert grid_mismatch(image, (cols, rows)) is None
    assert grid_mismatch(image, (rows, cols)) is None
    assert grid_mismatch(image, (cols + 2, rows)) == (
        f"found an {cols}x{rows} grid of inner corners, you configured {cols + 2}x{rows}")


def test_swapped_counts_are_the_same_board_and_the_same_calibration() -> None:
    """Why ``[8, 11]`` for an 11x8 board is accepted: a checkerboard turned 90° shows the
    other count first, so no image tells a swap from a turned board (the mock shows its own
    correctly configured board 8 across at its first station). The swap only turns the board
    frame: the intrinsics and the hand-eye come out the same."""
    cols, rows = BOARD
    images, tcp_poses = rendered_stations(8)
    results = []
    for pattern in ((cols, rows), (rows, cols)):
        found = [detect_checkerboard(image, pattern) for image in images]
        assert all(d is not None for d in found)
        results.append(calibrate_set(StationInputs(found, tcp_poses, image_size=SIZE),
                                     Checkerboard(pattern, SQUARE)))
    configured, swapped = results
    rot, trans = pose_error(configured.hand_eye, swapped.hand_eye)
    assert rot < 1e-5 and trans < 1e-6, (rot, trans)
    np.testing.assert_allclose(configured.K, swapped.K, rtol=1e-6)


@pytest.mark.timeout(60)
def test_pose_list_run_fails_at_its_first_station(client: TestClient) -> None:
    r = client.post("/runs", json={"poses": poses(4), "target": WRONG})
    assert r.status_code == 201, r.text
    run = wait_run(client, r.json()["id"], finished)
    assert run["state"] == "failed"
    assert run["error"] == {"code": "board_mismatch", "detail": "Wrong board configuration: "
                            f"{SEEN}; correct the run's target."}
    stations = client.get(f"/runs/{run['id']}/stations").json()
    assert [(s["index"], s["state"], s["error"]["code"]) for s in stations] == \
        [(0, "skipped", "board_mismatch")]  # the stations after it were not visited


@pytest.mark.timeout(60)
def test_planned_run_is_refused(client: TestClient) -> None:
    r = client.post("/runs", json={"stations": 5, "target": WRONG})
    assert r.status_code == 422
    body: dict[str, Any] = r.json()
    assert body["code"] == "board_mismatch" and SEEN in body["detail"]


@pytest.mark.timeout(60)
def test_posted_station_says_what_was_seen(client: TestClient) -> None:
    run_id = external_run(client, target=WRONG)
    station = post(client, run_id, pose=robot_pose(client))
    assert station.status_code == 201, station.text
    assert station.json()["state"] == "skipped"
    assert station.json()["error"]["code"] == "board_mismatch"
    assert SEEN in station.json()["error"]["detail"]
