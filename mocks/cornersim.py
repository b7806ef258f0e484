"""Corner-level simulation of a mock scene, kinematic errors included, without rendering.

What a cell records when its arm has systematic errors (``MockScene.kinematics``): the board's
corners seen from the *true* flange poses, with Gaussian pixel noise, and the *nominal*
(commanded) poses with the scene's reading noise. Used by the uncertainty benchmark and the
tests of model selection and σ on such arms.
"""

from __future__ import annotations

import numpy as np

from calib import Pinhole, perturb, ur_pose_from_matrix
from mocks.scene import MockScene, camera_pose_for_tcp, sample_station_poses, true_tcp_pose


def simulate_corners(scene: MockScene, n: int, rng: np.random.Generator,
                     pixel_noise: float = 0.15) -> tuple[list[np.ndarray], list[list[float]]]:
    """``n`` stations the arm reaches: corners (N, 2) per station and UR tcp poses (6,)."""
    P_cmd, P_true = [], []
    while len(P_cmd) < n:  # keep the stations the UR5e reaches
        for P in sample_station_poses(scene, n, rng):
            try:
                P_true.append(true_tcp_pose(scene, P))
            except ValueError:
                continue
            P_cmd.append(P)
    P_cmd, P_true = np.array(P_cmd[:n]), np.array(P_true[:n])
    grid = scene.true_board_points()
    cam = scene.camera
    pinhole = Pinhole(cam.k_matrix, cam.dist_coeffs)
    corners = [pinhole.project(grid @ C[:3, :3].T + C[:3, 3])
               + rng.normal(0.0, pixel_noise, (len(grid), 2))
               for C in camera_pose_for_tcp(scene, P_true)]
    noise = scene.noise
    P = perturb(P_cmd, np.deg2rad(noise.robot_rot_deg), noise.robot_trans_mm * 1e-3, rng)
    return corners, ur_pose_from_matrix(P).tolist()
