import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.boards import Checkerboard, board_points
from calib.camera import Pinhole
from calib.chain import camera_from_robot, robot_from_camera
from calib.geometry import invert, make_transform, perturb, rotation_angle
from calib.handeye import calibrate_hand_eye
from calib.planning import (
    CellGuess,
    PlanOptions,
    look_at_view,
    order_for_travel,
    path_length,
    plan_stations,
    rough_target_from_image,
)
from mocks.scene import default_scene
from tests.support.helpers import assert_pose_close

SCENE = default_scene()
K = SCENE.camera.k_matrix
DIST = SCENE.camera.dist_coeffs
SIZE = SCENE.camera.image_size
CORNERS = SCENE.target.inner_corners
SQUARE = SCENE.target.square_size_m
D0 = SCENE.working_distance()
BAND = (0.8 * D0, 1.3 * D0)
BOX = ((-1.5, -1.5, 0.0), (1.5, 1.5, 1.5))
CENTRE = board_points(CORNERS, SQUARE)[[0, -1]].mean(axis=0)


def cell(setup):
    """(start base_T_tcp, hand_eye, target_pose) of a cell whose start view is square on."""
    if setup == "eye_in_hand":
        X, Y = SCENE.hand_eye_matrix, SCENE.target_pose_matrix
    else:  # camera 1.2 m above the table looking down; board 4 cm beyond a tilted flange
        X = make_transform(np.diag([1.0, -1.0, -1.0]), [0.5, 0.1, 1.2])
        Y = make_transform(Rotation.from_euler("xz", [10.0, 20.0], degrees=True).as_matrix(),
                           [-0.15, -0.1, 0.04])
    C0 = look_at_view(CENTRE, 0.0, 0.0, 0.0, D0)
    return robot_from_camera(C0, X, Y, setup), X, Y


def plan(setup="eye_in_hand", n=15, *, hand_eye_guess=None, target_pose_guess=None, K=K,
         **options):
    P0, X, Y = cell(setup)
    guess = CellGuess(P0, X if hand_eye_guess is None else hand_eye_guess,
                      Y if target_pose_guess is None else target_pose_guess, setup)
    options = dict(image_size=SIZE, distance_band=BAND, workspace=BOX, rng=3) | options
    return plan_stations(n, guess, Pinhole(K, DIST), Checkerboard(CORNERS, SQUARE),
                         PlanOptions(**options))


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
def test_planned_stations_keep_the_board_in_view_inside_the_workspace(setup):
    _, X, Y = cell(setup)
    p = plan(setup)
    assert p.tcp_poses.shape == p.views.shape == (15, 4, 4)
    C = camera_from_robot(p.tcp_poses, X, Y, setup)
    np.testing.assert_allclose(C, p.views, atol=1e-12)
    margin = 0.04 * min(SIZE) - 1e-6
    s = SQUARE
    plate = np.array([[-s, -s, 0], [CORNERS[0] * s, -s, 0], [-s, CORNERS[1] * s, 0],
                      [CORNERS[0] * s, CORNERS[1] * s, 0]])
    for Ci in C:
        pts = np.vstack([plate, board_points(CORNERS, SQUARE)])
        assert (pts @ Ci[:3, :3].T + Ci[:3, 3])[:, 2].min() > 0.0
        uv = cv2.projectPoints(pts, cv2.Rodrigues(Ci[:3, :3])[0], Ci[:3, 3], K, DIST)[0]
        uv = uv.reshape(-1, 2)
        assert (uv >= margin).all() and (uv <= np.array(SIZE) - margin).all()
    t = p.tcp_poses[:, :3, 3]
    assert (t >= BOX[0]).all() and (t <= BOX[1]).all()


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
def test_cut_stations_put_corners_near_the_image_corners(setup):
    """cut_fraction 0.4 of 15: six views cut the board at the border with >= 12 corners in
    view, one of them near an image corner; the other nine show the whole board."""
    _, X, Y = cell(setup)
    p = plan(setup, cut_fraction=0.4, min_cut_points=12)
    grid = board_points(CORNERS, SQUARE)
    w, h = SIZE
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]])
    cut, reach = 0, []
    for C in camera_from_robot(p.tcp_poses, X, Y, setup):
        uv = cv2.projectPoints(grid, cv2.Rodrigues(C[:3, :3])[0], C[:3, 3], K, DIST)[0]
        uv = uv.reshape(-1, 2)
        inside = ((uv >= 0) & (uv <= SIZE)).all(axis=1)
        if not inside.all():
            cut += 1
            assert inside.sum() >= 12
            reach.append(np.linalg.norm(uv[inside][:, None] - corners, axis=-1).min())
    assert cut == 6
    assert max(reach) <= 0.15 * min(SIZE)
    full = plan(setup)
    assert np.mean(reach) < 0.5 * _corner_reach(full, X, Y, setup)


def _corner_reach(p, X, Y, setup):
    """Mean over stations of the distance (px) from the nearest image corner to a corner."""
    w, h = SIZE
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]])
    out = []
    for C in camera_from_robot(p.tcp_poses, X, Y, setup):
        uv = cv2.projectPoints(board_points(CORNERS, SQUARE), cv2.Rodrigues(C[:3, :3])[0],
                               C[:3, 3], K, DIST)[0].reshape(-1, 2)
        out.append(np.linalg.norm(uv[:, None] - corners, axis=-1).min())
    return float(np.mean(out))


def test_views_tilt_and_roll_about_varied_axes_within_the_band():
    p = plan(max_tilt_deg=35.0, max_roll_deg=90.0)
    axis = p.views[:, :3, :3].transpose(0, 2, 1)[:, :, 2]  # optical axis in the target frame
    tilt = np.degrees(np.arccos(axis[:, 2]))
    assert tilt.max() <= 35.0 + 1e-9 and tilt.max() > 20.0
    azimuth = np.degrees(np.arctan2(axis[:, 1], axis[:, 0]))
    assert np.ptp(azimuth) > 180.0  # tilted towards every side
    x_axis = p.views[:, 0, :3]  # camera x in the target frame
    roll = np.degrees(np.arctan2(x_axis[:, 1], x_axis[:, 0]))
    assert np.ptp(roll) > 60.0
    centre_cam = p.views[:, :3, :3] @ CENTRE + p.views[:, :3, 3]
    dist = np.linalg.norm(centre_cam, axis=1)
    slack = 0.25 * np.linalg.norm(CENTRE)  # look-at jitter
    assert dist.min() > BAND[0] - slack and dist.max() < BAND[1] + slack


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
def test_hand_eye_solver_recovers_x_on_noise_free_observations_of_the_plan(setup):
    """The plan uses rough guesses; the true cell differs by millimetres and a degree."""
    rng = np.random.default_rng(11)
    _, X_true, Y_true = cell(setup)
    X_guess = perturb(X_true, np.deg2rad(1.0), 0.005, rng)
    Y_guess = perturb(Y_true, np.deg2rad(1.0), 0.005, rng)
    p = plan(setup, n=10, hand_eye_guess=X_guess, target_pose_guess=Y_guess)
    C = camera_from_robot(p.tcp_poses, X_true, Y_true, setup)
    result = calibrate_hand_eye(p.tcp_poses, C, setup=setup, method="sm")
    assert_pose_close(result.hand_eye, X_true, rot=1e-9, trans=1e-9)
    assert_pose_close(result.target_pose, Y_true, rot=1e-9, trans=1e-9)


def test_same_seed_same_plan():
    np.testing.assert_array_equal(plan(rng=5).tcp_poses, plan(rng=5).tcp_poses)


def test_order_reduces_travel_against_unordered_plans():
    P0, _, _ = cell("eye_in_hand")
    p = plan(n=15)
    assert p.travel == pytest.approx(path_length(P0, p.tcp_poses))
    rng = np.random.default_rng(0)
    shuffled = [path_length(P0, p.tcp_poses[rng.permutation(15)]) for _ in range(20)]
    assert p.travel < 0.6 * np.mean(shuffled)
    assert p.travel < min(shuffled)


def test_nearest_neighbour_order_walks_a_line():
    x = np.array([3.0, 1.0, 4.0, 2.0])
    poses = make_transform(np.broadcast_to(np.eye(3), (4, 3, 3)),
                           np.stack([x, 0 * x, 0 * x], axis=1))
    np.testing.assert_array_equal(order_for_travel(np.eye(4), poses), [1, 3, 0, 2])
    assert path_length(np.eye(4), poses[[1, 3, 0, 2]]) == pytest.approx(4.0)


def test_travel_counts_rotation():
    turned = make_transform(Rotation.from_rotvec([0, 0, 1.0]).as_matrix(), [0.0, 0.0, 0.0])
    assert path_length(np.eye(4), turned[None]) == pytest.approx(0.1)


@pytest.mark.parametrize(("kw", "match"), [
    ({"n": 2}, "at least 3 stations"),
    ({"max_tilt_deg": 0.0}, "max_tilt_deg must be in"),
    ({"distance_band": (0.5, 0.3)}, "distance_band"),
    ({"workspace": ((0, 0, 0), (0, 1, 1))}, "lo < hi"),
    ({"setup": "eye_on_base"}, "unknown setup"),
    ({"K": np.eye(2)}, "K must be a finite 3x3"),
    ({"image_size": (0, 480)}, "image_size"),
    ({"cut_fraction": 1.5}, "cut_fraction must be in"),
    ({"min_cut_points": 3}, "min_cut_points must be at least 6"),
    ({"hand_eye_guess": np.zeros((4, 4))}, "hand_eye_guess"),
])
def test_bad_options_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        plan(**kw)


def test_workspace_too_small_is_refused():
    P0 = cell("eye_in_hand")[0][:3, 3]
    box = (P0 - 0.05, P0 + 0.05)
    with pytest.raises(ValueError, match=r"could place only \d+ of 15 .*workspace box .* "
                                         r"too small to fit the views"):
        plan(workspace=box)


def test_board_that_cannot_fit_the_image_is_refused():
    with pytest.raises(ValueError, match=r"board does not fit in the image.*increase the "
                                         "distance band"):
        plan(distance_band=(0.3 * D0, 0.4 * D0))


def test_parallel_rotation_axes_are_refused():
    """Views tilted by under a degree: every motion turns about nearly the optical axis."""
    with pytest.raises(ValueError, match=r"would not determine the hand-eye.*parallel.*raise "
                                         "max_tilt_deg"):
        plan(n=3, max_tilt_deg=0.5)


def test_motions_too_small_to_define_screw_axes_are_refused():
    with pytest.raises(ValueError, match=r"would not determine the hand-eye.*rotate by more "
                                         "than"):
        plan(max_tilt_deg=0.5, max_roll_deg=0.0)


def test_start_pose_not_facing_the_board_is_refused():
    Y = cell("eye_in_hand")[2]
    flipped = Y @ make_transform(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="does not face the front of the board"):
        plan(target_pose_guess=flipped)


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
def test_rough_target_from_image_closes_the_chain(setup):
    P0, X, Y = cell(setup)
    P0 = P0 @ make_transform(Rotation.from_euler("xy", [8.0, -5.0], degrees=True).as_matrix(),
                             [0.01, -0.02, 0.0])
    C = camera_from_robot(P0, X, Y, setup)
    uv = cv2.projectPoints(board_points(CORNERS, SQUARE), cv2.Rodrigues(C[:3, :3])[0],
                           C[:3, 3], K, DIST)[0].reshape(-1, 2)
    board, guess = Checkerboard(CORNERS, SQUARE), CellGuess(P0, X, setup=setup)
    Y_est = rough_target_from_image(uv, Pinhole(K, DIST), board, guess)
    assert_pose_close(Y_est, Y, rot=1e-6, trans=1e-6)
    # a partial view: the left half of the board, with its point ids
    x = board.points()[:, 0]
    part = np.flatnonzero(x < 0.5 * x.max())
    Y_part = rough_target_from_image(uv[part], Pinhole(K, DIST), board, guess, point_ids=part)
    assert_pose_close(Y_part, Y, rot=1e-6, trans=1e-6)
    # approximate intrinsics (focal length 3 % off) still give a usable guess
    K_rough = K * [[1.03], [1.03], [1.0]]
    Y_rough = rough_target_from_image(uv, Pinhole(K_rough, DIST), board, guess)
    assert rotation_angle(invert(Y_rough)[:3, :3] @ Y[:3, :3]) < np.deg2rad(3.0)
    assert np.linalg.norm(Y_rough[:3, 3] - Y[:3, 3]) < 0.05 * D0


def test_rough_target_needs_one_point_per_corner():
    with pytest.raises(ValueError, match="got 10 corners for 88 board points"):
        rough_target_from_image(np.zeros((10, 2)), Pinhole(K, None), Checkerboard(CORNERS, SQUARE),
                                CellGuess(np.eye(4), np.eye(4)))
