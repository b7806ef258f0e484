"""MockRobot and MockCamera: noise statistics, settle semantics, limits, faults, rendering."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest

from calib.boards import detect_checkerboard
from calib.geometry import matrix_from_ur_pose, pose_error, ur_pose_from_matrix
from drivers.base import Camera, Robot
from drivers.errors import (
    CameraError,
    CameraStalledError,
    CameraTimeoutError,
    ProtectiveStopError,
    RobotConnectionError,
    RobotError,
    WorkspaceError,
)
from drivers.stall import STALL_AFTER
from mocks import ur_kinematics as kin
from mocks.camera import MockCamera
from mocks.devices import MockRobot, MockTiming, Workspace
from mocks.scene import Noise, camera_pose_for_tcp, default_scene
from tests.support.helpers import wait_for

SCENE = default_scene()
EXACT = SCENE.model_copy(update={"noise": Noise()})


def connected(scene=SCENE, **kwargs) -> MockRobot:
    robot = MockRobot(scene, **kwargs)
    robot.connect()
    return robot


def shifted(pose: np.ndarray, dz: float) -> np.ndarray:
    out = np.array(pose, dtype=float)
    out[2] += dz
    return out


def reading_error(robot: MockRobot) -> tuple[float, float]:
    angle, dist = pose_error(matrix_from_ur_pose(robot.tcp_pose()), robot.true_pose)
    return float(angle), float(dist)


def test_implements_the_protocols() -> None:
    robot = MockRobot(SCENE)
    assert isinstance(robot, Robot)
    assert isinstance(MockCamera(SCENE, robot), Camera)


@pytest.mark.timeout(30)
def test_reading_noise_matches_the_scene() -> None:
    scene = SCENE.model_copy(update={"noise": Noise(robot_rot_deg=0.05, robot_trans_mm=0.2)})
    robot = connected(scene, seed=3)
    start = robot.tcp_pose()
    errors = []
    for k in range(400):
        robot.move_linear(shifted(start, -0.01 * (k % 2)))
        errors.append(reading_error(robot))
    angle, dist = np.array(errors).T
    # perturb(): Gaussian angle and length of the given sigmas, so their RMS is the sigma.
    assert np.sqrt(np.mean(angle**2)) == pytest.approx(np.deg2rad(0.05), rel=0.12)
    assert np.sqrt(np.mean(dist**2)) == pytest.approx(0.2e-3, rel=0.12)


def test_reading_is_stable_at_rest_and_redrawn_per_settle() -> None:
    robot = connected()
    target = shifted(robot.tcp_pose(), -0.02)
    robot.move_linear(target)
    robot.wait_settled()
    first = robot.tcp_pose()
    assert all(np.array_equal(first, robot.tcp_pose()) for _ in range(5))
    robot.move_linear(target)  # same target, new rest: a new reading error
    robot.wait_settled()
    assert not np.array_equal(first, robot.tcp_pose())
    assert np.array_equal(robot.true_pose, matrix_from_ur_pose(target))


def test_noise_is_seeded() -> None:
    def readings(seed: int | None) -> np.ndarray:
        robot = connected(seed=seed)
        out = []
        for dz in (0.0, -0.01, -0.02):
            robot.move_linear(shifted(ur_pose_from_matrix(SCENE.start_pose()), dz))
            out.append(robot.tcp_pose())
        return np.array(out)

    assert np.array_equal(readings(None), readings(SCENE.seed))
    assert not np.array_equal(readings(1), readings(2))


def test_noise_free_scene_reports_the_true_pose() -> None:
    robot = connected(EXACT)
    target = shifted(robot.tcp_pose(), -0.05)
    robot.move_linear(target)
    np.testing.assert_allclose(robot.tcp_pose(), target, atol=1e-12)


@pytest.mark.timeout(10)
def test_timed_motion_and_settling() -> None:
    robot = connected(EXACT, timing=MockTiming(instant=False, settle_time=0.1))
    target = shifted(robot.tcp_pose(), -0.05)
    t0 = time.monotonic()
    robot.move_linear(target, speed=0.25, acceleration=2.5)  # 0.05 m: 0.3 s trapezoid
    moved = time.monotonic() - t0
    robot.wait_settled(timeout=5.0)
    settled = time.monotonic() - t0
    # Lower bounds only: a busy machine makes both later, never earlier.
    assert moved > 0.3 - 1e-3
    assert settled > 0.3 + 0.1 - 1e-3  # the move, then 0.1 s of ringing
    np.testing.assert_allclose(robot.tcp_pose(), target, atol=1e-12)


@pytest.mark.timeout(10)
def test_wait_settled_from_another_thread_waits_for_the_move() -> None:
    robot = connected(EXACT, timing=MockTiming(instant=False, settle_time=0.1))
    target = shifted(robot.tcp_pose(), -0.05)
    mover = threading.Thread(target=robot.move_linear, args=(target,),
                             kwargs={"speed": 0.25, "acceleration": 2.5})
    start_z = robot.true_pose[2, 3]
    t0 = time.monotonic()
    mover.start()
    wait_for("the move to begin", lambda: robot.true_pose[2, 3] != start_z, 10)
    robot.wait_settled(timeout=5.0)
    assert time.monotonic() - t0 > 0.3 + 0.1 - 1e-3  # 0.3 s move + 0.1 s ringing
    np.testing.assert_allclose(robot.tcp_pose(), target, atol=1e-12)
    mover.join(5.0)


@pytest.mark.timeout(10)
def test_speed_slider_scales_motion_time() -> None:
    robot = connected(EXACT, timing=MockTiming(instant=False, speed=0.5, settle_time=0.0))
    t0 = time.monotonic()
    robot.move_linear(shifted(robot.tcp_pose(), -0.05), speed=0.25, acceleration=2.5)
    assert time.monotonic() - t0 > 0.45  # 0.05 m at 0.125 m/s, 1.25 m/s^2


@pytest.mark.timeout(10)
def test_stop_interrupts_a_move() -> None:
    robot = connected(EXACT, timing=MockTiming(instant=False))
    start = robot.tcp_pose()

    def stop_once_moving() -> None:
        try:
            wait_for("2 mm of the move", lambda: robot.true_pose[2, 3] <= start[2] - 2e-3, 5)
        finally:
            robot.stop()

    threading.Thread(target=stop_once_moving, daemon=True).start()
    with pytest.raises(RobotError, match="stopped on request") as err:
        robot.move_linear(shifted(start, -0.2), speed=0.1, acceleration=1.0)
    assert err.value.code == "motion_stopped"
    z = robot.tcp_pose()[2]
    assert start[2] - 0.2 < z < start[2] - 1e-3  # stopped part way


def test_workspace_refuses_targets_outside() -> None:
    robot = connected(workspace=Workspace(lo=(-1.0, -1.0, 0.3), hi=(1.0, 1.0, 1.0)))
    before = robot.true_pose
    with pytest.raises(WorkspaceError, match=r"outside the workspace limits") as err:
        robot.move_linear(np.array([0.5, 0.0, 0.1, np.pi, 0.0, 0.0]))
    assert err.value.code == "outside_workspace"
    assert np.array_equal(robot.true_pose, before)
    with pytest.raises(WorkspaceError):
        robot.move_joint(np.array([0.0, -0.3, 2.6, -2.3, -1.57, 0.0]))  # TCP near the floor


def test_input_validation() -> None:
    robot = connected()
    with pytest.raises(ValueError, match="millimetres"):
        robot.move_linear(np.array([600.0, 0.0, 600.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        robot.move_linear(np.zeros(3))
    with pytest.raises(ValueError, match="degrees"):
        robot.move_joint(np.array([0.0, -90.0, 90.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="positive"):
        robot.move_linear(robot.tcp_pose(), speed=0.0)


def test_not_connected() -> None:
    robot = MockRobot(SCENE)
    with pytest.raises(RobotConnectionError, match="Connect first"):
        robot.tcp_pose()
    assert not robot.status().connected
    with robot:
        assert robot.status().ready
    assert not robot.status().connected


def test_protective_stop_fault() -> None:
    robot = connected(EXACT)
    start = robot.tcp_pose()
    robot.inject_fault("protective_stop")
    with pytest.raises(ProtectiveStopError, match="protective stop"):
        robot.move_linear(shifted(start, -0.1))
    assert robot.tcp_pose()[2] == pytest.approx(start[2] - 0.05)  # stopped half way
    assert robot.status().protective_stop and not robot.status().ready
    with pytest.raises(ProtectiveStopError, match="Unlock it"):
        robot.move_linear(start)
    robot.unlock_protective_stop()
    robot.move_linear(start)
    np.testing.assert_allclose(robot.tcp_pose(), start, atol=1e-12)


def test_disconnect_fault() -> None:
    robot = connected(faults=["disconnect"])
    with pytest.raises(RobotConnectionError, match="during a move"):
        robot.move_linear(shifted(robot.tcp_pose(), -0.1))
    assert not robot.status().connected
    with pytest.raises(RobotConnectionError):
        robot.tcp_pose()
    robot.connect()
    robot.tcp_pose()


def test_unreachable_fault_leaves_the_robot_in_place() -> None:
    robot = connected(faults=["unreachable"])
    before = robot.true_pose
    with pytest.raises(RobotError, match="out of reach") as err:
        robot.move_linear(shifted(robot.tcp_pose(), -0.1))
    assert err.value.code == "motion_failed"
    assert np.array_equal(robot.true_pose, before)
    robot.move_linear(shifted(robot.tcp_pose(), -0.1))  # one-shot


@pytest.mark.timeout(10)
def test_slow_fault_times_out_settling() -> None:
    robot = connected()
    robot.inject_fault("slow", 1.0)
    robot.move_linear(shifted(robot.tcp_pose(), -0.01))
    with pytest.raises(RobotError, match=r"did not come to rest within 0\.05 s") as err:
        robot.wait_settled(timeout=0.05)
    assert err.value.code == "not_settled"
    robot.wait_settled(timeout=10.0)


def test_unknown_fault() -> None:
    with pytest.raises(ValueError, match="unknown fault 'meteor'"):
        MockRobot(SCENE, faults=["meteor"])
    with pytest.raises(ValueError, match="unknown fault"):
        MockCamera(SCENE, MockRobot(SCENE)).inject_fault("meteor")


def test_joint_moves_follow_ur5e_kinematics() -> None:
    robot = connected(EXACT)
    robot.move_joint(kin.HOME_Q)
    np.testing.assert_allclose(robot.joint_positions(), kin.HOME_Q)
    np.testing.assert_allclose(robot.tcp_pose(), kin.fk_pose(kin.HOME_Q), atol=1e-12)
    target = shifted(robot.tcp_pose(), 0.05)
    robot.move_linear(target)  # joints now come from inverse kinematics
    np.testing.assert_allclose(kin.fk_pose(robot.joint_positions()), target, atol=1e-6)
    robot.move_linear(np.array([1.2, 0.6, 0.5, np.pi, 0.0, 0.0]))  # beyond UR5e reach
    with pytest.raises(RobotError, match="beyond the reach") as err:
        robot.joint_positions()
    assert err.value.code == "joints_unknown"


# ---- camera --------------------------------------------------------------------------------


@pytest.fixture
def rig() -> tuple[MockRobot, MockCamera]:
    robot = connected()
    camera = MockCamera(SCENE, robot)
    camera.open()
    return robot, camera


@pytest.mark.timeout(30)
def test_camera_renders_the_board_from_the_true_pose(rig) -> None:
    robot, camera = rig
    station = ur_pose_from_matrix(robot.true_pose)
    station[:2] += [0.03, -0.02]
    robot.move_linear(station)
    image = camera.grab()
    assert image.shape == (1024, 1280) and image.dtype == np.uint8
    assert camera.resolution == (1280, 1024)
    det = detect_checkerboard(image, SCENE.target.inner_corners)
    assert det.ok, det.reason
    T = camera_pose_for_tcp(SCENE, robot.true_pose)
    expected, _ = cv2.projectPoints(SCENE.true_board_points(), cv2.Rodrigues(T[:3, :3])[0],
                                    T[:3, 3], SCENE.camera.k_matrix, SCENE.camera.dist_coeffs)
    err = np.linalg.norm(det.corners - expected.reshape(-1, 2), axis=1)
    assert err.max() < 0.3, f"corner error {err.max():.3f} px"
    assert not np.array_equal(image, camera.grab())  # fresh sensor noise per frame


@pytest.mark.timeout(30)
def test_camera_faults(rig) -> None:
    _, camera = rig
    camera.inject_fault("timeout")
    t0 = time.monotonic()
    with pytest.raises(CameraTimeoutError, match=r"no frame within 0\.1 s"):
        camera.grab(timeout=0.1)
    assert time.monotonic() - t0 > 0.1 - 1e-3  # it waited for the frame
    camera.inject_fault("corrupt")
    torn = camera.grab()
    assert (torn[-1] == 0).all()
    assert not detect_checkerboard(torn, SCENE.target.inner_corners).ok
    assert (camera.grab()[-1] > 0).any()  # one-shot
    camera.inject_fault("disconnect")
    for _ in range(2):
        with pytest.raises(CameraError, match="not open"):
            camera.grab()
    camera.open()
    camera.grab()


@pytest.mark.timeout(30)
def test_camera_unplugged_then_replugged(rig) -> None:
    _, camera = rig
    assert camera.opened
    camera.inject_fault("unplug")
    with pytest.raises(CameraError, match="disconnected") as err:
        camera.grab()
    assert err.value.code == "camera_disconnected" and not camera.opened
    with pytest.raises(CameraError, match="not open") as err:
        camera.grab()
    assert err.value.code == "camera_not_open"
    with pytest.raises(CameraError, match="plug it back in") as err:
        camera.open()
    assert err.value.code == "camera_not_found" and not camera.opened
    camera.replug()
    assert not camera.opened  # plugged in, not yet opened
    camera.open()
    assert camera.opened
    assert detect_checkerboard(camera.grab(), SCENE.target.inner_corners).ok


@pytest.mark.timeout(30)
def test_camera_stall_is_one_fault_after_consecutive_timeouts(rig) -> None:
    _, camera = rig
    camera.inject_fault("timeout", STALL_AFTER - 1)
    for _ in range(STALL_AFTER - 1):
        with pytest.raises(CameraTimeoutError):
            camera.grab(timeout=0.01)
    camera.grab()  # a frame ends the streak
    camera.inject_fault("stall")
    for _ in range(STALL_AFTER - 1):
        with pytest.raises(CameraTimeoutError):
            camera.grab(timeout=0.01)
        assert camera.opened
    with pytest.raises(CameraStalledError, match=f"no frame in {STALL_AFTER} grabs") as err:
        camera.grab(timeout=0.01)
    assert err.value.code == "camera_stalled" and not camera.opened
    with pytest.raises(CameraError, match="not open"):
        camera.grab(timeout=0.01)
    camera.open()  # still stalled after a reopen: the stream itself is stuck
    with pytest.raises(CameraTimeoutError):
        camera.grab(timeout=0.01)
    camera.clear_faults()
    camera.open()
    camera.grab()


def test_camera_configuration_and_lifecycle() -> None:
    robot = connected()
    camera = MockCamera(SCENE, robot)
    with pytest.raises(CameraError, match="not open"):
        camera.grab()
    with camera:
        camera.configure(resolution=(1280, 1024), exposure=0.01)
        with pytest.raises(CameraError, match="only delivers 1280x1024") as err:
            camera.configure(resolution=(640, 480))
        assert err.value.code == "camera_unsupported"
    camera.close()
