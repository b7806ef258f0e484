"""Re-checking a stored calibration: does the cell still look the way the calibration predicts?

A re-check revisits stations: it reads the robot pose, grabs, detects the board and compares
what the camera sees with what the stored calibration predicts from the robot pose alone,
``C_pred = inv(X) inv(P) Y`` (eye-in-hand; ``inv(X) P Y`` eye-to-hand, ``calib.chain``). That
is the prediction the calibration's cross-validation scored (``calib.crossval``: each station
predicted from its robot reading by the estimator fitted on the other folds), so the
cross-validated errors are what an unchanged cell shows, robot and detection noise included.

Per station: the corner error (RMS px between detected and predicted corners) and the offset
``D_k = C_pred inv(C_obs)`` (4, 4) between predicted and observed camera poses (``C_obs`` by
PnP). A camera mount that moved by ``D`` (the camera frame now at ``X D``) gives ``D_k = D`` at
every station, while robot and detection noise differ from station to station. The check's
verdict therefore tests the *mean* offset over its stations: ``degraded`` when its rotation or
its translation exceeds ``OFFSET_FACTOR`` times the cross-validated RMS pose error of a single
held-out station. For one station that is a 0.6 % false alarm rate (the RMS of a 3-vector is
√3 σ per axis; P(χ₃ > 2√3) = 0.006); for more stations the noise of the mean shrinks, but the
calibration's own error is common to all of them and does not, so the limit stays. Rotation
and translation are tested apart: in the image they can partly cancel, in ``D`` they cannot.
A station is ``degraded`` when its corner error exceeds ``STATION_FACTOR`` times the
cross-validated RMS (px).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib import so3
from calib.boards import Board
from calib.camera import Pinhole, solve_pnp
from calib.chain import camera_from_robot, check_setup
from calib.geometry import invert, rotation_angle

#: The mean offset is degraded above this multiple of the cross-validated RMS pose error.
OFFSET_FACTOR = 2.0
#: A station's corner error is degraded above this multiple of the cross-validated RMS.
STATION_FACTOR = 3.0
#: Smallest limits on the mean offset (rad, m): detection noise of a perfect calibration.
MIN_ROT_RAD = np.deg2rad(0.01)
MIN_TRANS_M = 0.05e-3


@dataclass(frozen=True)
class StationCheck:
    """One revisited station: corner error (px) and the camera pose offset ``D_k`` (4, 4)."""

    rms_px: float
    max_px: float
    offset: np.ndarray  # shape (4, 4), C_pred inv(C_obs)

    @property
    def rot_rad(self) -> float:
        """Angle of the station's offset."""
        return float(rotation_angle(self.offset[:3, :3]))

    @property
    def trans_m(self) -> float:
        """Length of the station's offset translation."""
        return float(np.linalg.norm(self.offset[:3, 3]))


@dataclass(frozen=True)
class StationView:
    """A station's board view against the calibration's prediction (:meth:`StoredCell.observe`).

    ``corners`` (N, 2) are the detected corners of the points ``ids`` (N,), in the order that
    fits the prediction (a 180°-symmetric board read from its other end is turned back);
    ``predicted`` (N, 2) their pixels predicted from the robot pose, ``C_pred`` and ``C_obs``
    (4, 4) the predicted and the observed (PnP) T_cam_target, ``residuals_px`` (N, 2) the PnP
    fit's projection minus ``corners``.
    """

    corners: np.ndarray
    ids: np.ndarray
    predicted: np.ndarray
    C_pred: np.ndarray
    C_obs: np.ndarray
    residuals_px: np.ndarray


@dataclass(frozen=True)
class StoredCell:
    """What a calibration says about the cell (metres, radians).

    ``hand_eye`` and ``target_pose`` (4, 4) as in the result document (X and Y of
    ``calib.chain``); ``board`` with the calibrated print scale ``kappa`` and aspect ``nu``
    places the board points (``Board.points``), taken by point id, so partial views work;
    ``robot_map`` (3, 3) the calibration's map of the robot's translations, if it has one
    (``calib.chain.corrected_readings``).
    """

    setup: str
    K: np.ndarray  # shape (3, 3)
    dist: np.ndarray  # shape (5,)
    hand_eye: np.ndarray  # shape (4, 4)
    target_pose: np.ndarray  # shape (4, 4)
    board: Board
    kappa: float = 1.0
    nu: float = 1.0
    robot_map: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_setup(self.setup)

    def points(self, ids: np.ndarray | None = None) -> np.ndarray:
        """Board points ``ids`` (all when None) at the calibrated κ, ν, target frame, (N, 3)."""
        return self.board.points(ids, kappa=self.kappa, nu=self.nu)

    def predict(self, T_base_tcp: np.ndarray,
                ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """T_cam_target (4, 4) and the pixels (N, 2) of points ``ids`` (all when None) seen
        from ``T_base_tcp``."""
        C = camera_from_robot(T_base_tcp, self.hand_eye, self.target_pose, self.setup,
                              self.robot_map)
        return C, Pinhole(self.K, self.dist).project(self.points(ids) @ C[:3, :3].T + C[:3, 3])

    def observe(self, T_base_tcp: np.ndarray, corners: np.ndarray, *,
                ids: np.ndarray | None = None, ambiguous: bool = False) -> StationView:
        """Detected ``corners`` (N, 2) of points ``ids`` (default all) seen from
        ``T_base_tcp``, against the prediction. A 180°-symmetric board (``ambiguous``, a
        whole checkerboard) is read in the order that fits the prediction, so its origin is
        the calibration's. ValueError if PnP fails on the corners."""
        corners = np.asarray(corners, dtype=float)
        ids = (self.board.point_ids if ids is None
               else np.asarray(ids, dtype=np.int64).reshape(-1))
        C_pred, predicted = self.predict(T_base_tcp, ids)
        seen = min((corners, corners[::-1]) if ambiguous else (corners,),
                   key=lambda c: float(np.sum((c - predicted) ** 2)))
        C_obs, residuals = solve_pnp(self.points(ids), seen, self.K, self.dist, guess=C_pred)
        return StationView(corners=seen, ids=ids, predicted=predicted, C_pred=C_pred,
                           C_obs=C_obs, residuals_px=residuals)

    def check(self, T_base_tcp: np.ndarray, corners: np.ndarray, *,
              ids: np.ndarray | None = None, ambiguous: bool = False) -> StationCheck:
        """Compare detected ``corners`` (N, 2) of points ``ids`` (default all) with the
        prediction from ``T_base_tcp`` (see :meth:`observe`)."""
        view = self.observe(T_base_tcp, corners, ids=ids, ambiguous=ambiguous)
        dists = np.linalg.norm(view.corners - view.predicted, axis=1)
        return StationCheck(rms_px=float(np.sqrt(np.mean(dists ** 2))),
                            max_px=float(dists.max()), offset=view.C_pred @ invert(view.C_obs))


@dataclass(frozen=True)
class Expected:
    """The calibration's cross-validated RMS errors: corners (px), camera pose (rad, m)."""

    rms_px: float
    rot_rad: float
    trans_m: float

    def __post_init__(self) -> None:
        for name in ("rms_px", "rot_rad", "trans_m"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0.0:
                raise ValueError(f"the cross-validated {name} must be positive, got {value}")

    @property
    def station_limit_px(self) -> float:
        """A station whose corner error exceeds this (px) is degraded."""
        return STATION_FACTOR * self.rms_px

    def station_state(self, check: StationCheck) -> str:
        """``ok`` or ``degraded`` for one station's corner error."""
        return "degraded" if check.rms_px > self.station_limit_px else "ok"


@dataclass(frozen=True)
class CheckVerdict:
    """A re-check's outcome: ``ok`` or ``degraded``, the mean offset and its limits."""

    state: str
    rms_px: float  # over all stations
    rot_rad: float  # angle of the mean offset
    trans_m: float  # length of the mean offset's translation
    rot_limit_rad: float
    trans_limit_m: float
    station_limit_px: float


def check_verdict(stations: Sequence[StationCheck], expected: Expected) -> CheckVerdict:
    """The check's verdict over its stations (at least one)."""
    if not stations:
        raise ValueError("a check needs at least one station with the board detected")
    offsets = np.stack([s.offset for s in stations])
    rot = float(np.linalg.norm(np.mean(so3.log(offsets[:, :3, :3]), axis=0)))
    trans = float(np.linalg.norm(np.mean(offsets[:, :3, 3], axis=0)))
    rot_limit = max(OFFSET_FACTOR * expected.rot_rad, MIN_ROT_RAD)
    trans_limit = max(OFFSET_FACTOR * expected.trans_m, MIN_TRANS_M)
    rms = float(np.sqrt(np.mean([s.rms_px ** 2 for s in stations])))
    state = "degraded" if rot > rot_limit or trans > trans_limit else "ok"
    return CheckVerdict(state=state, rms_px=rms, rot_rad=rot, trans_m=trans,
                        rot_limit_rad=rot_limit, trans_limit_m=trans_limit,
                        station_limit_px=expected.station_limit_px)
