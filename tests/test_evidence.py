"""Cross-validation, model selection, honest uncertainty and the verdict (issue 8, product.md
"Trust"), on projected corners of the mock scene and on the real UR sets."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from calib import (
    CornerStations,
    JointOptions,
    RobotNoise,
    StationInputs,
    matrix_from_ur_pose,
    solve_joint,
    ur_pose_from_matrix,
)
from calib.crossval import FoldEstimate, fold_indices
from calib.jointfit import JointData, JointModel, fit_joint
from calib.pipeline import calibrate_stations
from calib.uncertainty import JACKKNIFE_NOISE, UncertaintyEstimate, with_held_shift
from service.cli.main import main
from service.results.document import calibration_result
from tests.support.helpers import SHARED
from tests.support.projected import BOARD, calibrate, scene, stations

UR_SETS = [SHARED / "data" / name for name in ("ur-kinect-highR_highT", "ur-kinect-lowR_highT")]


def test_folds_are_interleaved_and_leave_one_out_below_ten():
    five = fold_indices(23)
    assert len(five) == 5 and sorted(np.concatenate(five).tolist()) == list(range(23))
    assert five[1].tolist() == [1, 6, 11, 16, 21]
    assert [f.tolist() for f in fold_indices(7)] == [[k] for k in range(7)]


def test_block_solver_reaches_the_minimum_of_solve_joint():
    res = calibrate(true_kappa=1.004)
    corners, poses = stations(1.004)
    P = matrix_from_ur_pose(np.array(poses))
    train = np.arange(0, 16, 2)
    data = JointData(CornerStations(corners, P, BOARD), "eye_in_hand", res.sigma_px)
    start = res.trust.model_selection.chosen.fit.cell
    fast = fit_joint(data.subset(train), JointModel("all", (), RobotNoise()), start)
    ref = solve_joint(CornerStations([corners[i] for i in train], P[train], BOARD), start,
                      JointOptions(sigma_px=res.sigma_px, outlier_sigma=None))
    assert fast.solution.converged and ref.converged
    assert abs(fast.cell.kappa - ref.kappa) < 1e-7
    assert np.abs(fast.cell.hand_eye - ref.hand_eye).max() < 1e-7


@pytest.fixture(scope="module")
def nominal():
    """The projected scene's calibration with its exact board (one for the module's tests)."""
    return calibrate(true_kappa=1.0)


def test_nominal_board_passes_with_kappa_held_and_cross_validation_in_the_result(nominal):
    res = nominal
    trust = res.trust
    cv = trust.cross_validation
    assert cv.kind == "k-fold" and cv.folds == 5 and len(cv.stations) == 16
    # held-out prediction error is dominated by the robot noise: about 0.25 mm at the board
    assert 0.05e-3 < cv.rms_m < 1.5e-3 and cv.rms_px > 0.15
    assert trust.quality.verdict == "pass", trust.quality.findings
    assert "kappa" in trust.model_selection.chosen.model.fix and res.kappa == 1.0
    names = [c.model.name for c in trust.model_selection.candidates]
    assert {"all estimated", "kappa = 1", "nu = 1", "robot noise estimated"} <= set(names)


def test_oversized_board_warns_with_the_measured_square_size():
    res = calibrate(true_kappa=1.08)
    assert abs(res.kappa - 1.08) < 0.002
    found = {f.code: f for f in res.trust.quality.findings}
    assert res.trust.quality.verdict == "warn"
    assert re.search(r"squares measure 32\.[34]\d mm", found["board_scale"].message)
    assert abs(found["board_scale"].values["measured_square_size_m"] - 0.0324) < 1e-4
    fixed = calibrate(true_kappa=1.08, kappa="fixed")
    assert fixed.kappa == 1.0 and "board_scale" not in {f.code for f in
                                                          fixed.trust.quality.findings}
    assert fixed.trust.cross_validation.rms_px > 3 * res.trust.cross_validation.rms_px


def test_a_skewed_robot_gets_its_translation_map_and_a_plain_one_does_not(nominal):
    """Readings whose translations are skewed by 0.3-0.4 % (an industrial arm's positions
    through a linear distortion): the map predicts held-out stations clearly better, is
    chosen and found; on the plain robot (the nominal-board test above) it is not chosen."""
    corners, poses = stations(1.0)
    S = np.array([[0.0, 3e-3, -4e-3], [-2e-3, 0.0, 3e-3], [4e-3, -3e-3, 0.0]])
    P_true = matrix_from_ur_pose(np.array(poses))
    read = P_true.copy()
    read[:, :3, 3] = np.linalg.solve(np.eye(3) + S, P_true[:, :3, 3].T).T  # t_true = t + S t
    res = calibrate_stations(StationInputs(corners, ur_pose_from_matrix(read).tolist(),
                                           image_size=tuple(scene().camera.image_size)), BOARD)
    chosen = res.trust.model_selection.chosen
    assert chosen.model.robot_map and res.robot_map is not None
    assert np.abs(res.robot_map - S).max() < 2e-3  # 16 stations, 0.25 mm reading noise
    plain = next(c for c in res.trust.model_selection.candidates if c.name == "all estimated")
    assert res.trust.cross_validation.rms_px < 0.5 * plain.cv.rms_px
    (found,) = [f for f in res.trust.quality.findings if f.code == "robot_translation_map"]
    assert found.severity == "info" and 1e-3 < found.values["largest_shift_m"] < 10e-3
    assert not nominal.trust.model_selection.chosen.model.robot_map


def test_wrong_setup_fails_with_setup_mismatch():
    res = calibrate(true_kappa=1.0, setup="eye_to_hand")
    assert res.trust.quality.verdict == "fail"
    assert [f.code for f in res.trust.quality.findings] == ["setup_mismatch"]


def test_reported_sigma_is_never_below_the_fold_jackknife_beyond_its_noise(nominal):
    """Vectors compare as a block (root-sum-square of their components), scalars directly;
    the jackknife debiased for its fold design by what the noise model expects of it."""
    u = nominal.trust.uncertainty
    assert u.folds == 5 and set(u.source) >= {"hand_eye_rot_rad", "hand_eye_trans_m"}
    assert set(u.expected) == set(u.source)
    for name, jk in u.jackknife.items():
        if name in u.source:
            # without the bias of a parameter held at 1 (tests below)
            reported = np.sqrt(np.asarray(u.sigmas[name]) ** 2 - u.bias.get(name, 0.0) ** 2)
            formal = np.asarray(u.formal[name])
            debiased = np.linalg.norm(jk) * np.linalg.norm(formal) / np.linalg.norm(
                u.expected[name])
            assert np.linalg.norm(reported) * JACKKNIFE_NOISE >= debiased * (1 - 1e-12)
            assert np.linalg.norm(reported) >= np.linalg.norm(formal) * (1 - 1e-12)
            if np.ndim(formal):  # the formal shape, at most scaled
                assert np.allclose(reported / np.linalg.norm(reported),
                                   formal / np.linalg.norm(formal))
    assert "jackknife" in u.note


def test_poses_held_kappa_would_move_are_in_their_sigma(nominal):
    """κ (and ν) held at 1 by the selection are not known to be 1: the poses' σ include the
    bias the shift to the same model estimating them (the 'all estimated' candidate) shows
    beyond its noise, in quadrature."""
    res = nominal
    u, selection = res.trust.uncertainty, res.trust.model_selection
    assert "kappa" in u.held and set(u.held) <= set(selection.chosen.model.fix)
    freed = next(c.fit.cell for c in selection.candidates if c.model.name == "all estimated")
    shift_t = np.abs(freed.hand_eye[:3, 3] - res.hand_eye[:3, 3])
    assert np.allclose(u.shift["hand_eye_trans_m"], shift_t) and shift_t.max() > 1e-6
    bias = u.bias["hand_eye_trans_m"]
    assert np.all(bias <= shift_t)
    before = np.sqrt(u.sigmas["hand_eye_trans_m"] ** 2 - bias ** 2)
    assert np.all(before >= u.formal["hand_eye_trans_m"] * (1 - 1e-9))
    assert "held at 1 by the model selection" in u.note
    document = calibration_result(res).uncertainty
    assert document.held_at_one == list(u.held)
    assert np.allclose(document.held_shift["hand_eye_trans_m"], shift_t)
    assert np.allclose(document.held_bias["hand_eye_trans_m"], bias)


def test_a_held_shift_within_its_noise_adds_nothing_and_beyond_it_its_shrunk_excess():
    """``with_held_shift``: a pose's 3-vector shift d is tested as one, Hausman's statistic
    ``T = Σ d² / v`` (v = σ_f² - σ_h², 0.09 mm² here) against χ²₃ at 95 % (7.81); beyond it
    each axis adds ``(1 - 7.81 / T) max(0, d² - v)`` to σ², within it nothing."""
    X, X_f = np.eye(4), np.eye(4)
    X_f[:3, 3] = [1e-3, 0.1e-3, 0.5e-3]
    sigma_h, sigma_f = np.full(3, 0.2e-3), np.full(3, np.hypot(0.2e-3, 0.3e-3))
    est = UncertaintyEstimate(sigmas={"hand_eye_trans_m": sigma_h}, formal={}, jackknife={},
                              source={}, folds=0)

    def shifted(d: list[float]) -> UncertaintyEstimate:
        X_f[:3, 3] = d
        return with_held_shift(est, ["kappa"],
                               (FoldEstimate(X, X, 1.0), {"hand_eye_trans_m": sigma_h}),
                               (FoldEstimate(X_f, X, 1.001), {"hand_eye_trans_m": sigma_f}))

    out = shifted([1e-3, 0.1e-3, 0.5e-3])
    T = (1e-6 + 0.01e-6 + 0.25e-6) / 0.09e-6
    keep = 1.0 - 7.8147 / T
    expected_bias = np.sqrt(keep * np.array([1e-6 - 0.09e-6, 0.0, 0.25e-6 - 0.09e-6]))
    assert np.allclose(out.bias["hand_eye_trans_m"], expected_bias, rtol=1e-4)
    assert np.allclose(out.sigmas["hand_eye_trans_m"], np.hypot(sigma_h, expected_bias))
    assert np.allclose(out.shift["hand_eye_trans_m"], [1e-3, 0.1e-3, 0.5e-3])
    # one axis beyond 1.96 times its noise, the vector within χ²₃ (T = 4): no bias (a test
    # per axis added 0.52 mm)
    within = shifted([0.6e-3, 0.0, 0.0])
    assert 0.6e-3 > 1.96 * 0.3e-3 and np.all(within.bias["hand_eye_trans_m"] == 0.0)
    # no jump at the threshold: just beyond it the bias is a tenth of the unshrunk excess
    edge = np.sqrt(7.8147 * 0.09e-6 / 3) * 1.001
    excess = np.sqrt(3 * (edge ** 2 - 0.09e-6))
    assert np.linalg.norm(shifted([edge] * 3).bias["hand_eye_trans_m"]) < 0.1 * excess
    assert with_held_shift(est, [], (None, {}), (None, {})) is est


def test_an_axis_the_held_parameter_does_not_inform_carries_no_bias():
    """Where freeing the parameter costs no precision (σ_f <= σ_h on an axis, Hausman's noise
    variance <= 0) the axis is left out of the test and adds nothing; the others are tested
    over their own degrees of freedom (χ²₁ here: one axis left)."""
    X, X_f = np.eye(4), np.eye(4)
    X_f[:3, 3] = [1e-3, 1e-3, 0.0]
    sigma_h = np.full(3, 0.2e-3)
    sigma_f = np.array([np.hypot(0.2e-3, 0.3e-3), 0.2e-3, 0.19e-3])
    est = UncertaintyEstimate(sigmas={"hand_eye_trans_m": sigma_h}, formal={}, jackknife={},
                              source={}, folds=0)
    out = with_held_shift(est, ["kappa"],
                          (FoldEstimate(X, X, 1.0), {"hand_eye_trans_m": sigma_h}),
                          (FoldEstimate(X_f, X, 1.001), {"hand_eye_trans_m": sigma_f}))
    T = 1e-6 / 0.09e-6
    keep = 1.0 - 3.8415 / T
    assert np.allclose(out.bias["hand_eye_trans_m"],
                       [np.sqrt(keep * (1e-6 - 0.09e-6)), 0.0, 0.0], rtol=1e-4)
    assert np.all(np.isfinite(out.sigmas["hand_eye_trans_m"]))


@pytest.mark.parametrize("directory", UR_SETS, ids=lambda p: p.name)
def test_real_ur_set_warns_about_a_33_mm_board(tmp_path, capsys, directory):
    out = tmp_path / "r.json"
    assert main(["calibrate", str(directory), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    found = {f["code"]: f for f in doc["quality"]["findings"]}
    assert doc["quality"]["verdict"] == "warn"
    assert abs(found["board_scale"]["measured_square_size_m"] - 0.033) < 0.0005
    assert "verdict warn" in capsys.readouterr().err
    cv = doc["cross_validation"]
    assert cv["folds"] == 5 and len(cv["stations"]) == 21 and cv["rms_px"] < 8.0


def test_wrong_setup_on_a_real_set_exits_3_and_still_writes(tmp_path, capsys):
    src = json.loads((UR_SETS[0] / "stations.json").read_text())
    src["setup"] = "eye_to_hand"
    for s in src["stations"]:
        shutil.copy(UR_SETS[0] / s["image"], tmp_path / s["image"])
    (tmp_path / "stations.json").write_text(json.dumps(src))
    out = tmp_path / "r.json"
    assert main(["calibrate", str(tmp_path), "--out", str(out)]) == 3
    doc = json.loads(out.read_text())
    assert doc["quality"]["verdict"] == "fail"
    assert doc["quality"]["findings"][0]["code"] == "setup_mismatch"
    assert "verdict fail" in capsys.readouterr().err
