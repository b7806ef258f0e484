"""The oracle bound of the cold start (``benchmarks.cold_start_bound``): its information model
is the planner's, and its greedy design lowers the hand-eye σ with every station."""

from __future__ import annotations

import numpy as np

from benchmarks import cold_start_bound as bound
from benchmarks import cold_start_views as views
from calib.chain import camera_from_robot
from calib.joint import JointOptions
from calib.viewselect import SIGMA_PX, station_information


def test_information_at_the_planners_noise_is_the_planners() -> None:
    t = views.truth(13)
    P = views.pool(t, np.random.default_rng(0), draws=100)[:4]
    ours = bound.station_information(t, P, bound.PLANNER_NOISE)
    planner = JointOptions(sigma_px=SIGMA_PX, setup=t.setup)
    np.testing.assert_allclose(ours, station_information(t.cell, P, t.board, planner),
                               rtol=1e-9, atol=1e-9 * np.abs(ours).max())


def test_greedy_design_lowers_sigma_with_every_station() -> None:
    t = views.truth(13)
    P = views.pool(t, np.random.default_rng(0), draws=150)
    assert len(P) >= 20
    assert views.feasible(t, camera_from_robot(
        P, t.cell.hand_eye, t.cell.target_pose, t.setup)).all()
    noise = bound.calibration_noise(t.scene)
    S0 = bound.station_information(t, t.start[None], noise)[0] + bound.prior_information()
    chosen, sigma = bound.greedy(S0, bound.station_information(t, P, noise), 8,
                                 float(t.cell.K[0, 0]), lambda i: True)
    assert len(set(chosen)) == 8
    assert (np.diff(sigma, axis=0) <= 1e-12).all()
    assert (sigma[-1] < 0.5 * sigma[0]).all()
