"""Partial views through the whole pipeline: a ChArUco board (κ 1.004, ν 0.998) seen whole
at some stations and cut by the image border at others, corners with their point ids."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from calib import (
    Charuco,
    Detection,
    Pinhole,
    SolverOptions,
    StationInputs,
    image_corner_error,
    make_transform,
    perturb,
    pose_error,
    ur_pose_from_matrix,
)
from calib.pipeline import calibrate_stations
from calib.stations import MIN_STATION_POINTS
from mocks.posesim import ViewSpread, default_cell, robot_poses, sample_camera_poses

BOARD = Charuco((12, 9), 0.03, 0.022, "DICT_5X5_100")
KAPPA, NU = 1.004, 0.998
DIST = np.array([-0.12, 0.08, 0.0005, -0.0003, 0.0])
SIGMA_PX = 0.1
#: Directions (image x, y) in which the cut stations are pushed: corners first, then edges.
_SIDES = [(1, 1), (-1, 1), (-1, -1), (1, -1), (1, 0), (0, 1), (-1, 0), (0, -1)]


@cache
def station_set(n: int = 15, seed: int = 3, cut: bool = True
                ) -> tuple[list[Detection], np.ndarray, object]:
    """``n`` stations, every other one (``cut``) shifted so the board runs off an image
    corner or edge (only the corners inside the image kept), plus one that sees too few
    corners; noisy tcp poses."""
    rng = np.random.default_rng(seed)
    cell = default_cell()
    cell = type(cell)(cell.setup, cell.hand_eye, cell.target_pose,
                      BOARD.points(kappa=KAPPA, nu=NU))
    camera = Pinhole(cell.K, DIST)
    w, h = cell.image_size
    C = sample_camera_poses(cell, n, rng, ViewSpread(distance=(0.6, 0.9)))
    for k in range(1, n, 2) if cut else ():  # push the board over an image corner or edge
        depth = (BOARD.points() @ C[k][:3, :3].T + C[k][:3, 3])[:, 2].mean()
        side = np.array(_SIDES[k // 2])
        shift_px = side * np.array([0.45 * w, 0.45 * h]) * (0.9 if side.all() else 1.0)
        C[k] = make_transform(np.eye(3), [*(shift_px * depth / cell.K[0, 0]), 0.0]) @ C[k]
    C = np.concatenate([C, make_transform(np.eye(3), [0.62 * C[0][2, 3], 0.5 * C[0][2, 3],
                                                      0.0])[None] @ C[:1]])
    detections = []
    for Ck in C:
        uv = camera.project(cell.board_points @ Ck[:3, :3].T + Ck[:3, 3])
        inside = np.flatnonzero(((uv > 3) & (uv < [w - 4, h - 4])).all(axis=1))
        detections.append(Detection(ok=True, corners=uv[inside] + rng.normal(
            0.0, SIGMA_PX, (len(inside), 2)), ids=inside))
    P = perturb(robot_poses(cell, C), np.deg2rad(0.02), 0.1e-3, rng)
    return detections, ur_pose_from_matrix(P), cell


def test_station_set_has_the_intended_views():
    detections, _, _ = station_set()
    counts = np.array([len(d.ids) for d in detections])
    n_all = len(BOARD.point_ids)
    assert (counts[:-1:2] == n_all).all()
    cut = counts[1:-1:2]
    assert (cut < 0.8 * n_all).all() and (cut >= 0.3 * n_all).all()
    assert 0 < counts[-1] < MIN_STATION_POINTS


def test_partial_views_calibrate_kappa_nu_and_hand_eye():
    detections, poses, cell = station_set()
    res = calibrate_stations(StationInputs(detections, poses, image_size=cell.image_size),
                             BOARD, SolverOptions(kappa="estimate"))
    assert res.rejected == (("015", f"only {len(detections[-1].ids)} board points usable, at "
                             f"least {MIN_STATION_POINTS} not on one line are needed"),)
    assert len(res.stations) == 15
    assert abs(res.nu - NU) < max(3 * res.sigmas["nu"], 5e-5) and res.sigmas["nu"] < 1e-4
    assert abs(res.kappa - KAPPA) < max(3 * res.sigmas["kappa"], 2e-4)
    rot, trans = pose_error(res.hand_eye, cell.hand_eye)
    assert trans < 4 * np.linalg.norm(res.sigmas["hand_eye_trans_m"]) and trans < 1e-3
    assert rot < 4 * np.linalg.norm(res.sigmas["hand_eye_rot_rad"]) and rot < np.deg2rad(0.05)
    # every report keeps its station's ids, and the residuals are at the corner noise
    for report, det in zip(res.stations, detections, strict=False):
        assert np.array_equal(report.point_ids, det.ids)
        assert np.shape(report.residuals_px) == (len(det.ids), 2)
        assert report.rms_px < 3 * SIGMA_PX


def test_partial_views_with_known_intrinsics_and_intrinsics_only():
    detections, poses, cell = station_set()
    known = calibrate_stations(
        StationInputs(detections, poses, image_size=cell.image_size,
                      intrinsics=(cell.K, DIST)), BOARD, SolverOptions(kappa="estimate"))
    assert np.array_equal(known.K, cell.K) and abs(known.nu - NU) < 3 * known.sigmas["nu"]
    trans = pose_error(known.hand_eye, cell.hand_eye)[1]
    assert trans < 4 * np.linalg.norm(known.sigmas["hand_eye_trans_m"]) and trans < 1e-3
    alone = calibrate_stations(StationInputs(detections, image_size=cell.image_size), BOARD)
    assert alone.method == "intrinsics" and abs(alone.nu - NU) < 2e-4
    assert [len(s.point_ids) for s in alone.stations] == [len(d.ids) for d in detections[:-1]]
    # views cut at the image border pin the distortion down where it is largest: the image
    # corners project better than from the same number of whole-board views
    full = station_set(cut=False)[0]
    whole = calibrate_stations(StationInputs(full, image_size=cell.image_size), BOARD)
    truth = Pinhole(cell.K, DIST)
    partial_err = image_corner_error(Pinhole(alone.K, alone.dist), truth, cell.image_size)
    whole_err = image_corner_error(Pinhole(whole.K, whole.dist), truth, cell.image_size)
    assert partial_err * 1.5 < whole_err, (partial_err, whole_err)


def test_point_ids_off_the_board_are_rejected_with_a_reason():
    detections, poses, cell = station_set()
    bad = Detection(ok=True, corners=detections[0].corners, ids=detections[0].ids + 5)
    with pytest.raises(ValueError, match=r"distinct board points 0\.\.87"):
        calibrate_stations(StationInputs([bad, *detections[1:3]], poses[:3],
                                         image_size=cell.image_size), BOARD)
