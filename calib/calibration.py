"""The one way into the solver: :func:`calibrate` a station set with :class:`SolverOptions`.

The command line (``cellcal calibrate DIR``), the service's calibration worker and the
benchmarks all come in here; what the stations hold decides the path:

* stations with images or detections (``calib.pipeline.calibrate_stations``): intrinsics with
  ν, hand-eye, κ, the joint maximum likelihood, validation; an intrinsics-only calibration
  when no station has a robot pose;
* pose-only stations (each with its measured ``T_cam_target``,
  ``calib.evidence.choose_pose_only``): the pose-level hand-eye, the refinement kept only when
  it predicts held-out stations no worse than SM.

A set that mixes the two is refused.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from calib.boards import board_from_target
from calib.crossval import PoseStations
from calib.evidence import Trust, choose_pose_only
from calib.handeye import HandEyeResult
from calib.options import SolverOptions
from calib.pipeline import CalibrationResult, calibrate_stations
from calib.stations import Observation, Station, Stations


@dataclass(frozen=True)
class PoseOnlyResult:
    """A pose-only hand-eye calibration (no camera model): the fit, the ids of its stations
    in order (one per row of ``fit.station_residuals``), its evidence, and the options as the
    result document lists them."""

    fit: HandEyeResult
    station_ids: tuple[str, ...]
    trust: Trust
    options: dict[str, Any]


#: What :func:`calibrate` returns: an image calibration or a pose-only one.
Calibration = CalibrationResult | PoseOnlyResult


def calibrate(stations: Stations, options: SolverOptions | None = None, *,
              images: Callable[[Station], Observation] | None = None,
              progress: Callable[[Iterable[Observation]], Iterable[Observation]] | None = None,
              on_stage: Callable[[str], None] | None = None) -> Calibration:
    """Calibrate ``stations`` as ``options`` say (default :class:`SolverOptions`).

    ``images(station)`` reads a station's image (grey or BGR pixels, or a
    :class:`calib.boards.Detection` saying why it cannot be read), one at a time as the board
    detection consumes them; without it each station's stored ``detection`` is used.
    ``progress`` and ``on_stage`` follow an image calibration
    (:func:`calib.pipeline.calibrate_stations`); a pose-only one has no stages to report.

    Raises
    ------
    ValueError
        A set mixing pose-only and image stations, a method the stations cannot take, too
        few usable stations, or stations that cannot determine the calibration.
    """
    options = SolverOptions() if options is None else options
    if stations.pose_only:
        return _pose_only(stations, options)
    posed = [s.id for s in stations.stations if s.T_cam_target is not None]
    if posed:
        raise ValueError(f"station {posed[0]} has a target_pose while others have images; a "
                         "station set is either pose-only or image-based")
    if stations.target is None:
        raise ValueError("stations with images need the target (the board) they show")
    return calibrate_stations(stations.inputs(images), board_from_target(stations.target),
                              options, progress=progress, on_stage=on_stage)


def _pose_only(stations: Stations, options: SolverOptions) -> PoseOnlyResult:
    """Hand-eye from the measured camera poses; κ is estimated only when ``options.kappa``
    says ``estimate`` (there is no model choice for it here)."""
    method = options.solver("poses")
    if method == "joint":
        raise ValueError("method 'joint' (maximum likelihood over the corners) needs images; "
                         "pose-only station sets use 'refine' (the default) or another "
                         "pose solver")
    T_base_tcp, T_cam_target = stations.pose_arrays()
    ids = tuple(s.id for s in stations.stations)
    estimate_kappa = options.kappa_mode == "estimate"
    fit, trust = choose_pose_only(
        PoseStations(T_base_tcp, T_cam_target, stations.setup), ids, method=method,
        options=options,
        square_size_m=None if stations.target is None else stations.target.square_size_m)
    return PoseOnlyResult(fit, ids, trust, {"estimate_kappa": estimate_kappa})
