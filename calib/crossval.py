"""Cross-validation of the returned estimator: how well it predicts stations it has not seen.

The stations are split into folds (k-fold, default 5; leave-one-out below ``LOO_BELOW``
stations). For each fold the estimator is fitted on the other stations — warm-started from the
full solution, so a fold costs a few solver iterations — and every held-out station is
predicted from its robot reading alone, with the fold's camera, κ and ν
(``docs/conventions.md``)::

    eye-in-hand:  T_cam_target = inv(X) inv(P_k) Y          (X = T_tcp_cam, Y = T_base_target)
    eye-to-hand:  T_cam_target = inv(X) P_k Y               (X = T_base_cam, Y = T_tcp_target)

Image stations compare the projected true-size corners (κν i s, κ j s, 0) with the detected
ones: the RMS pixel error of each station, and the same error in metres on the board plane
(each detected corner's ray cut with the predicted board plane, compared with the predicted
corner), which a person can read without knowing the camera. Pose-only stations compare the
predicted with the measured ``T_cam_target`` (at the fold's κ).

This is Zhao & Liu's pose prediction (eq. 23) and Strobl & Hirzinger's projection error of a
held-out view, made the measure by which models are chosen (``calib.selection``) and by which
the reported uncertainty is checked (``calib.uncertainty``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass, replace

import cv2
import numpy as np

from calib.camera import Pinhole, solve_pnp
from calib.chain import camera_from_robot
from calib.geometry import pose_error
from calib.joint import CellParameters
from calib.jointfit import JointData, JointModel, fit_joint
from calib.parallel import InlineExecutor

DEFAULT_FOLDS = 5
#: Below this many stations every station is its own fold (leave-one-out).
LOO_BELOW = 10


@dataclass(frozen=True)
class HeldOut:
    """Prediction error of one held-out station (metres, radians, pixels).

    ``rms_px``/``max_px`` over its corners and ``rms_m`` (corner error on the board plane) for
    image stations, None for pose-only ones; ``rot_rad``/``trans_m`` between the predicted and
    the observed camera pose (PnP with the fold's camera for images); ``range_m`` the error of
    the predicted camera-to-board distance alone, the one figure a wrong board scale (κ) moves
    directly: PnP reads the distance from the board's apparent size, the robot from its
    translations. ``dropped``: the fit dropped this station as an outlier, so it was in no
    fold's training set (:func:`predict_dropped`).
    """

    id: str
    fold: int
    rot_rad: float
    trans_m: float
    rms_px: float | None = None
    max_px: float | None = None
    rms_m: float | None = None
    range_m: float | None = None
    dropped: bool = False


@dataclass(frozen=True)
class FoldEstimate:
    """What one fold estimated: X, Y (4, 4), κ, ν and, for image sets, all of it (``cell``)."""

    hand_eye: np.ndarray
    target_pose: np.ndarray
    kappa: float
    nu: float = 1.0
    cell: CellParameters | None = None

    @classmethod
    def of(cls, cell: CellParameters) -> FoldEstimate:
        return cls(hand_eye=cell.hand_eye, target_pose=cell.target_pose, kappa=cell.kappa,
                   nu=cell.nu, cell=cell)


class _HeldOutRms:
    """RMS over the held-out stations of one ``HeldOut`` field (None where it does not apply),
    read as an attribute of ``CrossValidation`` of the same name."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, cv: CrossValidation | None, owner: type) -> float | None:
        return _rms([getattr(s, self.name) for s in cv.stations]) if cv is not None else None


@dataclass(frozen=True)
class CrossValidation:
    """Held-out prediction errors of every station and the estimates of every fold.

    ``rms_px`` is the RMS over held-out stations of each station's RMS pixel error, ``rms_m``
    the same on the board plane (metres), ``rot_rad``/``trans_m`` of the camera poses,
    ``range_m`` of their distances to the board. The stations include those the fit dropped as
    outliers when :func:`predict_dropped` added them: the arm makes such errors in use, so the
    honest figure covers them; :meth:`kept` gives the figures without them.
    """

    kind: str  # "k-fold" or "leave-one-out"
    stations: tuple[HeldOut, ...]
    estimates: tuple[FoldEstimate, ...]

    rms_px = _HeldOutRms()
    rms_m = _HeldOutRms()
    range_m = _HeldOutRms()
    rot_rad = _HeldOutRms()
    trans_m = _HeldOutRms()

    @property
    def folds(self) -> int:
        return len(self.estimates)

    @property
    def dropped(self) -> tuple[str, ...]:
        """Ids of the stations the fit dropped as outliers (predicted, never trained on)."""
        return tuple(s.id for s in self.stations if s.dropped)

    def kept(self) -> CrossValidation:
        """The cross-validation of the stations the fit kept (the dropped ones left out)."""
        return replace(self, stations=tuple(s for s in self.stations if not s.dropped))

    def station_errors(self) -> np.ndarray:
        """The figure models are compared by, per station (n,): pixels, or metres pose-only."""
        px = [s.rms_px for s in self.stations]
        return np.array(px if px and px[0] is not None else [s.trans_m for s in self.stations])

    def range_errors(self) -> np.ndarray:
        """Per station (n,) the camera-to-board distance error (m): the scale figure."""
        return np.array([np.nan if s.range_m is None else s.range_m for s in self.stations])


def _rms(values: Sequence[float | None]) -> float | None:
    if not values or values[0] is None:
        return None
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if len(v) else None


def fold_indices(n: int, folds: int = DEFAULT_FOLDS) -> list[np.ndarray]:
    """Held-out station indices of each fold: station k in fold ``k mod f`` (interleaved, so
    each fold samples the whole capture sequence); leave-one-out below ``LOO_BELOW``."""
    k = n if n < LOO_BELOW else max(2, min(folds, n))
    return [np.arange(f, n, k) for f in range(k)]


def cross_validate_joint(data: JointData, station_ids: Sequence[str], model: JointModel,
                         full: CellParameters, *, folds: int = DEFAULT_FOLDS) -> CrossValidation:
    """k-fold cross-validation of the joint estimator ``model`` on image stations.

    ``full`` is the fit on all stations (the start of every fold).
    """
    return submit_joint_folds(JointFolds(data, tuple(station_ids), model, full),
                              InlineExecutor(), folds=folds).result()


@dataclass(frozen=True)
class JointFolds:
    """What the folds of a joint cross-validation share: the data, the station ids, the
    model, and its fit on all stations (the start of every fold); ``corrections`` (n, 6) that
    fit's robot corrections, where each fold starts its stations' (``fit_joint``)."""

    data: JointData
    station_ids: tuple[str, ...]
    model: JointModel
    full: CellParameters
    corrections: np.ndarray | None = None


@dataclass(frozen=True)
class PendingFolds:
    """The folds of :func:`submit_joint_folds`, fitting in ``pool``; :meth:`result` waits
    for them and puts their held-out stations in the order of ``station_ids``."""

    station_ids: tuple[str, ...]
    kind: str
    folds: tuple[Future, ...]  # each (FoldEstimate, list[HeldOut])

    def result(self) -> CrossValidation:
        done = [f.result() for f in self.folds]
        held = _in_station_order((h for _, fold in done for h in fold), self.station_ids)
        return CrossValidation(kind=self.kind, stations=held,
                               estimates=tuple(estimate for estimate, _ in done))


def submit_joint_folds(job: JointFolds, pool: Executor, *,
                       folds: int = DEFAULT_FOLDS) -> PendingFolds:
    """:func:`cross_validate_joint` with every fold fitted and predicted as a task of
    ``pool`` (``calib.parallel``), so that the folds of several models share the cores."""
    n = len(job.data)
    parts = fold_indices(n, folds)
    tasks = tuple(pool.submit(_joint_fold, job, test, f) for f, test in enumerate(parts))
    return PendingFolds(station_ids=job.station_ids, kind=_kind(parts, n), folds=tasks)


def _joint_fold(job: JointFolds, test: np.ndarray, fold: int
                ) -> tuple[FoldEstimate, list[HeldOut]]:
    """Fold ``fold``: the model fitted without the stations ``test`` (from the full fit),
    and each of them predicted from its robot reading."""
    data = job.data
    train = np.setdiff1d(np.arange(len(data)), test)
    start = None if job.corrections is None else job.corrections[train]
    cell = fit_joint(data.subset(train), job.model, job.full, corrections=start).cell
    return FoldEstimate.of(cell), [
        predict_image_station(cell, data, int(k), job.station_ids[k], fold) for k in test]


def cross_validate_fixed_camera(data: JointData, station_ids: Sequence[str],
                                state: CellParameters,
                                solve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                                *, folds: int = DEFAULT_FOLDS) -> CrossValidation:
    """Cross-validation of a hand-eye method over image stations, camera held at ``state``.

    ``solve(train)`` returns X, Y from the training station indices (e.g. a closed-form method
    on the intrinsic stage's camera poses). The camera was calibrated on all images, so the
    figure is slightly optimistic; the joint estimator refits its camera in every fold.
    """
    n = len(data)
    held, estimates = [], []
    parts = fold_indices(n, folds)
    for f, test in enumerate(parts):
        try:
            X, Y = solve(np.setdiff1d(np.arange(n), test))
        except ValueError:
            continue  # the remaining stations cannot determine the hand-eye
        fold_state = replace(state, hand_eye=X, target_pose=Y)
        estimates.append(FoldEstimate.of(fold_state))
        held += [predict_image_station(fold_state, data, int(k), station_ids[k], f)
                 for k in test]
    return CrossValidation(kind=_kind(parts, n), stations=_in_station_order(held, station_ids),
                           estimates=tuple(estimates))


def predict_dropped(cv: CrossValidation, dropped: JointData, dropped_ids: Sequence[str],
                    positions: Sequence[int], order: Sequence[str]) -> CrossValidation:
    """``cv`` with the stations the fit dropped as outliers predicted too.

    ``dropped`` holds those stations, ``dropped_ids`` their ids, ``positions`` their indices
    among all the stations the fit started from, ``order`` the ids of all those stations in
    order. A dropped station is in no fold's training set, so every fold estimate predicts it
    out of sample; it is predicted by fold ``position mod folds``, the fold that holds it out
    when the folds are drawn over all stations (``fold_indices``).
    """
    if not cv.estimates or len(dropped) == 0:
        return cv
    extra = []
    for k, (sid, pos) in enumerate(zip(dropped_ids, positions, strict=True)):
        f = int(pos) % len(cv.estimates)
        cell = cv.estimates[f].cell
        if cell is None:
            raise ValueError("predict_dropped needs image-set fold estimates (with a cell)")
        extra.append(replace(predict_image_station(cell, dropped, k, sid, f), dropped=True))
    rank = {sid: i for i, sid in enumerate(order)}
    stations = sorted([*cv.stations, *extra], key=lambda h: rank[h.id])
    return replace(cv, stations=tuple(stations))


@dataclass(frozen=True)
class PoseStations:
    """Pose-only stations: readings T_base_tcp and observations T_cam_target (n, 4, 4)."""

    T_base_tcp: np.ndarray
    T_cam_target: np.ndarray
    setup: str


def cross_validate_poses(stations: PoseStations, station_ids: Sequence[str],
                         solve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, float]],
                         *, folds: int = DEFAULT_FOLDS) -> CrossValidation:
    """Cross-validation of a pose-only hand-eye estimator.

    ``solve(train)`` returns X, Y, κ from the training station indices; each held-out
    ``T_cam_target`` (its translation scaled by the fold's κ) is compared with the one
    predicted from its robot reading.
    """
    T_base_tcp, T_cam_target, setup = stations.T_base_tcp, stations.T_cam_target, stations.setup
    n = len(T_base_tcp)
    held, estimates = [], []
    parts = fold_indices(n, folds)
    for f, test in enumerate(parts):
        try:
            X, Y, kappa = solve(np.setdiff1d(np.arange(n), test))
        except ValueError:
            continue
        estimates.append(FoldEstimate(hand_eye=X, target_pose=Y, kappa=kappa))
        pred = camera_from_robot(T_base_tcp[test], X, Y, setup)
        observed = T_cam_target[test].copy()
        observed[:, :3, 3] *= kappa
        rot, trans = pose_error(pred, observed)
        held += [HeldOut(id=station_ids[k], fold=f, rot_rad=float(r), trans_m=float(t))
                 for k, r, t in zip(test, rot, trans, strict=True)]
    return CrossValidation(kind=_kind(parts, n), stations=_in_station_order(held, station_ids),
                           estimates=tuple(estimates))


def _in_station_order(held: Iterable[HeldOut], station_ids: Sequence[str]
                      ) -> tuple[HeldOut, ...]:
    """``held`` in the order of ``station_ids``, through a map of positions: a search of the
    id list per station was O(n²), 3 CPU-s of a 20,000-station calibration."""
    position: dict[str, int] = {}
    for k, station_id in enumerate(station_ids):
        position.setdefault(station_id, k)
    return tuple(sorted(held, key=lambda h: position[h.id]))


def _kind(parts: list[np.ndarray], n: int) -> str:
    return "leave-one-out" if len(parts) == n else "k-fold"


def predict_image_station(state: CellParameters, data: JointData, k: int, station_id: str,
                          fold: int) -> HeldOut:
    """Errors of station ``k``'s corners predicted from its robot reading through ``state``."""
    true = data.stations.board.points(data.stations.ids()[k], kappa=state.kappa, nu=state.nu)
    C = camera_from_robot(data.stations.T_base_tcp[k], state.hand_eye, state.target_pose,
                          data.setup, state.robot_map)
    K, dist = state.K, np.asarray(state.dist, dtype=float)
    detected = np.asarray(data.stations.image_points[k], dtype=float)
    uv = Pinhole(K, dist).project(true @ C[:3, :3].T + C[:3, 3])
    err = np.linalg.norm(uv - detected, axis=1)
    on_board = _board_plane_points(detected, C, K, dist)
    rms_m = float(np.sqrt(np.mean(np.sum((on_board - true[:, :2]) ** 2, axis=1))))
    try:
        observed, _ = solve_pnp(true, detected, K, dist, guess=C)
        rot, trans = (float(v) for v in pose_error(C, observed))
        rng = float(abs(np.linalg.norm(C[:3, 3]) - np.linalg.norm(observed[:3, 3])))
    except ValueError:
        rot = trans = rng = float("nan")
    return HeldOut(id=station_id, fold=fold, rot_rad=rot, trans_m=trans,
                   rms_px=float(np.sqrt(np.mean(err ** 2))), max_px=float(err.max()),
                   rms_m=rms_m, range_m=rng)


def _board_plane_points(uv: np.ndarray, T_cam_target: np.ndarray, K: np.ndarray,
                        dist: np.ndarray) -> np.ndarray:
    """Where the rays of pixels ``uv`` (N, 2) cut the board plane z = 0 of ``T_cam_target``,
    in target coordinates (N, 2), metres."""
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    R, t = T_cam_target[:3, :3], T_cam_target[:3, 3]
    normal = R[:, 2]
    depth = (normal @ t) / (rays @ normal)
    return ((rays * depth[:, None] - t) @ R)[:, :2]
