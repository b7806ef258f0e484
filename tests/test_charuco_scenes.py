"""Issue 9's κ/ν and partial-view claims on a small rendered ChArUco station set read by the
real detector (``Charuco.detect``): one fixed seed of ``benchmarks/charuco.py``'s scenes, so a
regression in rendering, detection or calibration fails the suite. The Monte-Carlo figures
(several seeds, Cramér-Rao and OpenCV ratios) are the benchmark's."""

from __future__ import annotations

from functools import cache

import numpy as np

from benchmarks.charuco import (
    CUT,
    SCENE,
    STATIONS,
    TOL_KAPPA,
    TOL_NU,
    corner_error,
    rendered_set,
)
from mocks.scene import StationSpread


@cache
def calibrations():
    """(cut set, its calibration, the whole-board set's calibration) of seed 0."""
    cut = rendered_set(SCENE, 0, CUT)
    whole = rendered_set(SCENE, 10_000, StationSpread())
    return cut, cut.calibrate(SCENE), whole.calibrate(SCENE)


def test_cut_views_are_read_in_part_and_every_station_is_used():
    cut, res, _ = calibrations()
    n_all = len(SCENE.true_board_points())
    partial = [len(d.ids) < n_all for d in cut.detections]
    assert cut.cut >= 0.3 * STATIONS and sum(partial) >= cut.cut
    assert all(d.ok for d in cut.detections) and len(res.stations) == STATIONS


def test_kappa_and_nu_of_the_print_are_recovered():
    _, res, _ = calibrations()
    assert abs(res.kappa - SCENE.target.kappa) <= TOL_KAPPA, res.kappa
    assert abs(res.nu - SCENE.target.nu) <= TOL_NU, res.nu


def test_cut_views_model_the_image_corners_better_than_whole_board_views():
    """The same number of stations, the board whole in every view: the distortion at the
    image corners is extrapolated, and projects there at least 1.5x worse."""
    _, res, whole = calibrations()
    cut_err, whole_err = corner_error(SCENE, res), corner_error(SCENE, whole)
    assert np.isfinite(cut_err) and cut_err * 1.5 <= whole_err, (cut_err, whole_err)
