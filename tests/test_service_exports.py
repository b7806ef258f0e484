"""``GET /calibrations/{id}/export``: every format as a file, and the refusals.

Calibration rows are written straight into the database (a solve is tested elsewhere), so
each case is fast and its result document known.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.exports import FORMATS, ExportNames, export
from service.store.records import CalibrationRecord, RunRecord
from tests.support.results import full_result, pose_only_result
from tests.support.service import CELL

pytestmark = [pytest.mark.timeout(20), pytest.mark.usefixtures("database")]

MEDIA = {"json": "application/json", "opencv-yaml": "application/yaml",
         "ros-camera-info": "application/yaml", "urdf": "application/xml",
         "ur-pose": "text/plain", "ros2-static-tf": "text/x-python"}



def add_calibration(client: TestClient, state: str = "done",
                    result: dict[str, Any] | None = None) -> str:
    """Store a run and a calibration of it in ``state``; the calibration id."""
    run = RunRecord(cell=CELL, robot="mock://", state="done", setup="eye_in_hand",
                    target={"inner_corners": [11, 8], "square_size_m": 0.03}, poses=[])
    with client.app.state.db.session() as s:
        s.add(run)
        s.flush()
        cal = CalibrationRecord(cell=CELL, run_id=run.id, state=state, options={}, result=result,
                                error="boom" if state == "failed" else None)
        s.add(cal)
        s.commit()
    return cal.id


@pytest.mark.parametrize("fmt", FORMATS)
def test_each_format_is_the_exported_file(client: TestClient, fmt: str) -> None:
    result = full_result()
    cal_id = add_calibration(client, result=result)
    r = client.get(f"/calibrations/{cal_id}/export", params={"format": fmt})
    assert r.status_code == 200, r.text
    content, media, name = export(result, fmt)
    assert r.headers["content-type"].split(";")[0] == media == MEDIA[fmt]
    assert r.headers["content-disposition"] == f'attachment; filename="{name}"'
    assert r.text == content


@pytest.mark.pg_fast
def test_json_is_the_default_and_round_trips(client: TestClient) -> None:
    result = full_result()
    cal_id = add_calibration(client, result=result)
    r = client.get(f"/calibrations/{cal_id}/export")
    assert r.headers["content-disposition"].endswith('filename="calibration.json"')
    assert json.loads(r.text) == result


@pytest.mark.parametrize("fmt", ["json", "urdf", "ur-pose"])
def test_pose_formats_of_a_pose_only_result(client: TestClient, fmt: str) -> None:
    cal_id = add_calibration(client, result=pose_only_result())
    assert client.get(f"/calibrations/{cal_id}/export", params={"format": fmt}).status_code \
        == 200


@pytest.mark.parametrize("fmt", ["opencv-yaml", "ros-camera-info"])
def test_camera_format_of_a_pose_only_result_is_422(client: TestClient, fmt: str) -> None:
    cal_id = add_calibration(client, result=pose_only_result())
    r = client.get(f"/calibrations/{cal_id}/export", params={"format": fmt})
    assert r.status_code == 422
    assert r.json()["code"] == "export_unavailable"
    assert f"format '{fmt}' needs a camera model" in r.json()["detail"]


def test_unknown_format_is_422(client: TestClient) -> None:
    cal_id = add_calibration(client, result=full_result())
    r = client.get(f"/calibrations/{cal_id}/export", params={"format": "csv"})
    assert r.status_code == 422
    assert r.json()["code"] == "invalid_request"
    assert r.json()["detail"].startswith("query.format: Input should be 'json'")


def test_unknown_calibration_is_404(client: TestClient) -> None:
    r = client.get("/calibrations/nope/export", params={"format": "urdf"})
    assert r.status_code == 404
    assert r.json() == {"detail": "No calibration nope.", "code": "not_found"}


@pytest.mark.parametrize("state", ["running", "failed"])
def test_unfinished_calibration_is_409(client: TestClient, state: str) -> None:
    cal_id = add_calibration(client, state=state)
    r = client.get(f"/calibrations/{cal_id}/export", params={"format": "json"})
    assert r.status_code == 409
    assert r.json() == {"detail": f"Calibration {cal_id} is {state}; only a finished "
                                  "calibration can be exported.", "code": "invalid_state"}


def test_export_needs_the_key(client: TestClient) -> None:
    cal_id = add_calibration(client, result=full_result())
    r = client.get(f"/calibrations/{cal_id}/export", headers={"Authorization": ""})
    assert r.status_code == 401


def test_frame_names_reach_the_export(client: TestClient) -> None:
    cal_id = add_calibration(client, result=full_result())
    params = {"format": "ros2-static-tf", "camera_name": "cam2", "parent_frame": "flange",
              "child_frame": "cam2_optical"}
    r = client.get(f"/calibrations/{cal_id}/export", params=params)
    assert r.status_code == 200, r.text
    assert r.text == export(full_result(), "ros2-static-tf",
                            ExportNames("cam2", parent_frame="flange",
                                        child_frame="cam2_optical"))[0]
    assert r.headers["content-disposition"].endswith('filename="cam2_static_tf.launch.py"')


def test_frame_name_that_cannot_be_written_is_422(client: TestClient) -> None:
    cal_id = add_calibration(client, result=full_result())
    r = client.get(f"/calibrations/{cal_id}/export",
                   params={"format": "urdf", "parent_frame": 'a"b'})
    assert r.status_code == 422
    assert r.json() == {"detail": "parent frame 'a\"b': use letters, digits, _ and /, each "
                                  "part not starting with a digit",
                        "code": "export_unavailable"}
