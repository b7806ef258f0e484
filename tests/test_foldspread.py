"""The fold jackknife read against its own expectation under the noise model
(``calib.foldspread``, ``calib.uncertainty.honest``; issue 18: a σ neither timid nor bold)."""

from __future__ import annotations

import numpy as np
import pytest

from calib import CornerStations, Pinhole, RobotNoise, matrix_from_ur_pose, perturb
from calib.crossval import FoldEstimate, fold_indices
from calib.joint import CellParameters
from calib.jointfit import JointData, JointModel, fit_joint
from calib.uncertainty import JACKKNIFE_NOISE, honest, jackknife_sigmas
from mocks.scene import camera_pose_for_tcp, sample_station_poses
from tests.support.projected import BOARD, ROT, TRANS, scene, stations

N = 16
#: One fold holds half the stations: its estimate rests on the other half and moves far.
UNBALANCED = [np.arange(0, 16, 2), *(np.arange(k, 16, 8) for k in (1, 3, 5, 7))]
NOISE = RobotNoise(ROT, TRANS)


@pytest.fixture(scope="module")
def fit():
    """The joint fit of the projected scene's 16 stations at their true noise levels."""
    corners, poses = stations(1.0)
    data = JointData(CornerStations(corners, matrix_from_ur_pose(np.array(poses)), BOARD),
                     "eye_in_hand", 0.15)
    return fit_joint(data, JointModel("all", (), NOISE), _truth())


def _truth() -> CellParameters:
    s = scene()
    return CellParameters(s.camera.k_matrix, s.camera.dist_coeffs, 1.0, 1.0,
                          s.hand_eye_matrix, s.target_pose_matrix)


def _size(sigmas: dict, name: str) -> float:
    return float(np.linalg.norm(sigmas[name]))


def test_balanced_folds_expect_the_formal_sigma_and_a_lopsided_design_more(fit):
    """Interleaved folds of a scene where no station dominates: the jackknife is expected at
    about the formal σ. A fold of half the stations leaves an estimate on the other half, so
    the same noise model expects a much wider jackknife (the design's bias, not the data's)."""
    noise = (0.15, ROT, TRANS)
    formal = fit.result(np.arange(N), noise=noise).sigmas
    balanced = fit.expected_jackknife(fold_indices(N), noise=noise)
    lopsided = fit.expected_jackknife(UNBALANCED, noise=noise)
    for name in ("hand_eye_rot_rad", "hand_eye_trans_m", "kappa"):
        assert 0.9 < _size(balanced, name) / _size(formal, name) < 1.25, name
        assert _size(lopsided, name) > 1.05 * _size(balanced, name), name
    for name in ("hand_eye_trans_m", "kappa"):  # what a fold of half the stations moves most
        assert _size(lopsided, name) > 1.15 * _size(balanced, name), name
    assert fit.expected_jackknife(fold_indices(N)[:2], noise=noise) == {}


def test_variance_factors_scale_the_expected_jackknife_like_the_formal_sigma(fit):
    """Corner and robot noise twice as large as assumed: every residual group's variance
    factor is 4, and both figures double."""
    noise, double = (0.15, ROT, TRANS), (0.30, 2 * ROT, 2 * TRANS)
    folds = fold_indices(N)
    base, scaled = (fit.expected_jackknife(folds, noise=n) for n in (noise, double))
    formal, formal2 = (fit.result(np.arange(N), noise=n).sigmas for n in (noise, double))
    for name in ("hand_eye_trans_m", "kappa"):
        assert np.allclose(np.asarray(scaled[name]), 2 * np.asarray(base[name]), rtol=1e-9)
        assert np.allclose(np.asarray(formal2[name]), 2 * np.asarray(formal[name]), rtol=1e-9)


def _estimates(shifts_mm: np.ndarray) -> list[FoldEstimate]:
    """Fold estimates whose hand-eye translations are ``shifts_mm`` (g, 3) from identity."""
    out = []
    for d in shifts_mm:
        X = np.eye(4)
        X[:3, 3] = 1e-3 * d
        out.append(FoldEstimate(hand_eye=X, target_pose=np.eye(4), kappa=1.0))
    return out


def test_the_jackknife_counts_only_beyond_what_the_noise_model_expects_of_it():
    """``honest``: a jackknife twice the formal σ is reported where the noise model expects
    about the formal σ for these folds (or no expectation is given, as before), but not
    where it expects that jackknife (a lopsided fold design): then the formal σ stands."""
    rng = np.random.default_rng(0)
    estimates = _estimates(rng.normal(0.0, 1.0, (5, 3)))
    reference = FoldEstimate(hand_eye=np.eye(4), target_pose=np.eye(4), kappa=1.0)
    jk = jackknife_sigmas(estimates, reference)["hand_eye_trans_m"]
    size_jk = float(np.linalg.norm(jk))
    formal = {"hand_eye_trans_m": np.array([0.3, 0.4, 0.5]) * size_jk / 2.0 / np.sqrt(0.5)}
    assert np.isclose(np.linalg.norm(formal["hand_eye_trans_m"]), size_jk / 2.0)
    assert JACKKNIFE_NOISE < 2.0
    lopsided = honest(formal, estimates, reference, {"hand_eye_trans_m": jk * 0.9})
    assert lopsided.source["hand_eye_trans_m"] == "formal"
    assert np.allclose(lopsided.sigmas["hand_eye_trans_m"], formal["hand_eye_trans_m"])
    assert np.allclose(lopsided.expected["hand_eye_trans_m"], jk * 0.9)
    assert "what the noise model predicts" in lopsided.note
    for expected in (None, {"hand_eye_trans_m": 1.1 * formal["hand_eye_trans_m"]}):
        u = honest(formal, estimates, reference, expected)
        assert u.source["hand_eye_trans_m"] == "jackknife"
        # the jackknife's size, in the formal shape
        assert np.allclose(u.sigmas["hand_eye_trans_m"], 2.0 * formal["hand_eye_trans_m"])


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_expected_jackknife_matches_the_monte_carlo_mean_of_the_jackknife():
    """40 noise draws on the same 16 poses, every fold refitted: the mean square jackknife
    matches the expectation within its Monte-Carlo noise, for interleaved folds and for the
    lopsided design (where the formal σ would understate it by far)."""
    sc = scene()
    P_true = sample_station_poses(sc, N, np.random.default_rng(3))
    grid, cam = sc.true_board_points(), sc.camera
    clean = [Pinhole(cam.k_matrix, cam.dist_coeffs).project(grid @ C[:3, :3].T + C[:3, 3])
             for C in camera_pose_for_tcp(sc, P_true)]
    model, truth = JointModel("all", (), NOISE), _truth()
    designs = {"interleaved": fold_indices(N), "lopsided": UNBALANCED}
    squares = {name: [] for name in designs}
    expected: dict[str, dict] = {}
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        corners = [c + rng.normal(0.0, 0.15, c.shape) for c in clean]
        data = JointData(CornerStations(corners, perturb(P_true, ROT, TRANS, rng), BOARD),
                         "eye_in_hand", 0.15)
        full = fit_joint(data, model, truth)
        for name, folds in designs.items():
            if seed == 0:
                expected[name] = full.expected_jackknife(folds, noise=(0.15, ROT, TRANS))
            ests = [FoldEstimate.of(fit_joint(data.subset(np.setdiff1d(np.arange(N), held)),
                                              model, full.cell).cell) for held in folds]
            jk = jackknife_sigmas(ests, FoldEstimate.of(full.cell))
            squares[name].append([np.sum(np.square(jk[k])) for k in ("hand_eye_trans_m",
                                                                      "kappa")])
    for name in designs:
        mean = np.mean(squares[name], axis=0)
        for k, key in enumerate(("hand_eye_trans_m", "kappa")):
            ratio = np.sqrt(mean[k]) / _size(expected[name], key)
            assert 0.8 < ratio < 1.25, (name, key, ratio)
