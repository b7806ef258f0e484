"""Station planning: robot poses that show the board well and determine the hand-eye.

Pure geometry, no I/O. Frames follow ``docs/conventions.md``; the two guesses a plan needs are
the two unknowns of the calibration, in the result's own convention:

============  ==========================  ===========================================
setup         ``hand_eye_guess``          ``target_pose_guess``
============  ==========================  ===========================================
eye-in-hand   T_tcp_cam (camera on tool)  T_base_target (board fixed in the cell)
eye-to-hand   T_base_cam (fixed camera)   T_tcp_target (board carried by the tool)
============  ==========================  ===========================================

Rough values are enough (a CAD guess for the hand-eye, :func:`rough_target_from_image` for
the target): the plan keeps a margin around the board in the image.

Every station is first chosen as a *view* ``T_cam_target``: the camera looks at a point near
the pattern centre along the board normal tilted by up to ``max_tilt_deg`` about an in-plane
axis (axes spread around the circle, so the motions between stations rotate about varied
axes), rolled about its optical axis, from a distance in ``distance_band``. A view is kept when
the whole board projects inside the image with a margin and its tcp pose lies in the workspace
box. The stations are then ordered for short travel, and a plan whose motions could not
determine the hand-eye (Chen: two non-parallel screw axes) is refused before the robot moves.

On request (``PlanOptions.cut_fraction``, for boards read in partial views such as ChArUco) a
share of the stations instead *cut* the board at the image border on purpose: their look-at
point ranges over the whole board, and a view is kept when some points fall outside the image
while at least ``min_cut_points`` stay inside and one of those lies near an image corner
(:func:`cuts_board_at_corner`). Those are the points that decide the lens distortion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from calib import so3
from calib.boards import Board
from calib.camera import Pinhole, solve_pnp
from calib.chain import (
    camera_from_robot,
    check_motion_diversity,
    check_setup,
    robot_from_camera,
    target_from_station,
    tool_side_motions,
)
from calib.geometry import check_transforms, invert, make_transform, rotation_angle
from calib.handeye import MIN_STATIONS

#: Metres of travel one radian of tool rotation is worth when ordering stations.
ROTATION_WEIGHT_M_PER_RAD = 0.1
#: A plan's motion axes must spread at least this much (stricter than the solver's 2 deg:
#: a plan should be well conditioned, not merely solvable).
MIN_PLAN_AXIS_SPREAD_DEG = 10.0
#: Largest view tilt accepted: beyond it corners foreshorten too much to detect reliably.
MAX_TILT_LIMIT_DEG = 70.0
#: Candidate views tried per station before the request is declared infeasible.
_ATTEMPTS_PER_STATION = 300
#: Look-at points are jittered by this fraction of the pattern's half extent.
_LOOK_AT_JITTER = 0.2
#: Smallest cosine between the start camera's optical axis and the board normal.
_MIN_START_FACING = 0.2
#: A cut view shows a point within this fraction of the smaller image side of an image corner.
CORNER_REACH_FRAC = 0.15
#: Points of a cut view count as in view this fraction of the smaller image side inside it.
_CUT_MARGIN_FRAC = 0.01


@dataclass(frozen=True)
class Plan:
    """Stations in visiting order.

    ``tcp_poses`` (n, 4, 4) are the T_base_tcp to command, ``views`` (n, 4, 4) the
    T_cam_target expected at each station under the guesses, ``travel`` the path length from
    the start through all stations: metres plus ``ROTATION_WEIGHT_M_PER_RAD`` times radians
    (:func:`path_length`).
    """

    tcp_poses: np.ndarray
    views: np.ndarray
    travel: float


@dataclass(frozen=True)
class CellGuess:
    """What a plan assumes about the cell, in the result's own convention (module docstring).

    ``start_tcp_pose`` (4, 4) is T_base_tcp where the robot is now (the tour starts here and
    the views' roll is measured from the start view's); ``hand_eye`` and ``target_pose``
    (4, 4) are the rough unknowns (``target_pose`` None until :func:`rough_target_from_image`
    found it).
    """

    start_tcp_pose: np.ndarray
    hand_eye: np.ndarray
    target_pose: np.ndarray | None = None
    setup: str = "eye_in_hand"


@dataclass(frozen=True)
class PlanOptions:
    """What the views must satisfy, checked on construction (``ValueError`` saying what to change).

    ``image_size`` (width, height) pixels; ``distance_band`` (near, far) metres from the camera
    to the look-at point on the board; ``workspace`` (lo, hi), each (3,), the box in the base
    frame the tcp positions must lie in; ``max_tilt_deg`` the largest angle between the optical
    axis and the board normal; ``max_roll_deg`` the largest roll about the optical axis relative
    to the start view; ``margin_frac`` the free image border around the board, as a fraction of
    the smaller image side; ``rng`` a generator or seed. ``cut_fraction`` of the stations cut
    the board at the image border on purpose (module docstring), each keeping at least
    ``min_cut_points`` points in view; only for boards read in partial views.
    """

    image_size: tuple[int, int]
    distance_band: tuple[float, float]
    workspace: tuple[ArrayLike, ArrayLike]
    max_tilt_deg: float = 35.0
    max_roll_deg: float = 90.0
    margin_frac: float = 0.04
    rng: np.random.Generator | int | None = None
    cut_fraction: float = 0.0
    min_cut_points: int = 12

    def __post_init__(self) -> None:
        if not 0.0 <= self.cut_fraction <= 1.0:
            raise ValueError(f"cut_fraction must be in [0, 1], got {self.cut_fraction}")
        if self.min_cut_points < 6:
            raise ValueError(f"min_cut_points must be at least 6 (a camera pose needs them), "
                             f"got {self.min_cut_points}")
        if not 0.0 < self.max_tilt_deg <= MAX_TILT_LIMIT_DEG:
            raise ValueError(f"max_tilt_deg must be in (0, {MAX_TILT_LIMIT_DEG:g}], got "
                             f"{self.max_tilt_deg}: tilted views are what make the hand-eye "
                             "solvable")
        near, far = (float(d) for d in self.distance_band)
        if not 0.0 < near <= far:
            raise ValueError(f"distance_band must be (near, far) metres with 0 < near <= far, "
                             f"got {self.distance_band}")
        lo, hi = self.box()
        if not (lo < hi).all():
            raise ValueError(f"workspace must be (lo, hi) with lo < hi on every axis, got "
                             f"lo={lo.tolist()}, hi={hi.tolist()}")
        if len(self.image_size) != 2 or min(self.image_size) <= 0:
            raise ValueError(f"image_size must be (width, height) in pixels, got "
                             f"{self.image_size}")

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The workspace corners lo, hi as float arrays (3,)."""
        lo, hi = (np.asarray(b, dtype=float).reshape(3) for b in self.workspace)
        return lo, hi


def plan_stations(n: int, guess: CellGuess, camera: Pinhole, board: Board,
                  options: PlanOptions) -> Plan:
    """Plan ``n`` calibration stations; refuse requests that would give a degenerate plan.

    Parameters
    ----------
    n : number of stations, at least ``MIN_STATIONS``.
    guess : the start pose and the rough unknowns (``target_pose`` required).
    camera : approximate intrinsics (distortion may be zero).
    board : inner corners (cols, rows) and nominal square size (m).
    options : the constraints on the views, and the random generator.

    Raises
    ------
    ValueError
        Saying what to change: too few stations, bad options, a start pose that does not face
        the board, a board or workspace that cannot fit the views, or parallel motion axes.
    """
    if n < MIN_STATIONS:
        raise ValueError(f"a plan needs at least {MIN_STATIONS} stations to determine the "
                         f"hand-eye, got {n}: ask for more stations (10-20 is typical)")
    guess, camera = _checked(guess, camera)
    rng = np.random.default_rng(options.rng)
    grid = board.points()
    centre = grid[[0, -1]].mean(axis=0)
    half_extent = grid[-1] - centre
    outline = board.outline()
    P0, X, Y, setup = guess.start_tcp_pose, guess.hand_eye, guess.target_pose, guess.setup
    roll0 = _start_roll(camera_from_robot(P0, X, Y, setup))
    lo, hi = options.box()

    views: list[np.ndarray] = []
    tcps: list[np.ndarray] = []
    for k in range(n):
        in_view = 0
        cut = np.floor((k + 1) * options.cut_fraction) > np.floor(k * options.cut_fraction)
        for _ in range(_ATTEMPTS_PER_STATION):
            azimuth = 2.0 * np.pi * (k + rng.uniform()) / n
            tilt = np.deg2rad(options.max_tilt_deg) * np.sqrt(rng.uniform(0.1, 1.0))
            roll = roll0 + np.deg2rad(options.max_roll_deg) * rng.uniform(-1.0, 1.0)
            jitter = 1.0 if cut else _LOOK_AT_JITTER
            look_at = centre + jitter * half_extent * rng.uniform(-1.0, 1.0, 3)
            C = look_at_view(look_at, tilt, azimuth, roll, rng.uniform(*options.distance_band))
            if not (_cuts_board(C, grid, camera, options) if cut
                    else _board_in_view(C, outline, camera, options)):
                continue
            in_view += 1
            P = robot_from_camera(C, X, Y, setup)
            if (P[:3, 3] >= lo).all() and (P[:3, 3] <= hi).all():
                views.append(C)
                tcps.append(P)
                break
        else:
            raise ValueError(_infeasible_message(k, n, in_view > 0, options))

    P_all, C_all = np.array(tcps), np.array(views)
    try:
        check_motion_diversity(tool_side_motions(P_all, C_all, setup),
                               min_spread_deg=MIN_PLAN_AXIS_SPREAD_DEG)
    except ValueError as err:
        raise ValueError(f"planned stations would not determine the hand-eye ({err}); "
                         "raise max_tilt_deg or the number of stations") from None
    order = order_for_travel(P0, P_all)
    return Plan(tcp_poses=P_all[order], views=C_all[order],
                travel=path_length(P0, P_all[order]))


def _checked(guess: CellGuess, camera: Pinhole) -> tuple[CellGuess, Pinhole]:
    """The guess and camera validated and as float arrays (``ValueError`` naming the problem)."""
    check_setup(guess.setup)
    if guess.target_pose is None:
        raise ValueError("target_pose_guess is required: see rough_target_from_image")
    K = np.asarray(camera.K, dtype=float)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("K must be a finite 3x3 camera matrix with positive focal lengths")
    dist = np.zeros(5) if camera.dist is None else np.asarray(camera.dist, dtype=float)
    return CellGuess(start_tcp_pose=check_transforms(guess.start_tcp_pose, "start_tcp_pose")[0],
                     hand_eye=check_transforms(guess.hand_eye, "hand_eye_guess")[0],
                     target_pose=check_transforms(guess.target_pose, "target_pose_guess")[0],
                     setup=guess.setup), Pinhole(K, dist)


def rough_target_from_image(corners: np.ndarray, camera: Pinhole, board: Board,
                            guess: CellGuess, point_ids: np.ndarray | None = None
                            ) -> np.ndarray:
    """Rough target pose from one detection at the start pose, for :func:`plan_stations`.

    ``solvePnP`` of the nominal board gives T_cam_target, closed through the chain:
    T_base_target = ``P X C`` eye-in-hand, T_tcp_target = ``inv(P) X C`` eye-to-hand
    (``docs/conventions.md``). Approximate intrinsics are fine: errors of a few percent in
    focal length move the board by a few percent of its distance, which the plan's margin
    absorbs.

    Parameters
    ----------
    corners : shape (N, 2), detected corners of the points ``point_ids``.
    camera : approximate intrinsics (distortion may be zero or None).
    board : the printed target.
    guess : the start pose T_base_tcp when the image was taken, and the hand-eye guess
        T_tcp_cam (eye-in-hand) or T_base_cam (eye-to-hand); its target pose is not used.
    point_ids : shape (N,), the board point ids of ``corners`` (a partial view); default all.

    Returns
    -------
    target_pose : shape (4, 4), T_base_target (eye-in-hand) or T_tcp_target (eye-to-hand).
    """
    check_setup(guess.setup)
    obj = board.points(point_ids)
    img = np.asarray(corners, dtype=float).reshape(-1, 2)
    if img.shape[0] != obj.shape[0]:
        raise ValueError(f"got {img.shape[0]} corners for {obj.shape[0]} board points")
    P = check_transforms(guess.start_tcp_pose, "start_tcp_pose")[0]
    X = check_transforms(guess.hand_eye, "hand_eye_guess")[0]
    try:
        C, _ = solve_pnp(obj, img, camera.K, camera.dist)
    except ValueError:
        raise ValueError("solvePnP failed on the detected corners: check K and the target "
                         "configuration") from None
    return target_from_station(P, X, C, guess.setup)


def look_at_view(look_at: np.ndarray, tilt: float, azimuth: float, roll: float,
                 distance: float) -> np.ndarray:
    """T_cam_target, shape (4, 4), of a camera ``distance`` m from ``look_at`` (target frame).

    The optical axis is the board normal +z (which points away from a camera seeing the
    front) tilted by ``tilt`` rad about the in-plane axis at ``azimuth`` rad from x; at zero
    tilt the camera x axis is at angle ``roll`` from the board x axis.
    """
    tilt_axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    R_target_cam = so3.exp(tilt * tilt_axis) @ so3.exp(np.array([0.0, 0.0, roll]))
    origin = np.asarray(look_at, dtype=float) - distance * R_target_cam[:, 2]
    return invert(make_transform(R_target_cam, origin))


def travel_cost(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """Combined distance between poses (..., 4, 4): metres + weight x rotation angle (rad)."""
    dR = np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_b[..., :3, :3]
    return (np.linalg.norm(T_b[..., :3, 3] - T_a[..., :3, 3], axis=-1)
            + ROTATION_WEIGHT_M_PER_RAD * rotation_angle(dR))


def path_length(start: np.ndarray, poses: np.ndarray) -> float:
    """Total :func:`travel_cost` from ``start`` (4, 4) through ``poses`` (n, 4, 4) in order."""
    path = np.concatenate([np.asarray(start)[None], poses])
    return float(travel_cost(path[:-1], path[1:]).sum())


def order_for_travel(start: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Greedy nearest-neighbour visiting order of ``poses`` (n, 4, 4) from ``start``, (n,) int."""
    left = list(range(len(poses)))
    order: list[int] = []
    here = np.asarray(start)
    while left:
        nxt = left[int(np.argmin(travel_cost(here, poses[left])))]
        order.append(nxt)
        left.remove(nxt)
        here = poses[nxt]
    return np.array(order, dtype=int)


def _start_roll(C0: np.ndarray) -> float:
    """Roll (rad) of the start view: angle of the camera x axis in the board plane."""
    R_target_cam = C0[:3, :3].T
    if R_target_cam[2, 2] < _MIN_START_FACING or C0[2, 3] <= 0.0:
        raise ValueError(
            "at the start pose the camera does not face the front of the board under the "
            "given guesses: check target_pose_guess, hand_eye_guess and setup, or move the "
            "robot so that the camera sees the board")
    x = R_target_cam[:, 0]
    return float(np.arctan2(x[1], x[0]))


def _board_in_view(C: np.ndarray, outline: np.ndarray, camera: Pinhole,
                   options: PlanOptions) -> bool:
    """Whether the outline projects in front of the camera and inside the image margin."""
    in_cam = outline @ C[:3, :3].T + C[:3, 3]
    if (in_cam[:, 2] <= 0.0).any():
        return False
    uv = camera.project(in_cam)
    w, h = options.image_size
    m = options.margin_frac * min(w, h)
    return bool((uv >= m).all() and (uv <= [w - m, h - m]).all())


def _cuts_board(C: np.ndarray, grid: np.ndarray, camera: Pinhole,
                options: PlanOptions) -> bool:
    """Whether view ``C`` cuts the board of points ``grid`` (N, 3) as a cut station should."""
    in_cam = grid @ C[:3, :3].T + C[:3, 3]
    uv = np.full((len(grid), 2), np.nan)
    front = in_cam[:, 2] > 0.0
    uv[front] = camera.project(in_cam[front])
    return cuts_board_at_corner(uv, options.image_size, options.min_cut_points)


def cuts_board_at_corner(uv: np.ndarray, image_size: tuple[int, int], min_points: int) -> bool:
    """Whether projected points ``uv`` (N, 2), NaN for points behind the camera, cut the board.

    True when some points fall outside the image, at least ``min_points`` lie inside it (by
    ``_CUT_MARGIN_FRAC`` of the smaller side), and one of those is within
    ``CORNER_REACH_FRAC`` of the smaller image side from an image corner.
    """
    w, h = image_size
    margin_px = _CUT_MARGIN_FRAC * min(w, h)
    with np.errstate(invalid="ignore"):
        inside = ((uv >= margin_px) & (uv <= [w - margin_px, h - margin_px])).all(axis=1)
    if inside.all() or inside.sum() < min_points:
        return False
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    reach = np.linalg.norm(uv[inside][:, None] - corners[None], axis=-1).min()
    return bool(reach <= CORNER_REACH_FRAC * min(w, h))


def _infeasible_message(k: int, n: int, views_fit: bool, options: PlanOptions) -> str:
    """Why station ``k`` could not be placed (``views_fit``: some views showed the board but
    their tcp poses left the workspace), and what to change."""
    band, (lo, hi) = options.distance_band, options.box()
    head = f"could place only {k} of {n} stations"
    if views_fit:
        box = " x ".join(f"[{a:.3f}, {b:.3f}]" for a, b in zip(lo, hi, strict=True))
        return (f"{head}: the workspace box {box} m is too small to fit the views (tcp poses "
                "outside it): enlarge the workspace, bring the board closer to its centre, or "
                "shorten the distance band")
    return (f"{head}: the board does not fit in the image with its margin at "
            f"{band[0]:.3f}-{band[1]:.3f} m: increase the distance band, or lower "
            "max_tilt_deg or max_roll_deg")
