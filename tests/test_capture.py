"""Station capture through the mock devices, the station-set files it writes, and calibrations
from those files (PnP + hand-eye, and `cellcal calibrate`) that recover the scene hand-eye."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.boards import board_points, detect_checkerboard
from calib.geometry import matrix_from_ur_pose, pose_error, ur_pose_from_matrix
from calib.handeye import calibrate_hand_eye
from calib.refine import RefineOptions
from calib.stations import Stations
from drivers.capture import CapturedStation, capture_station
from drivers.errors import CameraFrozenError, RobotError
from drivers.frozen import FrameWatch
from drivers.registry import open_camera, open_robot
from mocks.camera import MockCamera
from mocks.devices import MockRobot
from mocks.scene import default_scene, sample_station_poses
from service.cli import main as cli
from service.stationsets.format import load_station_set, station_record, write_station_set
from tests.support.helpers import assert_pose_close

SCENE = default_scene()
TARGET = {"type": "checkerboard", "inner_corners": list(SCENE.target.inner_corners),
          "square_size_m": SCENE.target.square_size_m}


@pytest.fixture
def rig() -> tuple[MockRobot, MockCamera]:
    robot = open_robot("mock://", config=SCENE)
    camera = open_camera("mock://", robot=robot)
    assert isinstance(robot, MockRobot) and isinstance(camera, MockCamera)
    return robot, camera


def station_targets(n: int, seed: int) -> np.ndarray:
    return ur_pose_from_matrix(sample_station_poses(SCENE, n, np.random.default_rng(seed)))


@pytest.mark.timeout(30)
def test_capture_station_pairs_a_fresh_frame_with_the_settled_pose(rig) -> None:
    robot, camera = rig
    target = station_targets(1, 0)[0]
    st = capture_station(robot, camera, target)
    assert st.image.shape == (1024, 1280)
    assert np.array_equal(st.tcp_pose, robot.tcp_pose())
    np.testing.assert_array_equal(st.target_tcp_pose, target)
    angle, dist = pose_error(matrix_from_ur_pose(st.tcp_pose), matrix_from_ur_pose(target))
    assert dist < 1e-3 and angle < np.deg2rad(0.1)  # the scene's reading noise, no more
    assert st.moved_at <= st.settled_at <= st.grabbed_at <= st.pose_read_at
    assert detect_checkerboard(st.image, SCENE.target.inner_corners).ok


class BumpedCamera:
    """A camera whose grab coincides with the robot being pushed 1 mm."""

    def __init__(self, camera: MockCamera, robot: MockRobot) -> None:
        self.camera, self.robot = camera, robot

    def grab(self, *, timeout: float = 2.0) -> np.ndarray:
        pose = self.robot.tcp_pose()
        pose[0] += 1e-3
        self.robot.move_linear(pose)
        return self.camera.grab(timeout=timeout)


@pytest.mark.timeout(30)
def test_capture_refuses_a_robot_that_moved_during_the_grab(rig) -> None:
    robot, camera = rig
    with pytest.raises(RobotError, match=r"robot moved by [\d.]+ mm") as err:
        capture_station(robot, BumpedCamera(camera, robot), station_targets(1, 1)[0])
    assert err.value.code == "moved_during_grab"


class MisreadRobot:
    """The mock robot whose pose readings come out wrong (a driver or controller fault)."""

    def __init__(self, robot: MockRobot, misread) -> None:
        self.robot, self.misread = robot, misread

    def tcp_pose(self) -> np.ndarray:
        return self.misread(self.robot.tcp_pose())

    def __getattr__(self, name: str):
        return getattr(self.robot, name)


@pytest.mark.timeout(30)
@pytest.mark.parametrize(("misread", "why"), [
    (lambda p: np.r_[np.nan, p[1:]], "NaN"),
    (lambda p: np.r_[p[:3] * 1000.0, p[3:]], "millimetres"),
    (lambda p: np.r_[p[:3], np.rad2deg(p[3:])], "degrees")])
def test_capture_refuses_a_robot_reading_that_is_no_pose(rig, misread, why) -> None:
    """Issue 22, a variant of its pose checks: a reading of NaN, millimetres or degrees was
    stored with the image (NaN made every later listing of the run's stations a 500)."""
    robot, camera = rig
    with pytest.raises(RobotError, match=why) as err:
        capture_station(MisreadRobot(robot, misread), camera, station_targets(1, 2)[0])
    assert err.value.code == "invalid_reading"


@pytest.mark.timeout(30)
def test_a_camera_that_repeats_one_frame_is_refused_once_the_robot_moved(rig) -> None:
    """A frozen camera (the mock's ``freeze``: its last frame again at every grab) passed
    every check: each station paired a new pose with the old image. The capture's watch
    refuses the repeat once the robot moved, not at a retry from the same pose."""
    robot, camera = rig
    targets, watch = station_targets(3, 3), FrameWatch()
    first = capture_station(robot, camera, targets[0], watch=watch)
    camera.inject_fault("freeze")
    again = capture_station(robot, camera, targets[0], watch=watch)  # no motion: no evidence
    assert np.array_equal(again.image, first.image) and watch.identical == 2
    with pytest.raises(CameraFrozenError, match="frozen: 3 identical frames") as err:
        capture_station(robot, camera, targets[1], watch=watch)
    assert err.value.code == "camera_frozen"
    camera.clear_faults()
    capture_station(robot, camera, targets[2], watch=watch)  # live again
    assert watch.identical == 1


def test_blank_or_unmoved_repeats_are_no_frozen_camera() -> None:
    """Identical frames count only with content and motion: a blank frame (a lens cap) is the
    board detection's to report, and a robot that stands gives no evidence."""
    watch = FrameWatch()
    pose = np.array([0.4, 0.0, 0.5, 3.1, 0.0, 0.0])
    still, moved = pose + np.array([0, 0, 0, 0, 0, 1e-4]), pose + np.array([0.05, 0, 0, 0, 0, 0])
    blank = np.zeros((48, 64), np.uint8)
    for p in (pose, moved, pose):
        watch.check(blank, p)
    scene = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    watch.check(scene, pose)
    watch.check(scene.copy(), still)  # below MIN_MOTION
    with pytest.raises(CameraFrozenError, match=r"3 identical frames.*moved 50\.0 mm"):
        watch.check(scene, moved)
    watch.check(scene[:, ::-1], moved)  # a new frame starts afresh
    assert watch.identical == 1


def test_capture_validates_the_target(rig) -> None:
    robot, camera = rig
    with pytest.raises(ValueError, match="shape"):
        capture_station(robot, camera, np.zeros(4))
    with pytest.raises(ValueError, match="millimetres"):
        capture_station(robot, camera, np.array([600.0, 0.0, 600.0, 0.0, 0.0, 0.0]))


def _station(tcp_pose: list[float]) -> CapturedStation:
    return CapturedStation(image=np.zeros((8, 8), np.uint8), tcp_pose=np.array(tcp_pose),
                           target_tcp_pose=np.array(tcp_pose), moved_at=0.0, settled_at=0.0,
                           grabbed_at=0.0, pose_read_at=0.0)


def test_station_record() -> None:
    pose = [0.5, 0.1, 0.4, 3.1, 0.0, 0.0]
    assert station_record(_station(pose).station("007"), "007.png") == {
        "id": "007", "tcp_pose": pose, "image": "007.png"}


def test_write_station_set_refuses_bad_input_and_overwrites(tmp_path: Path) -> None:
    stations = (_station([0.5, 0.1, 0.4, 3.1, 0.0, 0.0]).station("000"),)
    with pytest.raises(ValueError, match="inner_corners"):
        write_station_set(tmp_path / "a", Stations("eye_in_hand", stations,
                                                   target={"square_size_m": 0.03}))
    with pytest.raises(ValueError, match="setup"):
        write_station_set(tmp_path / "a", Stations("eye_on_head", stations, target=TARGET))
    assert not (tmp_path / "a").exists()  # nothing written for an invalid set
    write_station_set(tmp_path / "a", Stations("eye_in_hand", stations, target=TARGET))
    with pytest.raises(FileExistsError, match="already exists"):
        write_station_set(tmp_path / "a", Stations("eye_in_hand", stations, target=TARGET))


def pnp_observations(station_dir: Path, nu: float) -> tuple[np.ndarray, np.ndarray]:
    """(base_T_tcp, cam_T_target), each (n, 4, 4), from a station set's images by PnP.

    Stands in for the image pipeline: corners by ``detect_checkerboard``, poses by
    ``cv2.solvePnP`` with the scene's intrinsics and ν (which the intrinsic bundle adjustment
    estimates) on the *nominal* square size, so κ is left to the hand-eye solve.
    """
    stations = load_station_set(station_dir)
    assert stations.target is not None
    corners = tuple(stations.target.inner_corners)
    obj = board_points(corners, stations.target.square_size_m, nu=nu)
    P, C = [], []
    for s in stations.stations:
        image = cv2.imread(str(station_dir / s.image), cv2.IMREAD_UNCHANGED)
        det = detect_checkerboard(image, corners)
        assert det.ok, f"station {s.id}: {det.reason}"
        ok, rvec, tvec = cv2.solvePnP(obj, det.corners, SCENE.camera.k_matrix,
                                      SCENE.camera.dist_coeffs)
        assert ok
        P.append(s.tcp_pose)
        C.append(np.concatenate([tvec.ravel(), rvec.ravel()]))
    return matrix_from_ur_pose(np.array(P)), matrix_from_ur_pose(np.array(C))


@pytest.fixture(scope="module")
def captured_set(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[CapturedStation]]:
    """Ten stations captured through mock:// devices and written as a station set."""
    robot = open_robot("mock://", config=SCENE)
    camera = open_camera("mock://", robot=robot)
    captured = [capture_station(robot, camera, p) for p in station_targets(10, 5)]
    stations = tuple(c.station(f"{k:03d}") for k, c in enumerate(captured))
    path = write_station_set(tmp_path_factory.mktemp("capture") / "run",
                             Stations(SCENE.setup, stations, target=TARGET))
    return path, captured


@pytest.mark.timeout(60)
def test_captured_station_set_format(captured_set) -> None:
    path, captured = captured_set
    doc = json.loads(path.read_text())
    assert doc["format"] == "cellcal/stations@1" and doc["setup"] == "eye_in_hand"
    assert doc["target"] == TARGET
    assert [s["image"] for s in doc["stations"]] == [f"{k:03d}.png" for k in range(10)]
    for s, st in zip(doc["stations"], captured, strict=True):
        assert s["tcp_pose"] == st.tcp_pose.tolist()
        assert np.array_equal(cv2.imread(str(path.parent / s["image"]), cv2.IMREAD_UNCHANGED),
                              st.image)
    assert len(load_station_set(path.parent).stations) == 10


@pytest.mark.timeout(60)
def test_captured_poses_and_images_recover_the_scene_hand_eye(captured_set) -> None:
    path, _ = captured_set
    P, C = pnp_observations(path.parent, SCENE.target.nu)
    result = calibrate_hand_eye(P, C, setup=SCENE.setup,
                                options=RefineOptions(estimate_kappa=True))
    # Robot readings carry 0.02 deg / 0.1 mm noise; ten stations pin X far below that.
    assert_pose_close(result.hand_eye, SCENE.hand_eye_matrix, rot=np.deg2rad(0.03), trans=3e-4)
    assert_pose_close(result.target_pose, SCENE.target_pose_matrix, rot=np.deg2rad(0.03),
                      trans=5e-4)
    assert result.kappa == pytest.approx(SCENE.target.kappa, abs=5e-4)


@pytest.mark.timeout(120)
def test_cellcal_calibrate_reads_a_capture(captured_set, capsys) -> None:
    path, _ = captured_set
    out = path.parent.parent / "result.json"
    assert cli.main(["calibrate", str(path.parent), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert_pose_close(np.array(doc["hand_eye"]["matrix"]), SCENE.hand_eye_matrix,
                      rot=np.deg2rad(0.05), trans=5e-4)
    assert doc["target"]["kappa"] == pytest.approx(SCENE.target.kappa, abs=3e-3)
    assert doc["target"]["nu"] == pytest.approx(SCENE.target.nu, abs=1e-4)
