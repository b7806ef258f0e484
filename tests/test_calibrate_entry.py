"""``calib.calibrate(stations, options)``, the one way into the solver: what the stations hold
decides the path (pose-only or images), the options say how, and the solve job the service's
worker gets is a typed object that survives the trip to another process."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest

from calib import (
    COVERAGE_90,
    CalibrationResult,
    PoseOnlyResult,
    SolverOptions,
    Station,
    Stations,
    calibrate,
    pose_error,
    ur_pose_from_matrix,
)
from mocks.posesim import default_cell, simulate
from service.jobs.solve import SolveJob
from tests.support.stations import SIZE, TARGET, detections, rendered_stations


def pose_only_set(n: int = 12) -> tuple[Stations, np.ndarray]:
    cell = default_cell("eye_in_hand")
    P, C = simulate(cell, n, np.random.default_rng(3))
    stations = tuple(Station(f"{k:03d}", T_base_tcp=ur_pose_from_matrix(P[k]),
                             T_cam_target=ur_pose_from_matrix(C[k])) for k in range(n))
    return Stations("eye_in_hand", stations), cell.hand_eye


def image_set(n: int = 8) -> Stations:
    _, poses = rendered_stations()
    return Stations("eye_in_hand", tuple(
        Station(f"{k:03d}", T_base_tcp=np.asarray(poses[k]), image_size=SIZE,
                detection=det) for k, det in enumerate(detections()[:n])), TARGET.target())


def test_pose_only_stations_take_the_pose_path_with_refine_by_default():
    stations, X = pose_only_set()
    result = calibrate(stations)
    assert isinstance(result, PoseOnlyResult)
    assert result.station_ids == tuple(s.id for s in stations.stations)
    assert result.options == {"estimate_kappa": False}  # auto: no model choice for κ here
    rot, trans = pose_error(result.fit.hand_eye, X)
    assert rot < np.deg2rad(0.1) and trans < 1e-3
    assert result.trust.quality.verdict in ("pass", "warn")
    assert calibrate(stations, SolverOptions(method="sm")).fit.method == "sm"
    assert calibrate(stations, SolverOptions(kappa="estimate")).options == {
        "estimate_kappa": True}


def test_pose_only_stations_refuse_the_joint_method():
    stations, _ = pose_only_set()
    with pytest.raises(ValueError, match=r"'joint' .* needs images"):
        calibrate(stations, SolverOptions(method="joint"))


def test_image_stations_take_the_image_path_with_joint_by_default():
    result = calibrate(image_set())
    assert isinstance(result, CalibrationResult)
    assert result.method == "joint" and result.options["method"] == "joint"
    assert result.hand_eye is not None and len(result.stations) + len(result.rejected) == 8


def test_a_stored_detection_from_an_image_of_another_size_is_rejected():
    stations = image_set()
    odd = replace(stations.stations[3], image_size=(640, 480))
    stations = replace(stations, stations=(*stations.stations[:3], odd, *stations.stations[4:]))
    result = calibrate(stations, SolverOptions(method="sm"))
    assert dict(result.rejected) == {odd.id: f"image is 640x480, the others {SIZE[0]}x{SIZE[1]}"}


def test_a_set_mixing_pose_only_and_image_stations_is_refused():
    stations = image_set()
    mixed = replace(stations, stations=(replace(stations.stations[0], T_cam_target=np.array(
        [0.0, 0.0, 0.5, 0.0, 0.0, 0.0])), *stations.stations[1:]))
    with pytest.raises(ValueError, match="station 000 has a target_pose while others have "
                                         "images"):
        calibrate(mixed)


def test_options_are_checked_when_made():
    with pytest.raises(ValueError, match="unknown method"):
        SolverOptions(method="nonsense")
    with pytest.raises(ValueError, match="Method #2"):
        SolverOptions(method="sm", nu_method="extrinsics")


@pytest.mark.parametrize("kind", ["pose-only", "images"])
def test_a_result_beyond_the_tolerance_asked_for_is_a_warning(kind):
    """``SolverOptions.tolerance`` (rad, m): ``tolerance_not_met`` when the hand-eye's 90 %
    bound (COVERAGE_90 σ, root-sum-square over the axes) is beyond either figure."""
    stations = pose_only_set()[0] if kind == "pose-only" else image_set()
    plain = calibrate(stations)
    sigmas = plain.fit.sigmas if kind == "pose-only" else plain.sigmas
    bound = (COVERAGE_90 * np.linalg.norm(sigmas["hand_eye_rot_rad"]),
             COVERAGE_90 * np.linalg.norm(sigmas["hand_eye_trans_m"]))
    met = calibrate(stations, SolverOptions(tolerance=(1.01 * bound[0], 1.01 * bound[1])))
    assert met.trust.quality == plain.trust.quality
    for tight in ((0.99 * bound[0], 1.01 * bound[1]), (1.01 * bound[0], 0.99 * bound[1])):
        quality = calibrate(stations, SolverOptions(tolerance=tight)).trust.quality
        assert quality.verdict in ("warn", "fail")
        finding = quality.findings[-1]
        assert (finding.code, finding.severity) == ("tolerance_not_met", "warn")
        assert finding.values["bound_rot_rad"] == pytest.approx(bound[0])
        assert finding.values["bound_trans_m"] == pytest.approx(bound[1])
        assert f"{bound[1] * 1e3:.2f} mm" in finding.message


def test_a_tolerance_is_two_positive_figures():
    for bad in ((0.0, 1e-3), (1e-3, float("nan")), (1e-3,)):
        with pytest.raises(ValueError, match="tolerance must be two positive figures"):
            SolverOptions(tolerance=bad)


def test_the_workers_solve_job_pickles_whole():
    job = SolveJob(cal_id="c", run_id="r", stations=image_set(3),
                   options=SolverOptions(kappa="fixed"))
    back = pickle.loads(pickle.dumps(job))
    assert back.options == job.options and back.stations.target == job.stations.target
    assert [s.id for s in back.stations.stations] == ["000", "001", "002"]
    assert np.array_equal(back.stations.stations[1].detection.corners,
                          job.stations.stations[1].detection.corners)
