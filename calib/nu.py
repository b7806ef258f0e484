"""Board aspect ratio ν from the extrinsic residuals: Strobl & Hirzinger, Method #2.

Method #1 (``calib.intrinsics``) estimates ν from the corners alone. Method #2 chooses the ν
whose camera poses agree best with the robot: for each trial ν the intrinsic bundle adjustment
runs with ν held (eq. 3 with the board model scaled by ν), then X, Y and κ are refined from the
poses (eq. 6, ``calib.refine``); the cost is the sum of squared pose residuals over the
*configured* robot noise, so that costs at different ν compare.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from calib.chain import RobotNoise, check_setup
from calib.geometry import check_transforms
from calib.handeye import calibrate_hand_eye
from calib.intrinsics import IntrinsicsOptions, calibrate_intrinsics
from calib.joint import CornerStations
from calib.refine import RefineOptions, pose_residuals, scale_translations


@dataclass(frozen=True)
class NuSearch:
    """Options of :func:`nu_from_extrinsics`: the setup, the robot noise the cost is weighted
    with, intrinsic parameters held (``calib.intrinsics.FIXABLE``), and the half width of the
    search interval around the start."""

    setup: str = "eye_in_hand"
    noise: RobotNoise = field(default_factory=RobotNoise)
    fix: tuple[str, ...] = ()
    half_width: float = 0.005

    def __post_init__(self) -> None:
        check_setup(self.setup)


def nu_from_extrinsics(stations: CornerStations, image_size: Sequence[int], nu0: float,
                       search: NuSearch | None = None) -> tuple[float, float]:
    """ν by Method #2 and its standard deviation, (ν, σ_ν).

    A bounded 1-D search within ``nu0 ± half_width`` (the paper's "very restricted local
    search" started from Method #1, e.g. its estimate as ``nu0``) finds the minimum of the cost
    of the module docstring; σ_ν follows from the cost's curvature (Δχ² = 1, scaled by the
    reduced χ² at the minimum). ``image_size`` is (width, height) in pixels.
    """
    search = NuSearch() if search is None else search
    noise = search.noise
    weights = np.array([noise.rot_rad] * 3 + [noise.trans_m] * 3)
    T_base_tcp = check_transforms(stations.T_base_tcp, "tcp_pose")
    refine_kappa = RefineOptions(noise=noise, estimate_kappa=True)

    def cost(nu: float) -> float:
        intr = calibrate_intrinsics(stations.image_points, stations.board, image_size,
                                    IntrinsicsOptions(estimate_nu=False, nu=nu, fix=search.fix),
                                    point_ids=stations.point_ids)
        he = calibrate_hand_eye(T_base_tcp, intr.T_cam_target, setup=search.setup,
                                method="refine", options=refine_kappa)
        r = pose_residuals(T_base_tcp, scale_translations(intr.T_cam_target, he.kappa),
                           he.hand_eye, he.target_pose, search.setup)
        return float(np.sum((r / weights) ** 2))

    # here: only --nu-method extrinsics needs scipy.optimize, whose import costs every other
    # calibration 0.2-0.3 CPU s (calib.levmar)
    from scipy.optimize import minimize_scalar

    half_width = search.half_width
    sol = minimize_scalar(cost, bounds=(nu0 - half_width, nu0 + half_width), method="bounded",
                          options={"xatol": 1e-6})
    nu, f0 = float(sol.x), float(sol.fun)
    h = 1e-3 * half_width + 2e-4
    curvature = (cost(nu + h) + cost(nu - h) - 2.0 * f0) / (h * h)
    dof = max(6 * len(T_base_tcp) - 14, 1)
    sigma = float(np.sqrt(2.0 / curvature * f0 / dof)) if curvature > 0 else np.inf
    return nu, sigma
