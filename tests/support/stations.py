"""Station sets of the simulated cell: rendered images with noisy robot poses, their
detections and calibration, and station-set directories written from them."""

from __future__ import annotations

import json
from dataclasses import replace
from functools import cache

import cv2
import numpy as np

from calib.boards import Checkerboard, Detection, detect_checkerboard
from calib.geometry import perturb, ur_pose_from_matrix
from calib.options import SolverOptions
from calib.pipeline import StationInputs, calibrate_stations
from mocks.render import render_board
from mocks.scene import Noise, camera_pose_for_tcp, default_scene, sample_station_poses

#: The default cell with the robot noise of Strobl & Hirzinger's simulations (0.05 deg, 0.25 mm).
SCENE = default_scene().model_copy(update={"noise": Noise(
    robot_rot_deg=0.05, robot_trans_mm=0.25, image_noise=2.0, blur_px=0.7)})
BOARD = tuple(SCENE.target.inner_corners)
SQUARE = SCENE.target.square_size_m
SIZE = tuple(SCENE.camera.image_size)


@cache
def rendered_stations(n: int = 15, seed: int = 5) -> tuple[list[np.ndarray], list[list[float]]]:
    """n rendered images of the default scene (κ = 1.005, ν = 0.9975) and noisy tcp poses."""
    rng = np.random.default_rng(seed)
    P_true = sample_station_poses(SCENE, n, rng)
    images = [render_board(SCENE, C, rng=np.random.default_rng(seed + k))
              for k, C in enumerate(camera_pose_for_tcp(SCENE, P_true))]
    noise = SCENE.noise
    P = perturb(P_true, np.deg2rad(noise.robot_rot_deg), noise.robot_trans_mm * 1e-3, rng)
    return images, ur_pose_from_matrix(P).tolist()


@cache
def detections(n: int = 15, seed: int = 5) -> list[Detection]:
    return [detect_checkerboard(im, BOARD) for im in rendered_stations(n, seed)[0]]


TARGET = Checkerboard(BOARD, SQUARE)


def calibrate_set(inputs: StationInputs, board: Checkerboard = TARGET, **options):
    """``calibrate_stations`` with the options (and ``setup``) as plain arguments."""
    if "setup" in options:
        inputs = replace(inputs, setup=options.pop("setup"))
    return calibrate_stations(inputs, board, SolverOptions(**options))


def calibrate(observations, poses, *, intrinsics=None, **options):
    """``calibrate_set`` on the default board and image size."""
    return calibrate_set(StationInputs(observations, poses, image_size=SIZE,
                                       intrinsics=intrinsics), **options)


#: Stations in a station set that ``write_image_set`` writes by default.
N_IMAGES = 12


def halved(image: np.ndarray) -> np.ndarray:
    """``image`` at half its width and height: the board's grid still reads, and a search for
    a board of another size (one that is not there) costs a quarter to a third."""
    return cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)


def write_image_set(path, *, intrinsics=None, inner_corners=BOARD, n=N_IMAGES, half=False):
    """Station set of n rendered images (PNG, the first two JPEG; ``half``: ``halved``) with
    noisy tcp poses."""
    images, poses = rendered_stations()
    path.mkdir(parents=True, exist_ok=True)
    stations = []
    for k in range(n):
        name = f"{k:03d}.{'jpg' if k < 2 else 'png'}"
        cv2.imwrite(str(path / name), halved(images[k]) if half else images[k])
        stations.append({"id": f"{k:03d}", "tcp_pose": poses[k], "image": name})
    doc = {"format": "cellcal/stations@1", "setup": "eye_in_hand",
           "target": {"type": "checkerboard", "inner_corners": list(inner_corners),
                      "square_size_m": SQUARE},
           "stations": stations}
    if intrinsics:
        doc["intrinsics"] = intrinsics
    (path / "stations.json").write_text(json.dumps(doc))
    return path


def write_station_set(path, P, C, *, setup="eye_in_hand", mutate=None):
    doc = {"format": "cellcal/stations@1", "setup": setup,
           "stations": [{"id": f"{k:03d}", "tcp_pose": ur_pose_from_matrix(P[k]).tolist(),
                         "target_pose": ur_pose_from_matrix(C[k]).tolist()}
                        for k in range(len(P))]}
    if mutate:
        mutate(doc)
    path.mkdir(parents=True, exist_ok=True)
    (path / "stations.json").write_text(json.dumps(doc))
    return path
