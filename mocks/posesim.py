"""Pose-level simulation of a calibration cell: stations, robot noise, camera poses from PnP.

Used by tests and benchmarks of the hand-eye core where images are not needed: it produces what
a real cell would record (noisy robot readings and camera poses estimated by PnP from noisy
corners) together with the truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib import invert, make_transform, perturb, robot_from_camera, solve_pnp

#: A 1280x1024 camera with a 1400 px focal length (about 49 deg horizontal field of view).
DEFAULT_K = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 512.0], [0.0, 0.0, 1.0]])
DEFAULT_IMAGE_SIZE = (1280, 1024)


@dataclass(frozen=True)
class Cell:
    """The true geometry of a simulated cell (metres, see docs/conventions.md)."""

    setup: str
    hand_eye: np.ndarray  # shape (4, 4)
    target_pose: np.ndarray  # shape (4, 4)
    board_points: np.ndarray  # shape (N, 3), true corner positions in the target frame
    K: np.ndarray = field(default_factory=DEFAULT_K.copy)
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE


def default_cell(setup: str = "eye_in_hand", *, inner_corners: tuple[int, int] = (11, 8),
                 square_size: float = 0.03) -> Cell:
    """A typical UR cell: a camera 10 cm off the flange, a board 0.6 m in front of the base."""
    cols, rows = inner_corners
    jj, ii = np.mgrid[0:rows, 0:cols]
    board = np.stack([ii.ravel() * square_size, jj.ravel() * square_size,
                      np.zeros(ii.size)], axis=1)
    if setup == "eye_in_hand":
        X = make_transform(Rotation.from_euler("xyz", [2.0, -3.0, 90.0], degrees=True).as_matrix(),
                           [0.035, -0.082, 0.061])
        Y = make_transform(Rotation.from_euler("xyz", [180.0, 0.0, 20.0], degrees=True).as_matrix(),
                           [0.62, 0.05, 0.01])
    else:
        R_base_cam = Rotation.from_euler("xyz", [-150.0, 0.0, 90.0], degrees=True).as_matrix()
        X = make_transform(R_base_cam, [1.1, 0.0, 0.8])
        Y = make_transform(Rotation.from_euler("xyz", [0.0, 0.0, 45.0], degrees=True).as_matrix(),
                           [-0.12, -0.1, 0.03])
    return Cell(setup=setup, hand_eye=X, target_pose=Y, board_points=board)


@dataclass(frozen=True)
class ViewSpread:
    """How :func:`sample_camera_poses` spreads the views: ``distance`` range (m), the tilt from
    the board normal (up to ``max_tilt_deg``), and ``margin_px`` of image border to spare."""

    distance: tuple[float, float] = (0.35, 0.6)
    max_tilt_deg: float = 35.0
    margin_px: float = 20.0


@dataclass(frozen=True)
class StationNoise:
    """Noise of :func:`simulate`: robot readings (radians, metres) and corners (pixels)."""

    robot_rot_sigma: float = float(np.deg2rad(0.05))
    robot_trans_sigma: float = 0.25e-3
    pixel_noise: float = 0.15


def sample_camera_poses(cell: Cell, n: int, rng: np.random.Generator,
                        spread: ViewSpread = ViewSpread()) -> np.ndarray:
    """T_cam_target for ``n`` views that see the whole board, shape (n, 4, 4).

    Each camera looks at a point near the board centre from a distance in ``spread.distance``,
    with its axis tilted up to ``spread.max_tilt_deg`` from the board normal about a random axis
    and a random roll, so the motions between views rotate about varied axes.
    """
    centre = cell.board_points.mean(axis=0)
    w, h = cell.image_size
    poses: list[np.ndarray] = []
    while len(poses) < n:
        tilt = np.deg2rad(spread.max_tilt_deg) * np.sqrt(rng.uniform())
        azim = rng.uniform(0.0, 2.0 * np.pi)
        view = np.array([np.sin(tilt) * np.cos(azim), np.sin(tilt) * np.sin(azim), np.cos(tilt)])
        z = view  # camera axis in the target frame, pointing into the board
        x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.99 else [1.0, 0.0, 0.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        roll = Rotation.from_rotvec(z * rng.uniform(-np.pi, np.pi)).as_matrix()
        R_target_cam = roll @ np.stack([x, y, z], axis=1)
        aim = centre + rng.normal(0.0, 0.02, 3) * [1.0, 1.0, 0.0]
        T_target_cam = make_transform(R_target_cam, aim - rng.uniform(*spread.distance) * z)
        C = invert(T_target_cam)
        uv = project(cell, C, cell.board_points)
        m = spread.margin_px
        if (uv.min(axis=0) > m).all() and (uv.max(axis=0) < [w - m, h - m]).all():
            poses.append(C)
    return np.stack(poses)


def project(cell: Cell, C: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of target-frame ``points`` (N, 3) seen from T_cam_target ``C``."""
    p = points @ C[:3, :3].T + C[:3, 3]
    uv = p @ cell.K.T
    return uv[:, :2] / uv[:, 2:3]


def robot_poses(cell: Cell, C: np.ndarray) -> np.ndarray:
    """True T_base_tcp (n, 4, 4) that put the camera at T_cam_target ``C`` (n, 4, 4)."""
    return robot_from_camera(C, cell.hand_eye, cell.target_pose, cell.setup)


def pnp_observations(cell: Cell, C: np.ndarray, pixel_noise: float,
                     rng: np.random.Generator, nominal_points: np.ndarray | None = None
                     ) -> np.ndarray:
    """Camera poses (n, 4, 4) estimated by PnP from corners with Gaussian pixel noise.

    ``nominal_points`` (default: the true ones) is the board model the estimator assumes;
    a board of the wrong size shows up as scaled camera translations.
    """
    model = cell.board_points if nominal_points is None else nominal_points
    out = np.empty_like(C)
    for k, Ck in enumerate(C):
        uv = project(cell, Ck, cell.board_points) + rng.normal(0.0, pixel_noise,
                                                                (len(model), 2))
        out[k] = solve_pnp(model, uv, cell.K, guess=Ck)[0]
    return out


def simulate(cell: Cell, n: int, rng: np.random.Generator,
             noise: StationNoise = StationNoise()) -> tuple[np.ndarray, np.ndarray]:
    """Noisy station data: robot readings T_base_tcp and PnP camera poses, each (n, 4, 4)."""
    C_true = sample_camera_poses(cell, n, rng)
    P = perturb(robot_poses(cell, C_true), noise.robot_rot_sigma, noise.robot_trans_sigma, rng)
    C = (pnp_observations(cell, C_true, noise.pixel_noise, rng) if noise.pixel_noise > 0
         else C_true)
    return P, C
