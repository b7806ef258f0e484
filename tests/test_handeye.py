import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.geometry import invert, make_transform, pose_error
from calib.handeye import POSE_METHODS, calibrate_hand_eye
from calib.refine import RefineOptions
from calib.screw import screw_parameters, solve_sm
from mocks.posesim import default_cell, simulate
from tests.support.helpers import assert_pose_close, random_transforms


def exact_stations(rng, n, setup):
    """Noise-free stations with random rotations; returns P, C, X, Y."""
    X = random_transforms(rng, 1, scale=0.2)[0]
    Y = random_transforms(rng, 1, scale=1.0)[0]
    P = random_transforms(rng, n, scale=0.5)
    if setup == "eye_in_hand":  # P X C = Y
        C = invert(X) @ invert(P) @ Y
    else:  # inv(P) X C = Y
        C = invert(X) @ P @ Y
    return P, C, X, Y


@pytest.mark.parametrize("setup", ["eye_in_hand", "eye_to_hand"])
@pytest.mark.parametrize("method", POSE_METHODS)
def test_every_method_is_exact_on_noise_free_data(setup, method):
    for seed in range(3):
        P, C, X, Y = exact_stations(np.random.default_rng(seed), 10, setup)
        result = calibrate_hand_eye(P, C, setup=setup, method=method)
        assert result.method == method and result.setup == setup
        assert_pose_close(result.hand_eye, X, rot=1e-9, trans=1e-9)
        assert_pose_close(result.target_pose, Y, rot=1e-9, trans=1e-9)
        assert result.station_residuals.shape == (10, 2)
        assert result.station_residuals.max() < 1e-9


def test_sm_is_exact_with_two_motions():
    rng = np.random.default_rng(7)
    P, C, X, _ = exact_stations(rng, 3, "eye_in_hand")
    A = np.stack([invert(P[0]) @ P[1], invert(P[0]) @ P[2]])
    B = np.stack([C[0] @ invert(C[1]), C[0] @ invert(C[2])])
    assert_pose_close(solve_sm(A, B), X, rot=1e-10, trans=1e-10)


def test_screw_parameters_reconstruct_the_motion():
    """eq. (4): t = d u + (I - R) c, with c . u = 0."""
    T = random_transforms(np.random.default_rng(4), 30)
    u, theta, c, d = screw_parameters(T)
    np.testing.assert_allclose(np.einsum("ij,ij->i", c, u), 0.0, atol=1e-12)
    R = T[:, :3, :3]
    t = d[:, None] * u + c - np.einsum("nij,nj->ni", R, c)
    np.testing.assert_allclose(t, T[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_rotvec(u * theta[:, None]).as_matrix(), R, atol=1e-12)


def test_refine_recovers_kappa_exactly():
    """Camera translations of a board kappa times its nominal size are kappa times too small."""
    rng = np.random.default_rng(5)
    P, C, X, _ = exact_stations(rng, 12, "eye_in_hand")
    kappa = 1.005
    C_nominal = C.copy()
    C_nominal[:, :3, 3] /= kappa
    result = calibrate_hand_eye(P, C_nominal, method="refine",
                                options=RefineOptions(estimate_kappa=True))
    assert result.kappa == pytest.approx(kappa, abs=1e-9)
    assert_pose_close(result.hand_eye, X, rot=1e-9, trans=1e-9)
    # without kappa the nominal-size board biases the translation
    biased = calibrate_hand_eye(P, C_nominal, method="sm")
    assert pose_error(biased.hand_eye, X)[1] > 1e-4


def test_realistic_noise_errors_and_uncertainty():
    cell = default_cell("eye_in_hand")
    P, C = simulate(cell, 15, np.random.default_rng(11))
    result = calibrate_hand_eye(P, C)
    dr, dt = pose_error(result.hand_eye, cell.hand_eye)
    assert dr < np.deg2rad(0.1) and dt < 1e-3
    for key in ("hand_eye_rot_rad", "hand_eye_trans_m", "target_pose_rot_rad",
                "target_pose_trans_m"):
        sd = np.asarray(result.sigmas[key])
        assert sd.shape == (3,) and np.all(sd > 0) and np.all(np.isfinite(sd))
    # the reported sigma is of the size of the actual error (not off by orders of magnitude)
    assert 0.05 < dt / np.linalg.norm(result.sigmas["hand_eye_trans_m"]) < 5.0
    assert result.noise["trans_m"] > 0 and result.motions_used > 50


def test_stations_that_barely_rotate_are_skipped_not_fatal():
    rng = np.random.default_rng(8)
    P, C, X, _ = exact_stations(rng, 8, "eye_in_hand")
    # a ninth station: station 0 moved by 1 mm without rotation
    shift = make_transform(np.eye(3), [0.001, 0.0, 0.0])
    P9 = np.concatenate([P, (P[0] @ shift)[None]])
    C9 = np.concatenate([C, (invert(X) @ invert(shift) @ X @ C[0])[None]])
    result = calibrate_hand_eye(P9, C9, method="sm")
    assert result.motions_skipped >= 1
    assert_pose_close(result.hand_eye, X, rot=1e-9, trans=1e-9)


def valid_stations(n=6):
    return exact_stations(np.random.default_rng(9), n, "eye_in_hand")


@pytest.mark.parametrize("mutate, message", [
    (lambda P, C: P.__setitem__((2, 0, 3), np.nan), r"tcp_pose\[2\] contains NaN or inf"),
    (lambda P, C: C.__setitem__((4, 1, 3), np.inf), r"target_pose\[4\] contains NaN or inf"),
    (lambda P, C: P.__setitem__((1, 0, 1), 0.3), r"tcp_pose\[1\] rotation is not orthonormal"),
    (lambda P, C: C.__setitem__((0, 2, 3), 450.0), r"target_pose\[0\] translation .*millimetres"),
])
def test_bad_station_values_are_named(mutate, message):
    P, C, _, _ = valid_stations()
    mutate(P, C)
    with pytest.raises(ValueError, match=message):
        calibrate_hand_eye(P, C)


def test_millimetre_robot_poses_are_caught():
    P, C, _, _ = valid_stations()
    P[:, :3, 3] = P[:, :3, 3] * 1000.0 + 100.0
    with pytest.raises(ValueError, match="millimetres"):
        calibrate_hand_eye(P, C)


def test_too_few_stations():
    P, C, _, _ = valid_stations()
    with pytest.raises(ValueError, match="need at least 3 stations, got 2"):
        calibrate_hand_eye(P[:2], C[:2])


def test_mismatched_station_counts():
    P, C, _, _ = valid_stations()
    with pytest.raises(ValueError, match="6 robot poses but 5 camera poses"):
        calibrate_hand_eye(P, C[:5])


def test_parallel_rotation_axes_are_degenerate():
    rng = np.random.default_rng(10)
    X = random_transforms(rng, 1, scale=0.2)[0]
    Y = random_transforms(rng, 1)[0]
    angles = np.deg2rad([0, 20, 45, 70, 100, 130])
    R = Rotation.from_rotvec(np.outer(angles, [0, 0, 1])).as_matrix()
    P = make_transform(R, rng.normal(0, 0.3, (6, 3)))
    C = invert(X) @ invert(P) @ Y
    with pytest.raises(ValueError, match="rotation axes of all motions are parallel within 2 deg: "
                                         "add stations tilted about another axis"):
        calibrate_hand_eye(P, C)


def test_pure_translations_are_degenerate():
    rng = np.random.default_rng(12)
    X = random_transforms(rng, 1, scale=0.2)[0]
    P = make_transform(np.broadcast_to(np.eye(3), (5, 3, 3)), rng.normal(0, 0.3, (5, 3)))
    C = invert(X) @ invert(P)
    with pytest.raises(ValueError, match="fewer than 2 station pairs rotate"):
        calibrate_hand_eye(P, C)


def test_unknown_method_and_setup():
    P, C, _, _ = valid_stations()
    with pytest.raises(ValueError, match="unknown method 'magic': choose one of sm, tsai"):
        calibrate_hand_eye(P, C, method="magic")
    with pytest.raises(ValueError, match="unknown setup 'eye_on_hand'"):
        calibrate_hand_eye(P, C, setup="eye_on_hand")
    with pytest.raises(ValueError, match="kappa can only be estimated by the 'refine' method"):
        calibrate_hand_eye(P, C, method="park", options=RefineOptions(estimate_kappa=True))


@pytest.mark.slow
def test_reported_sigma_matches_monte_carlo_spread():
    cell = default_cell("eye_in_hand")
    errors, sigmas = [], []
    for seed in range(150):
        P, C = simulate(cell, 15, np.random.default_rng(1000 + seed))
        result = calibrate_hand_eye(P, C)
        errors.append(result.hand_eye[:3, 3] - cell.hand_eye[:3, 3])
        sigmas.append(result.sigmas["hand_eye_trans_m"])
    ratio = np.sqrt(np.mean(np.square(errors), axis=0)) / np.sqrt(np.mean(np.square(sigmas), 0))
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
