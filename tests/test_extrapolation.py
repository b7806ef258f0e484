"""The σ of using a hand-eye fitted at the stations over the whole workspace box
(``calib.extrapolation``, issue 17)."""

from __future__ import annotations

import numpy as np
import pytest

from calib import SolverOptions, so3
from calib.extrapolation import box_shift_sigmas, implied_hand_eyes
from calib.geometry import invert, make_transform
from calib.pipeline import StationInputs, calibrate_stations
from tests.support.projected import BOARD, calibrate, scene, stations

BOX = (np.array([-0.25, -0.25, 0.2]), np.array([0.25, 0.25, 0.7]))
CENTRE = (BOX[0] + BOX[1]) / 2
X = make_transform(so3.exp(np.array([0.3, -1.2, 0.4])), [0.05, -0.02, 0.11])
SIZE = tuple(scene(1.0).camera.image_size)


def _readings(positions: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tool poses (n, 4, 4) at ``positions``, turned at random."""
    return np.stack([make_transform(so3.exp(rng.normal(0.0, 0.4, 3)), p) for p in positions])


def _corner_cloud(rng: np.random.Generator, n: int = 15, offset: float = 0.15) -> np.ndarray:
    return CENTRE + offset + rng.normal(0.0, 0.05, (n, 3))


def test_stations_centred_on_the_box_add_nothing_and_the_term_grows_with_the_offset():
    rng = np.random.default_rng(1)
    positions = _corner_cloud(rng)
    delta = rng.normal(0.0, 2e-4, (len(positions), 6))
    centred = positions - positions.mean(axis=0) + CENTRE
    P = _readings(centred, rng)
    at_centre = box_shift_sigmas(P, delta, X, "eye_in_hand", BOX)
    assert np.allclose(at_centre["hand_eye_rot_rad"], 0.0, atol=1e-12)
    P_far, P_farther = P.copy(), P.copy()
    P_far[:, :3, 3] += 0.05
    P_farther[:, :3, 3] += 0.10
    far = box_shift_sigmas(P_far, delta, X, "eye_in_hand", BOX)
    farther = box_shift_sigmas(P_farther, delta, X, "eye_in_hand", BOX)
    for name in ("hand_eye_rot_rad", "hand_eye_trans_m"):
        assert np.all(far[name] > 0)
        assert np.allclose(farther[name], 2.0 * far[name])  # linear in the distance
    assert box_shift_sigmas(P[:3], delta[:3], X, "eye_in_hand", BOX) == {}


def test_it_is_the_mean_square_shift_to_the_box_of_a_linear_field_of_unknown_direction():
    """A kinematic error that turns the tool by ``G (p - c)`` (G of random direction): the
    hand-eye the stations see, averaged over them, is off the box's average by
    ``G (μ_B - μ_S)``; over many such fields its mean square is the term's (derivation in
    the module docstring)."""
    rng = np.random.default_rng(7)
    P = _readings(_corner_cloud(rng), rng)
    p = P[:, :3, 3]
    shift2, term2 = np.zeros(3), np.zeros(3)
    for _ in range(2000):
        G = rng.normal(0.0, 1e-3, (3, 3))  # rad per metre, tool-frame rotation
        delta = np.zeros((len(P), 6))
        delta[:, :3] = (p - CENTRE) @ G.T
        rot = so3.log(implied_hand_eyes(P, delta, X, "eye_in_hand")[:, :3, :3] @ X[:3, :3].T)
        assert np.allclose(rot, delta[:, :3], atol=1e-9)  # each station's own hand-eye
        shift2 += (G @ (CENTRE - p.mean(axis=0))) ** 2  # box mean 0, stations' G (μ_S - c)
        term2 += box_shift_sigmas(P, delta, X, "eye_in_hand", BOX)["hand_eye_rot_rad"] ** 2
    assert 0.85 < shift2.sum() / term2.sum() < 1.15


def test_eye_to_hand_sees_a_base_side_error_that_is_the_same_everywhere_as_no_spread():
    """Eye-to-hand, a base-side error A common to every reading (``P E_i = A P``) moves every
    station's own hand-eye alike: no spread, nothing to extrapolate."""
    rng = np.random.default_rng(3)
    P = _readings(_corner_cloud(rng), rng)
    A = make_transform(so3.exp(np.array([2e-4, -1e-4, 3e-4])), [2e-4, 0.0, -1e-4])
    E = np.stack([invert(Pi) @ A @ Pi for Pi in P])
    delta = np.column_stack([so3.log(E[:, :3, :3]), E[:, :3, 3]])
    X_i = implied_hand_eyes(P, delta, X, "eye_to_hand")
    assert np.allclose(X_i, invert(A) @ X, atol=1e-12)
    term = box_shift_sigmas(P, delta, X, "eye_to_hand", BOX)
    assert np.all(term["hand_eye_rot_rad"] < 1e-12) and np.all(term["hand_eye_trans_m"] < 1e-12)


def test_a_calibration_given_its_box_reports_the_term_in_its_hand_eye_sigma():
    """``SolverOptions.workspace``: the hand-eye σ are the ones without the box with the term
    added in quadrature (the stations 0.3 m off the box's centre on each axis)."""
    plain = calibrate()
    centre = np.mean([p[:3] for p in stations(1.0)[1]], axis=0) + 0.3
    res = calibrate(workspace=(tuple(centre - 0.4), tuple(centre + 0.4)))
    u = res.trust.uncertainty
    assert np.allclose(res.hand_eye, plain.hand_eye)  # the estimate is the same
    for name in ("hand_eye_rot_rad", "hand_eye_trans_m"):
        assert np.all(u.extrapolation[name] > 0)
        assert np.allclose(res.sigmas[name], np.hypot(plain.sigmas[name], u.extrapolation[name]))
    assert "workspace box" in u.note and not plain.trust.uncertainty.extrapolation


def test_the_term_is_taken_over_the_stations_kept_when_one_is_dropped():
    """A station the joint fit drops (its robot pose is 4 mm off) leaves the term to the
    others, as if it had not been captured. The kept stations' indices then run past their
    count: a cold-start demo run that dropped one failed with an IndexError. (The two fits
    start from different values, so they agree to about 0.3 %.)"""
    corners, poses = stations()
    poses[3][0] += 4e-3
    box = (CENTRE - 0.4, CENTRE + 0.4)
    res = calibrate_stations(StationInputs(corners, poses, image_size=SIZE), BOARD,
                             SolverOptions(workspace=box))
    assert [i for i, _ in res.rejected] == ["003"]
    others = [k for k in range(len(poses)) if k != 3]
    without = calibrate_stations(StationInputs([corners[k] for k in others],
                                               [poses[k] for k in others], image_size=SIZE),
                                 BOARD, SolverOptions(workspace=box))
    assert without.rejected == ()
    for name in ("hand_eye_rot_rad", "hand_eye_trans_m"):
        term = res.trust.uncertainty.extrapolation[name]
        assert np.all(term > 0)
        assert np.allclose(term, without.trust.uncertainty.extrapolation[name], rtol=0.02)


def test_a_box_that_is_not_two_ordered_corners_is_refused():
    with pytest.raises(ValueError, match="workspace"):
        SolverOptions(workspace=((0.0, 0.0, 0.0), (1.0, -1.0, 1.0)))
    with pytest.raises(ValueError, match="workspace"):
        SolverOptions(workspace=((0.0, 0.0), (1.0, 1.0)))
