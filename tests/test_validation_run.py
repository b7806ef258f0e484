import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.boards import Checkerboard, board_points
from calib.geometry import (
    invert,
    make_transform,
    matrix_from_ur_pose,
    rotation_angle,
    ur_pose_from_matrix,
)
from calib.validation import dot_hit
from drivers.base import Robot, RobotStatus
from drivers.errors import WorkspaceError
from mocks.scene import camera_pose_for_tcp, default_scene
from service.jobs.validation_run import (
    BoardEstimate,
    CellChecks,
    GroundTruth,
    Probe,
    approach_pose,
    board_in_base,
    probe_points,
    run_dot_hit,
    tcp_pose_for_probe,
)
from tests.support.helpers import assert_pose_close, random_transforms

SCENE = default_scene()
X_TRUE = SCENE.hand_eye_matrix
Y_TRUE = SCENE.target_pose_matrix
PROBE = make_transform(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [0.0, 0.01, 0.15])
T = SCENE.target
TRUE_POINTS = probe_points(Checkerboard(T.inner_corners, T.square_size_m), kappa=T.kappa, nu=T.nu)


class FakeRobot:
    """Goes exactly where it is told and reports it; records every command."""

    def __init__(self, start: np.ndarray) -> None:
        self.T = start.copy()
        self.commands: list[np.ndarray] = []

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def tcp_pose(self) -> np.ndarray:
        return ur_pose_from_matrix(self.T)

    def joint_positions(self) -> np.ndarray:
        return np.zeros(6)

    def move_linear(self, pose, *, speed=0.25, acceleration=1.2) -> None:
        self.commands.append(np.asarray(pose, dtype=float))
        self.T = matrix_from_ur_pose(pose)

    def move_joint(self, q, *, speed=1.05, acceleration=1.4) -> None: ...

    def wait_settled(self, *, timeout=5.0) -> None: ...

    def stop(self) -> None: ...

    def status(self) -> RobotStatus:
        return RobotStatus(connected=True)


def test_probe_points_are_the_outer_corners_and_the_centre():
    pts = probe_points(Checkerboard((4, 3), 0.02), kappa=1.01, nu=0.99)
    grid = board_points((4, 3), 0.02, kappa=1.01, nu=0.99)
    assert list(pts) == ["corner_0_0", "corner_3_0", "corner_0_2", "corner_3_2", "centre"]
    np.testing.assert_array_equal(pts["corner_3_0"], grid[3])
    np.testing.assert_array_equal(pts["corner_3_2"], grid[-1])
    np.testing.assert_allclose(pts["centre"], [1.5 * 0.02 * 1.01 * 0.99, 0.02 * 1.01, 0.0])


def test_board_in_base_is_eq_24():
    rng = np.random.default_rng(2)
    X, P, C = random_transforms(rng, 3, scale=0.5)
    p = np.array([0.1, 0.05, 0.0])
    eih = board_in_base(X, setup="eye_in_hand", observation=(P, C))
    eth = board_in_base(X, setup="eye_to_hand", observation=(P, C))
    # the same points as calib.validation.dot_hit reconstructs them (eq. 24)
    D_c = (C[:3, :3] @ p + C[:3, 3])[None]
    np.testing.assert_allclose(eih[:3, :3] @ p + eih[:3, 3],
                               dot_hit(D_c, D_c, X, T_base_tcp=P[None])[0][0], atol=1e-12)
    np.testing.assert_allclose(eth[:3, :3] @ p + eth[:3, 3],
                               dot_hit(D_c, D_c, X, setup="eye_to_hand")[0][0], atol=1e-12)
    # a consistent calibration's target pose is what the observation gives
    Y = P @ X @ C
    np.testing.assert_allclose(board_in_base(X, setup="eye_in_hand", target_pose=Y), eih)


def test_board_in_base_needs_an_observation_eye_to_hand():
    with pytest.raises(ValueError, match="eye-to-hand dot-hit needs an observation"):
        board_in_base(np.eye(4), setup="eye_to_hand", target_pose=np.eye(4))
    with pytest.raises(ValueError, match="needs the calibration's target_pose"):
        board_in_base(np.eye(4), setup="eye_in_hand")


def test_tcp_pose_for_probe_puts_the_tip_on_the_point_with_least_turn():
    rng = np.random.default_rng(4)
    reference = random_transforms(rng, 1)[0]
    point = np.array([0.4, -0.2, 0.1])
    direction = np.array([0.1, 0.2, -1.0])
    T = tcp_pose_for_probe(point, direction, PROBE, reference)
    tip = T @ PROBE
    np.testing.assert_allclose(tip[:3, 3], point, atol=1e-12)
    np.testing.assert_allclose(tip[:3, 2], direction / np.linalg.norm(direction), atol=1e-12)
    # turning the probe about its axis only increases the rotation from the reference, which
    # is the angle between the two probe axes
    ref_probe = (reference @ PROBE)[:3, :3]
    best = rotation_angle(ref_probe.T @ tip[:3, :3])
    assert best == pytest.approx(np.arccos(ref_probe[:, 2] @ tip[:3, 2]))
    for a in np.linspace(-0.5, 0.5, 11):
        spun = tip[:3, :3] @ Rotation.from_rotvec([0, 0, a]).as_matrix()
        assert rotation_angle(ref_probe.T @ spun) >= best - 1e-12
    # a reference already pointing that way is kept as is
    same = tcp_pose_for_probe(reference[:3, 3] + 0.1, (reference @ PROBE)[:3, 2], PROBE,
                              reference)
    assert rotation_angle(reference[:3, :3].T @ same[:3, :3]) < 1e-12


def test_approach_pose_backs_off_along_the_probe():
    T = tcp_pose_for_probe(np.array([0.3, 0.1, 0.0]), [0.0, 0.0, -1.0], PROBE, np.eye(4))
    tip = (approach_pose(T, PROBE, 0.03) @ PROBE)[:3, 3]
    np.testing.assert_allclose(tip, [0.3, 0.1, 0.03], atol=1e-12)


def start_and_observation(robot_pose=None):
    P = SCENE.start_pose() if robot_pose is None else robot_pose
    return P, (P, camera_pose_for_tcp(SCENE, P))


def test_run_touches_each_point_after_an_approach_with_a_fake_robot():
    P0, obs = start_and_observation()
    robot = FakeRobot(P0)
    assert isinstance(robot, Robot)
    report = run_dot_hit(robot, TRUE_POINTS,
                         BoardEstimate("eye_in_hand", X_TRUE, observation=obs),
                         Probe(PROBE, approach=0.04),
                         CellChecks(ground_truth=GroundTruth(board_pose=Y_TRUE)))
    assert [p.target_id for p in report.points] == list(TRUE_POINTS)
    assert len(robot.commands) == 3 * len(TRUE_POINTS) + 1
    assert_pose_close(matrix_from_ur_pose(robot.commands[-1]), P0, rot=1e-12, trans=1e-12)
    normal = Y_TRUE[:3, 2]  # into the board's front
    for k, p in enumerate(report.points):
        above, touch, back = (matrix_from_ur_pose(c) @ PROBE
                              for c in robot.commands[3 * k:3 * k + 3])
        truth = Y_TRUE[:3, :3] @ p.point_target + Y_TRUE[:3, 3]
        np.testing.assert_allclose(touch[:3, 3], truth, atol=1e-9)
        np.testing.assert_allclose(touch[:3, 2], normal, atol=1e-9)
        np.testing.assert_allclose(above[:3, 3], truth - 0.04 * normal, atol=1e-9)
        np.testing.assert_allclose(back, above, atol=1e-12)
        np.testing.assert_allclose(p.commanded, truth, atol=1e-9)
        np.testing.assert_allclose(p.reached, truth, atol=1e-9)
    assert report.errors_m.max() < 1e-9
    doc = report.to_json()
    assert doc["error_m"]["max"] < 1e-9 and doc["points"][4]["id"] == "centre"
    assert "centre: reached 0.00 mm from the commanded point, error 0.00 mm" in report.summary()


def test_run_without_truth_reports_no_errors():
    P0, _ = start_and_observation()
    report = run_dot_hit(FakeRobot(P0), TRUE_POINTS,
                         BoardEstimate("eye_in_hand", X_TRUE, target_pose=Y_TRUE), Probe(PROBE))
    assert report.errors_m is None and report.to_json()["error_m"] is None
    assert "error" not in report.summary()


def test_run_outside_the_workspace_is_refused_before_moving():
    P0, obs = start_and_observation()
    robot = FakeRobot(P0)

    def low_ceiling(pose):
        if pose[2] > 0.5:
            raise WorkspaceError("above the ceiling")

    with pytest.raises(WorkspaceError, match="ceiling"):
        run_dot_hit(robot, TRUE_POINTS, BoardEstimate("eye_in_hand", X_TRUE, observation=obs),
                    Probe(PROBE), CellChecks(workspace_check=low_ceiling))
    assert robot.commands == []


def test_eye_to_hand_run_probes_a_board_in_the_cell():
    """Fixed camera above the table looking down at a board lying on it."""
    X = make_transform(np.diag([1.0, -1.0, -1.0]), [0.4, 0.0, 1.0])
    board = make_transform(np.diag([1.0, -1.0, -1.0]), [0.3, -0.1, 0.0])
    C = invert(X) @ board
    start = make_transform(np.diag([1.0, -1.0, -1.0]), [0.4, 0.0, 0.4])
    report = run_dot_hit(FakeRobot(start), TRUE_POINTS,
                         BoardEstimate("eye_to_hand", X, observation=(start, C)), Probe(PROBE),
                         CellChecks(ground_truth=GroundTruth(board_pose=board)))
    assert report.errors_m.max() < 1e-9


def mock_run(hand_eye, seed=0):
    robot = pytest.importorskip("mocks.devices").MockRobot(SCENE, seed=seed)
    robot.connect()
    P_read = matrix_from_ur_pose(robot.tcp_pose())
    obs = (P_read, camera_pose_for_tcp(SCENE, robot.true_pose))
    report = run_dot_hit(robot, TRUE_POINTS,
                         BoardEstimate("eye_in_hand", hand_eye, observation=obs), Probe(PROBE),
                         CellChecks(workspace_check=robot.workspace.check,
                                    ground_truth=GroundTruth(board_pose=Y_TRUE,
                                                             tcp_pose=lambda: robot.true_pose)))
    return report, robot


def test_mock_robot_hits_the_true_points_with_a_correct_calibration():
    for seed in range(3):
        report, robot = mock_run(X_TRUE, seed)
        assert report.errors_m.max() < 1e-3, report.summary()
        # back at the start as read (the reading differs from the truth by the robot noise)
        assert_pose_close(robot.true_pose, SCENE.start_pose(), rot=1e-3, trans=1e-3)


def test_mock_robot_misses_by_the_hand_eye_error():
    wrong = X_TRUE @ make_transform(np.eye(3), [0.005, 0.0, 0.0])
    report, _ = mock_run(wrong)
    assert report.errors_m.min() > 4e-3 and report.errors_m.max() < 6e-3, report.summary()
