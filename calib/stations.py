"""A station set on its way in: detection, which stations are usable, known-camera poses.

The first steps of ``calib.pipeline``: every observation is detected (a bad image becomes a
rejected station with its reason, never an abort), the usable stations are chosen, and the
per-image camera poses come from PnP when the camera is known. A 180°-symmetric board's origin
is made the same physical corner in every image from the robot motions.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from calib.boards import Board, BoardTarget, Detection, TargetAdapter
from calib.camera import solve_pnp
from calib.chain import check_setup
from calib.geometry import check_ur_poses, invert, make_transform, rotation_angle

Observation = np.ndarray | Detection
#: Fewest usable images (stations) a calibration accepts.
MIN_IMAGES = 3
#: Fewest board points a station must show, not all on one line (a homography needs four in
#: general position; two spare against a bad corner).
MIN_STATION_POINTS = 6


@dataclass(frozen=True)
class StationInputs:
    """What a station set holds.

    ``observations``: n items, one per station: a grey or BGR uint8 image (corners are
    detected by the board), a :class:`calib.boards.Detection` (corners with their point ids,
    partial views allowed; or ``ok=False`` with the reason a file could not be read), or
    corners of the whole board, float shape (N, 2) in the order of its point ids. Consumed
    once, so a generator keeps only one image in memory.
    ``tcp_poses``: n UR pose vectors T_base_tcp ``[x, y, z, rx, ry, rz]`` (m, rad) or None;
    None (or no pose at all) gives an intrinsics-only calibration. ``ids``: n names for reports
    (default ``000``, ``001``, ...). ``image_size``: (width, height), required when no
    observation is an image. ``intrinsics``: a known camera (K (3, 3), dist (5,)); the
    intrinsic stage is skipped and K, dist are held in the joint stage. ``setup``:
    ``eye_in_hand`` or ``eye_to_hand`` (``calib.chain.SETUPS``).
    """

    observations: Iterable[Observation]
    tcp_poses: Sequence[Sequence[float] | None] | None = None
    ids: Sequence[str] | None = None
    image_size: Sequence[int] | None = None
    intrinsics: tuple[np.ndarray, np.ndarray] | None = None
    setup: str = "eye_in_hand"

    def __post_init__(self) -> None:
        check_setup(self.setup)


@dataclass(frozen=True)
class Station:
    """One calibration station, the same from capture to solver, storage and API.

    ``id`` names it in reports (``000``, ``001``, ...). ``T_base_tcp``: the TCP pose read at the
    image, a UR pose vector (6,) ``[x, y, z, rx, ry, rz]`` (m, rad); None when unknown.
    ``image``: its pixels (grey or BGR uint8, as captured) or its file, a path relative to the
    directory that holds the station (the station set's, or the service's data directory);
    ``image_size`` (width, height) when known.
    ``detection``: what the board detection saw (None until detected). ``T_cam_target``: the
    measured camera pose (6,) of a pose-only station. ``rejected``: why the station cannot be
    used, None when it can. ``freshness``: how the capture made sure the image was exposed
    after the robot had settled (the camera's account, e.g. ``drivers.freshness``); None when
    unknown (an image that came from elsewhere).
    """

    id: str
    T_base_tcp: np.ndarray | None = None
    image: str | np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    detection: Detection | None = None
    T_cam_target: np.ndarray | None = None
    rejected: str | None = None
    freshness: str | None = None


@dataclass(frozen=True)
class Stations:
    """A station set: the setup, the board, known intrinsics (K (3, 3), dist) and the stations.

    ``target`` is the board's configuration, the one target type of ``calib.boards``
    (checkerboard or ChArUco; :func:`calib.boards.board_from_target` makes the board); None
    for pose-only sets.
    """

    setup: str
    stations: tuple[Station, ...]
    target: BoardTarget | None = None
    intrinsics: tuple[np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        if self.target is not None:  # a configuration given as data is parsed here, once
            object.__setattr__(self, "target", TargetAdapter.validate_python(self.target))

    @property
    def pose_only(self) -> bool:
        return all(s.T_cam_target is not None for s in self.stations)

    def pose_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """T_base_tcp and T_cam_target, each (n, 4, 4), of a pose-only set; validated."""
        missing = [s.id for s in self.stations if s.T_base_tcp is None]
        if missing:
            raise ValueError(f"station {missing[0]} has no tcp_pose: hand-eye needs one per "
                             "station")
        return (check_ur_poses([s.T_base_tcp for s in self.stations], "tcp_pose"),
                check_ur_poses([s.T_cam_target for s in self.stations], "target_pose"))

    def inputs(self, images: Callable[[Station], Observation] | None = None) -> StationInputs:
        """The solver's input: each station's stored detection (a rejection when its image
        size differs from the first's), or ``images(station)`` (read one at a time as the
        solver consumes them) when given."""
        sizes = [tuple(s.image_size) for s in self.stations if s.image_size is not None]
        size = sizes[0] if sizes else None

        def stored(station: Station) -> Observation | None:
            seen = None if station.image_size is None else tuple(station.image_size)
            return station.detection if seen in (None, size) else other_size(seen, size)

        observations = (stored(s) if images is None else images(s) for s in self.stations)
        return StationInputs(observations, [s.T_base_tcp for s in self.stations],
                             ids=[s.id for s in self.stations], image_size=size,
                             intrinsics=self.intrinsics, setup=self.setup)


def usable_stations(detections: list[tuple[Detection, tuple[int, int] | None]],
                     stations: StationInputs, board: Board
                     ) -> tuple[list[str], list[int], list[tuple[str, str]], tuple[int, int]]:
    """Station ids, the indices of usable stations, the rejected (id, reason) and the image
    size (width, height); ``ValueError`` when too few are usable. A station needs
    :data:`MIN_STATION_POINTS` points of ``board``, not all on one line."""
    n, tcp_poses = len(detections), stations.tcp_poses
    ids = ([f"{k:03d}" for k in range(n)] if stations.ids is None
           else [str(s) for s in stations.ids])
    if len(ids) != n or (tcp_poses is not None and len(tcp_poses) != n):
        raise ValueError(f"{n} observations but {len(ids)} station ids and "
                         f"{'no' if tcp_poses is None else len(tcp_poses)} robot poses")
    rejected: list[tuple[str, str]] = []
    size = None if stations.image_size is None else (int(stations.image_size[0]),
                                                     int(stations.image_size[1]))
    usable: list[int] = []
    for k, (det, shape) in enumerate(detections):
        if shape is not None:
            size = size or shape
            if shape != size:
                det = other_size(shape, size)
        if det.ok:
            det = _enough_points(det, board)
        if det.ok:
            usable.append(k)
        else:
            rejected.append((ids[k], det.reason or "rejected"))
    if tcp_poses is not None and any(p is not None for p in tcp_poses):
        for k in [k for k in usable if tcp_poses[k] is None]:
            rejected.append((ids[k], "no tcp_pose, while the other stations have one"))
            usable.remove(k)
    if len(usable) < MIN_IMAGES:
        why = "; ".join(f"{i}: {r}" for i, r in rejected[:3])
        raise ValueError(f"only {len(usable)} of {n} stations usable, need at least "
                         f"{MIN_IMAGES}" + (f" ({why}{'; ...' if len(rejected) > 3 else ''})"
                                            if why else ""))
    if size is None:
        raise ValueError("image_size is required when no observation is an image")
    return ids, usable, rejected, size


def other_size(shape: Sequence[int], size: Sequence[int]) -> Detection:
    """The rejection of an image of ``shape`` (width, height) in a set of ``size`` images."""
    return Detection(ok=False, reason=(
        f"image is {shape[0]}x{shape[1]}, the others {size[0]}x{size[1]}"))


def _enough_points(det: Detection, board: Board) -> Detection:
    """``det``, or a rejection when its points are too few, repeated, not the board's, or
    all on one line."""
    ids, n_board = det.ids, len(board.point_ids)
    if ids.min(initial=0) < 0 or ids.max(initial=0) >= n_board or len(set(ids)) != len(ids):
        return Detection(ok=False, reason=(
            f"point ids must be distinct board points 0..{n_board - 1}"))
    grid = board.points(ids)[:, :2]
    if len(ids) < MIN_STATION_POINTS or np.linalg.matrix_rank(
            grid - grid.mean(axis=0), tol=1e-9) < 2:
        return Detection(ok=False, reason=(
            f"only {len(ids)} board points usable, at least {MIN_STATION_POINTS} not on one "
            "line are needed"))
    return det


def detect_all(items: Iterable[Observation], board: Board, *,
                workers: int | None = None) -> list[tuple[Detection, tuple[int, int] | None]]:
    """``_detect`` over all observations on a few threads, in order.

    OpenCV's detector releases the GIL, so threads use every core. At most ``2 x workers``
    observations are in flight, so a generator of images still holds only a few in memory.
    """
    workers = workers or min(4, os.cpu_count() or 1)
    out: list[tuple[Detection, tuple[int, int] | None]] = []
    with ThreadPoolExecutor(workers) as pool:
        pending: deque[Future] = deque()
        for obs in items:
            pending.append(pool.submit(_detect, obs, board))
            if len(pending) >= 2 * workers:
                out.append(pending.popleft().result())
        out.extend(f.result() for f in pending)
    return out


def _detect(obs: Observation, board: Board) -> tuple[Detection, tuple[int, int] | None]:
    """Detection of one observation and the image size (w, h) if it was an image."""
    if isinstance(obs, Detection):
        return obs, None
    arr = np.asarray(obs)
    if arr.ndim == 2 and arr.shape[1] == 2 and np.issubdtype(arr.dtype, np.floating):
        return whole_board_detection(arr, board), None
    shape = (arr.shape[1], arr.shape[0]) if arr.ndim >= 2 else None
    return board.detect(arr), shape


def whole_board_detection(corners: np.ndarray, board: Board) -> Detection:
    """Corners (N, 2) of every point of ``board``, in the order of its point ids, as a
    detection; a rejection when they are not all there or not finite."""
    n_board = len(board.point_ids)
    if len(corners) != n_board or not np.isfinite(corners).all():
        return Detection(ok=False, reason=(
            f"{len(corners)} corners given, the board has {n_board} (or some are not "
            "finite); give a detection with point ids for a partial view"))
    return Detection(ok=True, corners=np.asarray(corners, dtype=float), ids=board.point_ids)


def check_intrinsics(K: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Known intrinsics as K (3, 3) and dist (5,); more than 5 non-zero terms are refused."""
    K, dist = np.asarray(K, dtype=float), np.asarray(dist, dtype=float).ravel()
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("intrinsics: K must be a finite 3x3 matrix with positive fx, fy")
    if len(dist) < 4 or not np.isfinite(dist).all() or np.any(dist[5:] != 0):
        raise ValueError("intrinsics: dist must be [k1, k2, p1, p2(, k3)]; terms beyond k3 "
                         "are not supported")
    return K, np.concatenate([dist, np.zeros(5)])[:5]


def poses_from_known_intrinsics(corners: list[np.ndarray], grids: list[np.ndarray],
                                 K: np.ndarray, dist: np.ndarray
                                 ) -> tuple[np.ndarray, float, np.ndarray]:
    """Per-image T_cam_target (nominal board) by PnP, σ_px and per-image RMS (n,);
    ``grids`` holds each image's board points (N_i, 3)."""
    poses, sq = [], []
    for m, grid in zip(corners, grids, strict=True):
        try:
            C, residuals = solve_pnp(grid, m, K, dist)
        except ValueError:
            raise ValueError("PnP failed with the given intrinsics: are K and dist right?"
                             ) from None
        sq.append(np.sum(residuals ** 2, axis=1))
        poses.append(C)
    total = np.concatenate(sq)
    sigma_px = float(np.sqrt(total.sum() / max(total.size * 2 - 6 * len(corners), 1)))
    return np.array(poses), sigma_px, np.sqrt(np.array([s.mean() for s in sq]))


def resolve_symmetric_origin(P: np.ndarray, C: np.ndarray, corners: list[np.ndarray],
                              grid: np.ndarray, nu: float
                              ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Put a 180°-symmetric board's origin at the same physical corner in every image.

    A camera motion rotates by the same angle as the robot motion (``A X = X B`` is a
    similarity). For each station the detected frame and the frame turned by 180° about the
    board centre are tried against the first station; the one whose motion angle agrees
    with the robot's wins. Turning the frame reverses the corner order.
    """
    centre = np.array([grid[-1, 0] * nu, grid[-1, 1], 0.0])  # far corner, nominal scale
    F = make_transform(np.diag([-1.0, -1.0, 1.0]), centre)  # T_old_new
    C, corners = C.copy(), list(corners)
    angle_A = rotation_angle((invert(P[0]) @ P[1:])[:, :3, :3])
    for k in range(1, len(C)):
        keep_err = abs(rotation_angle(C[0][:3, :3] @ C[k][:3, :3].T) - angle_A[k - 1])
        flip_err = abs(rotation_angle(C[0][:3, :3] @ (C[k] @ F)[:3, :3].T) - angle_A[k - 1])
        if flip_err < keep_err:
            C[k] = C[k] @ F
            corners[k] = corners[k][::-1].copy()
    return C, corners
