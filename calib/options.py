"""How a calibration is computed: the one options type of :func:`calib.calibrate`.

The station set says *what* is calibrated (its setup, board, stations); :class:`SolverOptions`
says *how*: the solver, whether the board's scale κ and aspect ν are estimated and how, the
robot's reading noise and the outlier rule. The same options serve image station sets
(``calib.pipeline``) and pose-only ones (``calib.evidence.choose_pose_only``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from calib.chain import RobotNoise
from calib.peers import OPENCV_HAND_EYE_METHODS, OPENCV_ROBOT_WORLD_METHODS

#: Solvers of pose-only hand-eye: screw motions, OpenCV's, and SM with the refinement.
POSE_METHODS = ("sm", *OPENCV_HAND_EYE_METHODS, *OPENCV_ROBOT_WORLD_METHODS, "refine")
#: Calibration methods: the pose-level hand-eye solvers, and ``joint`` (the default with
#: images), the maximum likelihood over all corners and robot poses started from ``refine``.
METHODS = (*POSE_METHODS, "joint")
#: Ways to estimate ν: ``images`` (Method #1, eq. 5) or ``extrinsics`` (Method #2).
NU_METHODS = ("images", "extrinsics")
#: Board scale κ: ``auto`` (chosen by prediction, ``calib.selection``), ``estimate``, ``fixed``.
KAPPA_MODES = ("auto", "estimate", "fixed")
#: Joint stage: stations whose robot correction lies beyond this many σ (Mahalanobis) are
#: dropped as outliers.
OUTLIER_SIGMA = 5.0
#: The method when none is named: the joint estimate with images, the refinement without.
DEFAULT_METHOD = {"images": "joint", "poses": "refine"}


@dataclass(frozen=True)
class SolverOptions:
    """How :func:`calib.calibrate` calibrates; checked on construction.

    ``method``: a name of ``METHODS``, or None for the default (``joint`` with images,
    ``refine`` for pose-only stations): ``refine``, ``sm`` or an OpenCV solver.
    ``estimate_nu``, ``estimate_kappa``: False holds ν (κ) at 1, the traditional nominal-size
    calibration. ``nu_method``: ``images`` (Method #1) or ``extrinsics`` (Method #2; ``joint``
    only), then ν is held at the Method #2 value in the joint stage. ``noise``: the robot
    reading noise, the joint prior. ``outlier_sigma``: joint stage: drop stations whose robot
    correction lies beyond this many σ (Mahalanobis); None keeps all. ``kappa``: ``auto`` (κ
    estimated only when that predicts held-out stations clearly better, ``calib.selection``;
    pose-only stations have no such choice and hold κ at 1), ``estimate``, or ``fixed`` (held at
    exactly 1: the entered square size was measured); ``estimate_kappa=False`` means ``fixed``.
    ``workspace``: the box (lo, hi corners, metres in the base frame) the robot's tool will work
    in with the result; the hand-eye σ then include using the stations' estimate over it
    (``calib.extrapolation``; joint only). None: the σ hold at the stations. ``tolerance``
    (rotation rad, translation m, the order of ``ColdStartScene.tolerance``): the accuracy the
    user needs of the hand-eye; a result whose 90 % bound is beyond it gets the finding
    ``tolerance_not_met`` (``calib.quality``).
    """

    method: str | None = None
    estimate_nu: bool = True
    estimate_kappa: bool = True
    kappa: str = "auto"
    nu_method: str = "images"
    noise: RobotNoise = field(default_factory=RobotNoise)
    outlier_sigma: float | None = OUTLIER_SIGMA
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    tolerance: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.method is not None and self.method not in METHODS:
            raise ValueError(f"unknown method '{self.method}': choose one of "
                             f"{', '.join(METHODS)}")
        if self.kappa not in KAPPA_MODES:
            raise ValueError(f"unknown kappa mode '{self.kappa}': choose one of "
                             f"{', '.join(KAPPA_MODES)}")
        if self.nu_method not in NU_METHODS:
            raise ValueError(f"unknown nu_method '{self.nu_method}': choose one of "
                             f"{NU_METHODS}")
        if self.workspace is not None and not (
                len(self.workspace) == 2 and all(len(c) == 3 for c in self.workspace)
                and all(lo < hi for lo, hi in zip(*self.workspace, strict=True))):
            raise ValueError(f"workspace must be two corners (x, y, z) with lo < hi on every "
                             f"axis, got {self.workspace}")
        if self.tolerance is not None and not (
                len(self.tolerance) == 2 and all(math.isfinite(v) and v > 0
                                                 for v in self.tolerance)):
            raise ValueError(f"tolerance must be two positive figures (rotation rad, "
                             f"translation m), got {self.tolerance}")
        if self.nu_method == "extrinsics" and (self.method not in (None, "joint")
                                               or not self.estimate_nu):
            raise ValueError("nu_method 'extrinsics' (Method #2) needs method 'joint' and "
                             "estimate_nu")

    @property
    def kappa_mode(self) -> str:
        """``kappa``, or ``fixed`` when ``estimate_kappa`` is off."""
        return self.kappa if self.estimate_kappa else "fixed"

    def solver(self, stations: str) -> str:
        """The method for ``stations`` (``images`` or ``poses``): the named one, else the
        default."""
        return self.method or DEFAULT_METHOD[stations]

    def record(self, known_intrinsics: bool) -> dict[str, Any]:
        """The options of an image calibration as the result document lists them."""
        return dict(method=self.solver("images"), estimate_nu=self.estimate_nu,
                    estimate_kappa=self.kappa_mode != "fixed", kappa=self.kappa_mode,
                    nu_method=self.nu_method,
                    robot_noise_rot_rad=self.noise.rot_rad,
                    robot_noise_trans_m=self.noise.trans_m, outlier_sigma=self.outlier_sigma,
                    known_intrinsics=known_intrinsics,
                    **({"workspace": [list(c) for c in self.workspace]} if self.workspace
                       else {}),
                    **({"tolerance": list(self.tolerance)} if self.tolerance else {}))
