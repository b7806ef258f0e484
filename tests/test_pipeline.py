"""From rendered images and noisy robot poses to a calibration: accuracy, options, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boards import Checkerboard, Detection, board_points
from calib.camera import Pinhole
from calib.geometry import perturb, pose_error, ur_pose_from_matrix
from calib.pipeline import StationInputs
from mocks.posesim import default_cell, robot_poses, sample_camera_poses
from tests.support.stations import (
    BOARD,
    SCENE,
    SIZE,
    SQUARE,
    calibrate,
    calibrate_set,
    detections,
    halved,
    rendered_stations,
)


def test_joint_recovers_nu_and_kappa_and_beats_the_nominal_pipeline():
    poses = rendered_stations()[1]
    # κ estimation itself is under test: the default (auto) estimates κ only when that predicts
    # held-out stations clearly better (tests/test_evidence.py)
    joint = calibrate(detections(), poses, kappa="estimate")
    assert joint.method == "joint" and joint.rejected == ()
    assert abs(joint.nu - SCENE.target.nu) < 3 * joint.sigmas["nu"]
    assert abs(joint.kappa - SCENE.target.kappa) < 3 * joint.sigmas["kappa"]
    assert joint.sigmas["kappa"] < 2e-3 and joint.sigmas["nu"] < 1e-4
    assert 0.5 < joint.variance_factor < 2.0
    nominal = calibrate(detections(), poses, estimate_nu=False, estimate_kappa=False)
    assert nominal.nu == 1.0 and nominal.kappa == 1.0
    _, t_joint = pose_error(joint.hand_eye, SCENE.hand_eye_matrix)
    _, t_nominal = pose_error(nominal.hand_eye, SCENE.hand_eye_matrix)
    assert t_joint < 0.3e-3
    assert t_nominal > 4 * t_joint, (t_nominal, t_joint)
    # the reported uncertainty covers the actual error
    sd = np.linalg.norm(joint.sigmas["hand_eye_trans_m"])
    assert t_joint < 4 * sd
    v = joint.validation
    assert v["n_motions"] > 50 and v["E_R"] < 1e-2 and v["E_t"] < 1e-3
    assert v["loo_solver"] == "sm" and v["loo_trans_m_mean"] < 2e-3
    assert len(joint.stations) == 15 and all(s.rms_px < 0.2 for s in joint.stations)
    assert all(s.chain_rms_px > s.rms_px for s in joint.stations)


def test_images_are_detected_and_unusable_ones_rejected_with_reasons():
    images, poses = rendered_stations()
    blank = np.full(SIZE[::-1], 110, np.uint8)
    clutter = np.random.default_rng(0).integers(0, 256, SIZE[::-1], dtype=np.uint8)
    unread = Detection(ok=False, reason="cannot read image file 'x.png'")
    obs = [*images[:10], blank, clutter, unread]
    ids = [f"s{k}" for k in range(len(obs))]
    res = calibrate_set(StationInputs(obs, [*poses[:10], *poses[10:13]], ids=ids),
                        kappa="estimate")
    reasons = dict(res.rejected)
    assert list(reasons) == ["s10", "s11", "s12"]
    assert "blank" in reasons["s10"] and "board not found" in reasons["s11"]
    assert reasons["s12"] == "cannot read image file 'x.png'"
    assert res.image_size == SIZE and [s.id for s in res.stations] == ids[:10]
    assert abs(res.kappa - SCENE.target.kappa) < 4 * res.sigmas["kappa"]


def test_all_images_rejected_is_a_clear_error():
    blank = np.full(SIZE[::-1], 110, np.uint8)
    with pytest.raises(ValueError, match=r"only 0 of 3 stations usable, need at least 3 "
                                         r"\(000: image is blank"):
        calibrate_set(StationInputs([blank] * 3, None))


def test_wrong_inner_corners_says_what_is_visible():
    images, poses = rendered_stations()
    with pytest.raises(ValueError, match=r"only 0 of 3 stations usable.*a larger 11x8 grid "
                                         r"is visible: check inner_corners"):
        calibrate_set(StationInputs([halved(im) for im in images[:3]], poses[:3]),
                      Checkerboard((10, 8), SQUARE))


def test_corrupted_robot_pose_is_rejected_with_its_reason():
    poses = [list(p) for p in rendered_stations()[1]]
    poses[3][0] += 4e-3
    res = calibrate(detections(), poses, kappa="estimate")
    assert [i for i, _ in res.rejected] == ["003"]
    assert "robot pose inconsistent with the image" in res.rejected[0][1]
    assert "003" not in [s.id for s in res.stations]
    assert pose_error(res.hand_eye, SCENE.hand_eye_matrix)[1] < 0.3e-3
    # the cross-validated figure covers the dropped station too, predicted by fold 3 mod 5
    cv = res.trust.cross_validation
    assert [s.id for s in cv.stations] == [f"{k:03d}" for k in range(15)]
    assert cv.dropped == ("003",)
    held = cv.stations[3]
    assert held.dropped and held.fold == 3 and held.rms_px > 5 * cv.kept().rms_px
    assert cv.kept().rms_px < cv.rms_px
    assert len(cv.kept().stations) == 14 and not any(s.dropped for s in cv.kept().stations)


def test_intrinsics_only_without_robot_poses():
    res = calibrate(detections(), None)
    assert res.method == "intrinsics" and res.hand_eye is None and res.target_pose is None
    assert abs(res.nu - SCENE.target.nu) < 4 * res.sigmas["nu"]
    assert np.abs(res.K - SCENE.camera.k_matrix).max() < 2.0
    assert res.validation == {} and len(res.stations) == 15


def test_known_intrinsics_are_kept():
    K, dist = SCENE.camera.k_matrix, SCENE.camera.dist_coeffs
    res = calibrate(detections(), rendered_stations()[1], intrinsics=(K, dist),
                    kappa="estimate")
    np.testing.assert_array_equal(res.K, K)
    np.testing.assert_array_equal(res.dist, dist)
    assert res.sigmas["fx"] == 0.0 and res.options["known_intrinsics"]
    assert abs(res.kappa - SCENE.target.kappa) < 4 * res.sigmas["kappa"]
    assert abs(res.nu - SCENE.target.nu) < 4 * res.sigmas["nu"]


@pytest.mark.parametrize("method", ["sm", "park"])
def test_other_hand_eye_methods_use_the_per_image_poses(method):
    res = calibrate(detections(), rendered_stations()[1], method=method)
    assert res.method == method and res.kappa == 1.0 and res.variance_factor is None
    assert "hand_eye_trans_m" not in res.sigmas
    rot, _ = pose_error(res.hand_eye, SCENE.hand_eye_matrix)
    assert rot < np.deg2rad(0.1)


def test_refine_is_the_pose_level_estimate_without_the_joint_stage():
    res = calibrate(detections(), rendered_stations()[1], method="refine")
    assert res.method == "refine" and res.variance_factor is None
    assert res.stations[0].correction_rot_rad is None  # no robot corrections: not joint
    assert res.sigmas["kappa"] > 0 and res.sigmas["hand_eye_trans_m"].shape == (3,)
    assert abs(res.kappa - SCENE.target.kappa) < 4 * res.sigmas["kappa"]
    rot, _ = pose_error(res.hand_eye, SCENE.hand_eye_matrix)
    assert rot < np.deg2rad(0.1)


def test_symmetric_board_origin_is_made_consistent():
    """An 8x6 board looks the same turned by 180 deg; half the detections come out turned."""
    cell = default_cell("eye_in_hand", inner_corners=(8, 6))
    rng = np.random.default_rng(9)
    C = sample_camera_poses(cell, 10, rng)
    pts = board_points((8, 6), 0.03)
    obs = []
    for k, c in enumerate(C):
        uv = Pinhole(cell.K, np.zeros(5)).project(pts @ c[:3, :3].T + c[:3, 3]) \
            + rng.normal(0.0, 0.1, (len(pts), 2))
        obs.append(Detection(ok=True, corners=uv[::-1] if k % 2 else uv, ambiguous=True))
    P = perturb(robot_poses(cell, C), np.deg2rad(0.05), 0.25e-3, rng)
    res = calibrate_set(StationInputs(obs, ur_pose_from_matrix(P).tolist(),
                                      image_size=(1280, 1024)), Checkerboard((8, 6), 0.03))
    assert res.rejected == ()
    rot, trans = pose_error(res.hand_eye, cell.hand_eye)
    assert rot < np.deg2rad(0.05) and trans < 0.5e-3


def test_bad_options_are_named():
    obs = detections()[:3]
    with pytest.raises(ValueError, match="unknown method 'magic'"):
        calibrate(obs, None, method="magic")
    with pytest.raises(ValueError, match="Method #2"):
        calibrate(obs, None, method="sm", nu_method="extrinsics")
    with pytest.raises(ValueError, match="3 observations but 3 station ids and 2 robot poses"):
        calibrate(obs, rendered_stations()[1][:2])
    with pytest.raises(ValueError, match="image_size is required"):
        calibrate_set(StationInputs([d.corners for d in obs], None))
    with pytest.raises(ValueError, match="terms beyond k3 are not supported"):
        calibrate(obs, None, intrinsics=(SCENE.camera.k_matrix, [0, 0, 0, 0, 0, 0.1]))


@pytest.mark.slow
def test_method_2_recovers_nu_from_the_extrinsics():
    res = calibrate(detections(), rendered_stations()[1], nu_method="extrinsics",
                    kappa="estimate")
    assert res.options["nu_method"] == "extrinsics"
    assert abs(res.nu - SCENE.target.nu) < 4 * res.sigmas["nu"] and res.sigmas["nu"] < 2e-4
    assert abs(res.kappa - SCENE.target.kappa) < 4 * res.sigmas["kappa"]


@pytest.mark.parametrize("method", ["joint", "park", None])
def test_stations_carry_their_corners_and_fit_residuals(method):
    """Per-corner residuals (for the report's plots) agree with the per-station RMS and with
    the detections, both kept to 0.001 px; None is the intrinsics-only calibration."""
    poses = None if method is None else rendered_stations()[1]
    res = calibrate(detections(), poses, **({} if method is None else {"method": method}))
    by_id = {f"{k:03d}": d for k, d in enumerate(detections())}
    for s in res.stations:
        np.testing.assert_allclose(s.corners_px, by_id[s.id].corners, rtol=0, atol=5e-4)
        residuals = np.asarray(s.residuals_px)
        assert residuals.shape == (BOARD[0] * BOARD[1], 2)
        rms = np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))
        assert rms == pytest.approx(s.rms_px, abs=5e-4)
        assert 0.0 < rms < 0.2
