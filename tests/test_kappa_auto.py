"""``kappa: auto`` decides by prediction (calib.selection): a board printed 0.5 % large is
seen and corrected, while an exact board on an arm with systematic kinematic errors — which
scatter κ by a few 0.1 % — is not reported as off and passes (issue 8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib import Checkerboard, StationInputs
from calib.pipeline import calibrate_stations
from mocks.cornersim import simulate_corners
from mocks.scene import MockScene, load_scene

SCENE = Path(__file__).resolve().parents[1] / "mocks" / "scenes" / "ur5e_kinematic_errors.json"


def calibrate(scene: MockScene, n: int, seed: int):
    corners, poses = simulate_corners(scene, n, np.random.default_rng(seed))
    t = scene.target
    return calibrate_stations(
        StationInputs(corners, poses, image_size=tuple(scene.camera.image_size),
                      setup=scene.setup), Checkerboard(tuple(t.inner_corners), t.square_size_m))


def with_board(kappa: float, kinematic_errors: bool) -> MockScene:
    scene = load_scene(SCENE)
    update = {"target": scene.target.model_copy(update={"kappa": kappa})}
    if not kinematic_errors:
        update["kinematics"] = None
    return scene.model_copy(update=update)


#: Two scenes of each test run in ``make test``; the other two are further Monte-Carlo draws of
#: the same claim (20 stations cost twice as much as 12), run by ``make test-slow``.
MORE = pytest.mark.slow


@pytest.mark.parametrize(("n", "seed"), [(8, 1), (12, 3), pytest.param(12, 0, marks=MORE),
                                         pytest.param(20, 1, marks=MORE)])
def test_a_board_half_a_percent_large_is_estimated_and_reported(n, seed):
    res = calibrate(with_board(1.005, kinematic_errors=False), n, seed)
    chosen = res.trust.model_selection.chosen.model
    assert "kappa" not in chosen.fix
    assert abs(res.kappa - 1.005) < 0.0015
    found = {f.code: f for f in res.trust.quality.findings}
    assert res.trust.quality.verdict == "warn"
    assert abs(found["board_scale"].values["measured_square_size_m"] - 0.0201) < 0.00003
    # the hand-eye is not biased by the nominal size (held at 1 it is off by 1-2 mm here)
    X = load_scene(SCENE).hand_eye_matrix
    assert np.linalg.norm(res.hand_eye[:3, 3] - X[:3, 3]) < 0.6e-3


@pytest.mark.parametrize(("n", "seed"), [(12, 0), (12, 1), pytest.param(20, 0, marks=MORE),
                                         pytest.param(20, 3, marks=MORE)])
def test_an_exact_board_on_an_arm_with_kinematic_errors_passes(n, seed):
    """No board warning, and κ and the hand-eye within 3 σ of the truth.

    Not "κ held at 1" (asserted until 2026-11-26): on 12-20 stations this arm's
    pose-dependent errors scatter κ by ±0.3-0.4 % (formal σ and jackknife agree; 60
    noise-free stations of the same arm give κ 1.0000 and 0.9992, so the errors are no
    scale), and some draws put it 2 σ from 1: [12-0] κ = 1.0080 ± 0.0040, [20-3] 0.9966.
    A 0.5 % board gives the same evidence on some draws (``benchmarks.kappa_nu`` seeds 0,
    12, 57: 2-3 σ), where holding κ moved the hand-eye 3.6 mm at a σ of 0.15 mm; so κ is
    estimated beyond 1 σ (``calib.selection.KAPPA_SIGMAS``) and such a draw of an exact
    board gets an estimated κ whose σ covers it. What must hold is what the user is told:
    the board is not called off (``board_scale`` needs 3 σ) and the result is as uncertain
    as it says (benchmarks/README.md, the κ/ν section).
    """
    res = calibrate(with_board(1.0, kinematic_errors=True), n, seed)
    quality = res.trust.quality
    assert quality.verdict == "pass", [f.message for f in quality.findings]
    assert "board_scale" not in {f.code for f in quality.findings}
    # held (exactly 1, no σ) or estimated within 3 σ of the true 1
    assert abs(res.kappa - 1.0) <= 3 * float(res.sigmas.get("kappa") or 0.0)
    # the true hand-eye: this scene has no workspace box, so the one its readings see
    # (mocks.blindcells.readings_hand_eye) is the same, and κ's readings-frame truth is 1
    X = load_scene(SCENE).hand_eye_matrix
    error = np.linalg.norm(res.hand_eye[:3, 3] - X[:3, 3])
    assert error <= 3 * np.linalg.norm(res.sigmas["hand_eye_trans_m"])
    # the robot's errors show in the prediction error, and the report says so
    info = [f for f in quality.findings if f.code == "high_prediction_error"]
    assert all(f.severity == "info" for f in info)
    assert res.trust.cross_validation.rms_m < 1e-3
