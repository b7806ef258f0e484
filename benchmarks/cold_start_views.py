"""Feasible views of a blind cell as an oracle sees them: the truth of cell ``k`` and a pool of
views the cell would detect and the box allows (``benchmarks.cold_start_bound``).

Two families: views around the board (any tilt up to ``MAX_TILT_DEG``, azimuth and roll, a
look-at point anywhere on the board, distances over all the box allows) and views from
anywhere in the box (eye-in-hand the camera anywhere in it looking at a board point,
eye-to-hand the tool anywhere in it with the board facing the camera), turned about the
camera centre so the board lands anywhere in the image. A view is feasible when, under the
true camera, every corner lies ``IMAGE_MARGIN_PX`` inside the image, the board is less oblique
than ``CornerCell.MAX_DETECT_TILT_DEG``, and the tcp (and eye-in-hand the camera) lies inside
the box by ``BOX_MARGIN_M``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calib import Pinhole, board_from_target, look_at_view, robot_from_camera
from calib.boards import Board
from calib.chain import camera_from_robot
from calib.joint import CellParameters
from mocks.blindcells import CornerCell, random_blind_scene
from mocks.scene import MockScene

#: Candidate views drawn per family and round (around the board, from anywhere in the box),
#: the feasible views wanted, and the most rounds drawn for them.
DRAWS, POOL, ROUNDS = 4000, 4000, 5
#: Largest tilt from the board normal of the views around the board.
MAX_TILT_DEG = 60.0
#: Free border of every corner in the image, px (``CornerCell`` detects from 4 px).
IMAGE_MARGIN_PX = 8.0
#: The tcp's and the camera's least margin inside the box, m.
BOX_MARGIN_M = 0.01

@dataclass(frozen=True)
class Truth:
    """A blind cell as the oracle knows it: the scene, the joint model's parameters at the
    truth, the nominal board, the box (lo, hi) and the start T_base_tcp (4, 4)."""

    scene: MockScene
    cell: CellParameters
    board: Board
    box: tuple[np.ndarray, np.ndarray]
    start: np.ndarray

    @property
    def setup(self) -> str:
        return self.scene.setup


def truth(k: int) -> Truth:
    """Blind cell ``k`` as ``benchmarks.cold_start.one_cell`` draws it, with its truth."""
    scene = random_blind_scene(k, ("eye_in_hand", "eye_to_hand")[k % 2])
    cam, target = scene.camera, scene.target
    cell = CellParameters(K=cam.k_matrix, dist=cam.dist_coeffs, nu=target.nu,
                          kappa=target.kappa, hand_eye=scene.hand_eye_matrix,
                          target_pose=scene.target_pose_matrix)
    return Truth(scene, cell, board_from_target(scene.nominal_target()),
                 (np.array(scene.workspace.lo), np.array(scene.workspace.hi)), scene.start_pose())


def _turned(C: np.ndarray, rng: np.random.Generator, half_fov: float) -> np.ndarray:
    """Views C (n, 4, 4) turned about the camera centre across the optical axis, by up to
    ``half_fov`` in a random direction, so the board lands anywhere in the image."""
    turn = np.tile(np.eye(4), (len(C), 1, 1))
    angle = rng.uniform(0.0, 2.0 * np.pi, len(C))
    xy = half_fov * rng.uniform(0.0, 1.0, (len(C), 1)) * np.column_stack([np.cos(angle),
                                                                           np.sin(angle)])
    turn[:, :3, :3] = Rotation.from_rotvec(np.column_stack([xy, np.zeros(len(C))])).as_matrix()
    return turn @ C


def _around_board(t: Truth, rng: np.random.Generator, n: int, d0: float) -> np.ndarray:
    """T_cam_target (n, 4, 4) of views around the board (module docstring)."""
    grid = t.board.points()
    centre = grid[[0, -1]].mean(axis=0)
    look = centre + (grid[-1] - centre) * rng.uniform(-1.0, 1.0, (n, 3)) * [1, 1, 0]
    tilt = np.deg2rad(MAX_TILT_DEG) * np.sqrt(rng.uniform(0.0, 1.0, n))
    dist = rng.uniform(max(0.05, d0 - 0.45), d0 + 0.45, n)
    return np.stack([look_at_view(look[k], tilt[k], *rng.uniform(0, 2 * np.pi, 2), dist[k])
                     for k in range(n)])


def _look_from(eye: np.ndarray, at: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R_cam_base (n, 3, 3) of cameras at ``eye`` (n, 3) looking at ``at`` (n, 3), rolled."""
    z = at - eye
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, _other_axis(z))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    R = np.stack([x, np.cross(z, x), z], axis=2)  # columns: camera axes in the base frame
    return np.swapaxes(R @ Rotation.from_rotvec(np.outer(roll, [0, 0, 1])).as_matrix(), 1, 2)


def _other_axis(z: np.ndarray) -> np.ndarray:
    """An axis (n, 3) not parallel to each row of ``z`` (n, 3)."""
    return np.where(np.abs(z[:, 2:]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])


def _from_box(t: Truth, rng: np.random.Generator, n: int) -> np.ndarray:
    """T_cam_target (n, 4, 4) of views from anywhere in the box (module docstring)."""
    lo, hi = t.box
    X, Y = t.cell.hand_eye, t.cell.target_pose
    grid = t.board.points()
    on_board = grid[0] + (grid[-1] - grid[0]) * rng.uniform(0.0, 1.0, (n, 3))
    roll = rng.uniform(0.0, 2.0 * np.pi, n)
    if t.setup == "eye_in_hand":  # the camera anywhere in the box, looking at a board point
        eye = rng.uniform(lo, hi, (n, 3))
        R = _look_from(eye, on_board @ Y[:3, :3].T + Y[:3, 3], roll)  # R_cam_base
        C = np.tile(np.eye(4), (n, 1, 1))
        C[:, :3, :3] = R @ Y[:3, :3]
        C[:, :3, 3] = np.einsum("nij,nj->ni", R, Y[:3, 3] - eye)
        return C
    # eye-to-hand: the tool anywhere in the box, the board facing the camera; its centre's
    # line of sight depends on the board's turn, so two rounds settle it
    tcp = rng.uniform(lo, hi, (n, 3))
    tcp_cam = (tcp - X[:3, 3]) @ X[:3, :3]  # tool positions in the camera frame
    centre = on_board
    C = np.tile(np.eye(4), (n, 1, 1))
    tilt = np.deg2rad(MAX_TILT_DEG) * np.sqrt(rng.uniform(0.0, 1.0, n))
    tilt_turn = Rotation.from_rotvec(np.column_stack([np.cos(roll), np.sin(roll), 0 * roll])
                                     * tilt[:, None]).as_matrix()
    sight = tcp_cam
    for _ in range(2):
        R_cam_target = np.swapaxes(_look_from(np.zeros((n, 3)), sight,
                                              rng.uniform(0, 2 * np.pi, n)), 1, 2) @ tilt_turn
        # the tcp at tcp_cam: C = inv(X) P Y, so the board origin is tcp_cam + R_cam_tcp t_Y
        C[:, :3, :3] = R_cam_target
        C[:, :3, 3] = tcp_cam + (R_cam_target @ Y[:3, :3].T) @ Y[:3, 3]
        sight = np.einsum("nij,nj->ni", R_cam_target, centre) + C[:, :3, 3]
    return C


def feasible(t: Truth, C: np.ndarray) -> np.ndarray:
    """Which views C = T_cam_target (n, 4, 4) the cell detects and the box allows, (n,)."""
    p = np.einsum("nij,mj->nmi", C[:, :3, :3], t.scene.true_board_points()) + C[:, None, :3, 3]
    front = (p[..., 2] > 0.02).all(axis=1)
    uv = Pinhole(t.cell.K, t.cell.dist).project(np.where(p[..., 2:] > 0.02, p, 1.0)
                                                .reshape(-1, 3)).reshape(len(C), -1, 2)
    w, h = t.scene.camera.image_size
    m = IMAGE_MARGIN_PX
    inside = ((uv >= m) & (uv <= [w - m, h - m])).all(axis=(1, 2))
    facing = C[:, 2, 2] > np.cos(np.deg2rad(CornerCell.MAX_DETECT_TILT_DEG))
    P = robot_from_camera(C, t.cell.hand_eye, t.cell.target_pose, t.setup)
    ok = front & inside & facing & _in_box(t, P[:, :3, 3])
    if t.setup == "eye_in_hand":
        ok &= _in_box(t, (P @ t.cell.hand_eye)[:, :3, 3])
    return ok


def _in_box(t: Truth, p: np.ndarray) -> np.ndarray:
    lo, hi = t.box
    return ((p >= lo + BOX_MARGIN_M) & (p <= hi - BOX_MARGIN_M)).all(axis=1)


def pool(t: Truth, rng: np.random.Generator, draws: int = DRAWS) -> np.ndarray:
    """Feasible views of both families, as T_base_tcp (n, 4, 4): rounds of ``draws`` per
    family (the views from the box half of them turned) until ``POOL`` are feasible or
    ``ROUNDS`` rounds are drawn."""
    C0 = camera_from_robot(t.start, t.cell.hand_eye, t.cell.target_pose, t.setup)
    half_fov = float(np.arctan(t.scene.camera.image_size[0] / 2.0 / t.cell.K[0, 0]))
    found: list[np.ndarray] = []
    for _ in range(ROUNDS):
        box = _from_box(t, rng, draws)
        C = np.concatenate([
            _turned(_around_board(t, rng, draws, float(np.linalg.norm(C0[:3, 3]))), rng,
                    half_fov), box[: draws // 2], _turned(box[draws // 2:], rng, half_fov)])
        found.append(C[feasible(t, C)])
        if sum(len(c) for c in found) >= POOL:
            break
    C = np.concatenate(found)[:POOL]
    return robot_from_camera(C, t.cell.hand_eye, t.cell.target_pose, t.setup)


