"""``cellcal robot|camera|devices`` end to end on mock:// devices, through ``service.cli.main``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.boards import detect_checkerboard
from calib.geometry import matrix_from_ur_pose, pose_error
from mocks.scene import default_scene
from service.cli import main as cli
from tests.support.cli import assert_one_line_error

SCENE = default_scene()


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err




@pytest.mark.timeout(30)
def test_robot_pose(capsys) -> None:
    code, out, _ = run(capsys, "robot", "pose", "--robot", "mock://")
    assert code == 0
    pose = np.array(json.loads(out)["tcp_pose"])
    angle, dist = pose_error(matrix_from_ur_pose(pose), SCENE.start_pose())
    assert dist < 1e-3 and angle < np.deg2rad(0.1)


@pytest.mark.timeout(30)
def test_robot_move(capsys) -> None:
    code, out, _ = run(capsys, "robot", "move", "--robot", "mock://",
                       "--pose=0.6,-0.05,0.55,3.1,0.2,0", "--speed", "0.2")
    assert code == 0
    reached = np.array(json.loads(out)["tcp_pose"])
    assert np.linalg.norm(reached[:3] - [0.6, -0.05, 0.55]) < 1e-3


@pytest.mark.timeout(30)
@pytest.mark.parametrize(("argv", "message", "exit_code"), [
    (["--pose", "0.6,0,0.5"], "expected six numbers", 2),
    (["--pose", "600,0,500,3.1,0,0"], "were millimetres given?", 2),
    (["--pose", "0.6,0,0.5,178,11,0"], "--pose rotation vector has norm 178, more than π rad: "
                                      "rotations must be rotation vectors in radians (were "
                                      "degrees given?)", 2),
    (["--pose", "0.6,0,-0.2,3.1,0,0"], "outside the workspace limits", 1),
    (["--pose", "0.6,0,0.5,3.1,0,0", "--speed", "0"], "must be positive", 2),
])
def test_robot_move_errors(capsys, argv: list[str], message: str, exit_code: int) -> None:
    code, out, err = run(capsys, "robot", "move", "--robot", "mock://", *argv)
    assert code == exit_code and out == ""
    assert_one_line_error(err, message)


def test_robot_move_in_degrees_is_refused_before_the_robot_is_touched(
        capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    opened = []
    monkeypatch.setattr("service.cli.devices.open_robot", lambda *a, **k: opened.append(a))
    code, out, err = run(capsys, "robot", "move", "--robot", "mock://",
                         "--pose=0.6,-0.05,0.55,177.6,11.5,0")
    assert (code, out, opened) == (2, "", [])
    assert_one_line_error(err, "were degrees given?")


@pytest.mark.timeout(30)
def test_camera_grab_mock(capsys, tmp_path: Path) -> None:
    out_png = tmp_path / "frame.png"
    code, _, err = run(capsys, "camera", "grab", "--camera", "mock://", "--out", str(out_png))
    assert code == 0 and "1280x1024 grey" in err
    image = cv2.imread(str(out_png), cv2.IMREAD_UNCHANGED)
    assert detect_checkerboard(image, SCENE.target.inner_corners).ok


@pytest.mark.timeout(30)
def test_camera_grab_image_directory(capsys, tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "000.png"), np.full((30, 40), 99, np.uint8))
    code, _, _ = run(capsys, "camera", "grab", "--camera", f"file://{tmp_path}/in",
                     "--out", str(tmp_path / "out.png"))
    assert code == 0
    assert cv2.imread(str(tmp_path / "out.png"), cv2.IMREAD_UNCHANGED).mean() == 99


@pytest.mark.timeout(30)
@pytest.mark.parametrize(("argv", "message"), [
    (["--camera", "v4l2:///dev/video987", "--out", "x.png"], "No camera at /dev/video987"),
    (["--camera", "gige://cam", "--out", "x.png"], "unknown camera address"),
    (["--camera", "mock://", "--out", "x.unknown"], "unknown image format"),
])
def test_camera_grab_errors(capsys, argv: list[str], message: str) -> None:
    code, _, err = run(capsys, "camera", "grab", *argv)
    assert code != 0
    assert_one_line_error(err, message)


@pytest.mark.timeout(30)
def test_scene_file(capsys, tmp_path: Path) -> None:
    scene = SCENE.model_copy(update={"start_tcp_pose": [0.5, 0.1, 0.6, 3.14159, 0.0, 0.0]})
    good = tmp_path / "scene.json"
    good.write_text(scene.model_dump_json())
    code, out, _ = run(capsys, "robot", "pose", "--robot", "mock://", "--scene", str(good))
    assert code == 0
    assert np.linalg.norm(np.array(json.loads(out)["tcp_pose"])[:3] - [0.5, 0.1, 0.6]) < 1e-3
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "cellcal/scene@1"}))
    code, _, err = run(capsys, "robot", "pose", "--robot", "mock://", "--scene", str(bad))
    assert code == 2
    assert_one_line_error(err, "bad.json: camera: Field required")


@pytest.mark.timeout(30)
def test_devices_check_ok(capsys) -> None:
    code, out, _ = run(capsys, "devices", "check", "--robot", "mock://", "--camera", "mock://")
    assert code == 0
    robot_line, camera_line = out.splitlines()
    assert robot_line.split()[:3] == ["robot", "mock://", "ok"] and "mm" in robot_line
    assert camera_line.split()[:3] == ["camera", "mock://", "ok"]
    assert "1280x1024 grey frame" in camera_line


@pytest.mark.timeout(30)
def test_devices_check_reports_each_failure(capsys, tmp_path: Path) -> None:
    code, out, err = run(capsys, "devices", "check", "--robot", "ur://", "--camera",
                         f"file://{tmp_path}/missing.avi")
    assert code == cli.EXIT_FAILED and err == ""
    robot_line, camera_line = out.splitlines()
    assert robot_line.startswith("robot   ur://  FAILED  ") and "ur://HOST" in robot_line
    assert camera_line.startswith("camera") and "FAILED" in camera_line
    assert "no such file or directory" in camera_line
    code, out, _ = run(capsys, "devices", "check", "--robot", "http://x", "--camera", "mock://")
    assert "a mock:// camera needs a working mock:// robot" in out.splitlines()[1]


def test_devices_check_needs_a_device(capsys) -> None:
    code, _, err = run(capsys, "devices", "check")
    assert code == 2
    assert_one_line_error(err, "give --robot URL and/or --camera URL")
