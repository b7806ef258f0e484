"""Thousands of stations (issue 11): bounded motion pairs, memory independent of n squared.

20,000 pose-only stations used to die in a 23.8 GiB allocation (every station pair was formed,
by SM and inside OpenCV); here they go through ``cellcal calibrate`` in a subprocess.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.chain import MAX_MOTION_PAIRS, spread_pairs
from calib.geometry import invert, make_transform, perturb, pose_error, ur_pose_from_matrix
from mocks.posesim import Cell, default_cell, robot_poses
from tests.support.cli import MEMORY_LIMIT, run_cli


def test_small_sets_use_every_pair():
    for n in (3, 12, 200):
        i, j = spread_pairs(n)
        ref_i, ref_j = np.triu_indices(n, 1)
        assert np.array_equal(i, ref_i) and np.array_equal(j, ref_j)


@pytest.mark.parametrize("n", [201, 1000, 20_000, 100_000])
def test_large_sets_get_a_bounded_spread_of_pairs(n):
    i, j = spread_pairs(n)
    assert 0 < len(i) <= MAX_MOTION_PAIRS and len(i) == len(j)
    assert (i < j).all() and (i >= 0).all() and (j < n).all()
    assert len(set(zip(i.tolist(), j.tolist(), strict=True))) == len(i)  # no pair twice
    assert len(i) > 0.9 * min(MAX_MOTION_PAIRS, n)  # few draws lost to duplicates
    used = np.count_nonzero(np.bincount(np.concatenate([i, j]), minlength=n))
    assert used >= min(n, MAX_MOTION_PAIRS)  # every station (or one per pair) takes part
    # partners near and far alike: the gap |a - b| of two uniform draws has the quantiles
    # 1 - sqrt(1 - q) (times n)
    q = np.array([0.1, 0.5, 0.9])
    assert np.quantile(j - i, q) == pytest.approx((1 - np.sqrt(1 - q)) * n, abs=0.03 * n)


def random_views(cell: Cell, n: int, rng: np.random.Generator) -> np.ndarray:
    """cam_T_target (n, 4, 4): the camera 0.35-0.6 m from the board centre, looking at it,
    tilted up to 35 deg about a random axis with a random roll (``sample_camera_poses``
    without its in-view check, vectorised: 20,000 views in milliseconds)."""
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    tilt = np.deg2rad(35.0) * np.sqrt(rng.uniform(size=n))
    axis = np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(n)], axis=1)
    roll = np.outer(rng.uniform(-np.pi, np.pi, n), [0.0, 0.0, 1.0])
    R_target_cam = (Rotation.from_rotvec(axis * tilt[:, None])
                    * Rotation.from_rotvec(roll)).as_matrix()
    centre = cell.board_points.mean(axis=0)
    position = centre - rng.uniform(0.35, 0.6, (n, 1)) * R_target_cam[:, :, 2]
    return invert(make_transform(R_target_cam, position))


# OpenCV's Tsai (capped at 200 stations) takes as long as SM: the slow suite runs it.
@pytest.mark.parametrize("method", ["sm", pytest.param("tsai", marks=pytest.mark.slow)])
def test_twenty_thousand_pose_only_stations(tmp_path, method):
    n = 20_000
    cell = default_cell("eye_in_hand")
    rng = np.random.default_rng(11)
    C_true = random_views(cell, n, rng)
    P = perturb(robot_poses(cell, C_true), np.deg2rad(0.05), 0.25e-3, rng)
    C = perturb(C_true, np.deg2rad(0.02), 0.2e-3, rng)
    d = tmp_path / "set"
    d.mkdir()
    doc = {"format": "cellcal/stations@1", "setup": "eye_in_hand",
           "stations": [{"id": f"{k:05d}", "tcp_pose": p, "target_pose": c} for k, (p, c) in
                        enumerate(zip(ur_pose_from_matrix(P).tolist(),
                                      ur_pose_from_matrix(C).tolist(), strict=True))]}
    (d / "stations.json").write_text(json.dumps(doc))
    out = tmp_path / "result.json"
    code, _, stderr, peak = run_cli("calibrate", str(d), "--method", method, "--out", str(out))
    assert code == 0, stderr
    result = json.loads(out.read_text())
    assert len(result["stations"]) == n
    assert result["motions"]["used"] + result["motions"]["skipped"] <= MAX_MOTION_PAIRS
    rot, trans = pose_error(np.array(result["hand_eye"]["matrix"]), cell.hand_eye)
    assert rot < np.deg2rad(0.05) and trans < 1e-3
    assert peak < MEMORY_LIMIT, f"peak RSS {peak / 1e6:.0f} MB"
