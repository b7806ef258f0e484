"""Projected corners (no images) of the mock scene with a chosen board scale κ and noisy
robot poses, and their calibration: quick, exact inputs for the model-selection tests."""

from __future__ import annotations

from functools import cache

import numpy as np

from calib import (
    Checkerboard,
    Pinhole,
    SolverOptions,
    StationInputs,
    perturb,
    ur_pose_from_matrix,
)
from calib.pipeline import calibrate_stations
from mocks.scene import Noise, Target, camera_pose_for_tcp, default_scene, sample_station_poses

ROT, TRANS = np.deg2rad(0.05), 0.25e-3
BOARD = Checkerboard((11, 8), 0.03)


def scene(kappa: float = 1.0, nu: float = 1.0):
    s = default_scene()
    return s.model_copy(update={
        "target": Target(inner_corners=(11, 8), square_size_m=0.03, kappa=kappa, nu=nu),
        "noise": Noise(robot_rot_deg=0.05, robot_trans_mm=0.25)})


@cache
def stations(kappa: float = 1.0, n: int = 16, seed: int = 3, pixel_noise: float = 0.15):
    """Corners (projected, Gaussian noise) and noisy tcp poses of a scene with this κ."""
    sc = scene(kappa)
    rng = np.random.default_rng(seed)
    P_true = sample_station_poses(sc, n, rng)
    grid = sc.true_board_points()
    cam = sc.camera
    corners = [Pinhole(cam.k_matrix, cam.dist_coeffs).project(grid @ C[:3, :3].T + C[:3, 3])
               + rng.normal(0.0, pixel_noise, (len(grid), 2))
               for C in camera_pose_for_tcp(sc, P_true)]
    P = perturb(P_true, ROT, TRANS, rng)
    return corners, ur_pose_from_matrix(P).tolist()


def calibrate(true_kappa: float = 1.0, setup: str = "eye_in_hand", **options):
    corners, poses = stations(true_kappa)
    sc = scene(true_kappa)
    return calibrate_stations(
        StationInputs(corners, poses, image_size=tuple(sc.camera.image_size), setup=setup),
        BOARD, SolverOptions(**options))
