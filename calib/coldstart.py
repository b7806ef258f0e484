"""A first estimate of the whole cell from a few small robot motions, with no guess needed.

What a cold start knows: the board, the setup, the image size and the robot's readings. From
a handful of views taken a few degrees apart (``calib.explorer``) this module estimates the
focal length, the hand-eye and the board pose, and then keeps the estimate up to date as
stations arrive (:func:`refit`).

The focal length is the one unknown that per-image PnP cannot fix on its own: near a
fronto-parallel view, focal length and distance trade off. The robot's motions break the
trade: a tool rotation by θ turns the camera by the same θ (Chen: the angles of ``A`` and
``B`` in ``A X = X B`` are equal), which moves the image by about ``f tan θ`` pixels, while the
board's size in the image fixes ``f / Z``. So for a few focal lengths the views'
PnP poses (principal point at the image centre, no distortion: Zhang's usual start) go through
the screw-motion solver (``calib.handeye``, SM) gives a start, and from a few such starts
spread over the plausible focal lengths the joint maximum likelihood (``calib.joint``) over
the focal lengths, principal point, k1, the hand-eye and the board pose (the rest held)
converges; the fit that reprojects best wins.

Guesses (a CAD hand-eye, a focal length from a data sheet) are *priors*: each enters as one
more start, and it is kept only if its fit to the images is as good as the blind one's. A wrong
guess loses and is reported (:attr:`Bootstrap.rejected_guess`), so a guess can never make a
run worse than no guess.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from calib.boards import Board
from calib.camera import solve_pnp
from calib.chain import robot_chain, target_from_station
from calib.handeye import average_transform, calibrate_hand_eye
from calib.joint import CAMERA_PARAMS, CellParameters, CornerStations, JointOptions, solve_joint
from calib.peers import solve_opencv

#: Focal lengths the joint fit starts from, as multiples of the image width (horizontal
#: fields of view from about 120° to 30°): from any of them the fit usually finds the
#: true one, so a handful is plenty and guards against the odd local minimum.
FOCAL_STARTS = (0.8, 0.55, 1.2, 0.3, 1.8)
#: A fit from a start that reprojects within this RMS (px) ends the search (a few times the
#: corner noise of a sharp image: a wrong focal length or hand-eye leaves whole pixels).
GOOD_FIT_PX = 0.25
#: Evaluations per joint fit from a start.
MAX_NFEV = 150
#: Corner noise assumed by the bootstrap fits, px per coordinate.
SIGMA_PX = 0.3
#: A guess is kept when its fit's RMS is within this factor of the blind fit's.
GUESS_SLACK = 1.2
#: Camera parameters free at each stage: by the number of views (at least), the free names.
_STAGES = ((0, ("fx", "fy", "cx", "cy", "k1")),
           (6, ("fx", "fy", "cx", "cy", "k1")),
           (9, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "kappa")))


@dataclass(frozen=True)
class View:
    """One image of the board: the robot's reading ``T_base_tcp`` (4, 4), the detected
    ``corners`` (N, 2) and their board point ``ids`` (N,)."""

    T_base_tcp: np.ndarray
    corners: np.ndarray
    ids: np.ndarray


@dataclass(frozen=True)
class Guess:
    """Optional priors: ``hand_eye`` (4, 4) in the setup's convention, ``focal_px``."""

    hand_eye: np.ndarray | None = None
    focal_px: float | None = None


@dataclass(frozen=True)
class Bootstrap:
    """The cell as estimated so far.

    ``cell`` the camera (K, dist), board κ, ν, hand-eye and target pose; ``rms_px`` the
    reprojection RMS of the chain through it; ``covariance`` (23, 23) over
    ``calib.joint.GLOBAL_PARAMS`` (formal, from the joint fit); ``free`` the camera parameters
    that were estimated; ``rejected_guess`` why a given guess was ignored (None if it was
    used or none was given).
    """

    cell: CellParameters
    rms_px: float
    covariance: np.ndarray
    free: tuple[str, ...]
    rejected_guess: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)


def bootstrap(views: Sequence[View], board: Board, image_size: tuple[int, int], setup: str,
              guess: Guess | None = None) -> Bootstrap:
    """First estimate of the cell from views at least two of which rotate about different
    axes (module docstring). Raises ``ValueError`` when no focal length explains the views."""
    if len(views) < 3:
        raise ValueError(f"a cold start needs at least 3 views, got {len(views)}")
    guess = guess or Guess()
    starts = [start for f in FOCAL_STARTS
              if (start := _screw_start(views, board, centred_camera(f * image_size[0],
                                                                     image_size), setup,
                                        None)) is not None]
    if not starts:
        raise ValueError("no focal length explains the first views: the motions may be too "
                         "small or about one axis only")
    blind = _best(views, board, setup, starts)
    if guess.hand_eye is None and guess.focal_px is None:
        return blind
    f = guess.focal_px or float(blind.cell.K[0, 0])
    guided = _screw_start(views, board, centred_camera(f, image_size), setup, guess.hand_eye)
    fit = None if guided is None else _best(views, board, setup, [guided])
    if fit is not None and fit.rms_px <= GUESS_SLACK * blind.rms_px:
        return fit
    why = (f"the configured guess does not fit the first {len(views)} images (chain RMS "
           f"{'n/a' if fit is None else f'{fit.rms_px:.2f}'} px against {blind.rms_px:.2f} px "
           f"without it; focal length {f:.0f} px against {blind.cell.K[0, 0]:.0f} px): ignored")
    return Bootstrap(**{**vars(blind), "rejected_guess": why})


def refit(views: Sequence[View], board: Board, setup: str, previous: Bootstrap) -> Bootstrap:
    """The estimate updated with all ``views``, freeing more of the camera as views accrue."""
    return _best(views, board, setup, [previous.cell])


def free_camera_params(n_views: int) -> tuple[str, ...]:
    """The camera parameters a fit of ``n_views`` views estimates (the rest held)."""
    return next(names for at_least, names in reversed(_STAGES) if n_views >= at_least)


def _best(views: Sequence[View], board: Board, setup: str,
          starts: Sequence[CellParameters]) -> Bootstrap:
    """The joint fit from each start, the one with the lowest reprojection RMS."""
    free = free_camera_params(len(views))
    fix = tuple(name for name in CAMERA_PARAMS if name not in free)
    stations = CornerStations([v.corners for v in views], np.stack([v.T_base_tcp for v in views]),
                              board, [v.ids for v in views])
    best = None
    for start in starts:
        try:
            res = solve_joint(stations, start, JointOptions(
                sigma_px=SIGMA_PX, setup=setup, fix=fix, outlier_sigma=None, max_nfev=MAX_NFEV))
        except (ValueError, np.linalg.LinAlgError):
            continue
        if not np.isfinite(res.rms_px) or res.K[0, 0] <= 0:
            continue
        if best is None or res.rms_px < best.rms_px:
            best = res
        if best.rms_px <= GOOD_FIT_PX:
            break
    if best is None:
        raise ValueError("the joint fit of the first views failed from every start")
    cell = CellParameters(K=best.K, dist=best.dist, nu=best.nu, kappa=best.kappa,
                          hand_eye=best.hand_eye, target_pose=best.target_pose)
    return Bootstrap(cell=cell, rms_px=float(best.rms_px), covariance=best.covariance,
                     free=free)


def centred_camera(f: float, image_size: tuple[int, int]) -> np.ndarray:
    """K (3, 3) of focal length ``f`` px with the principal point at the image centre."""
    w, h = image_size
    return np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])


def _screw_start(views: Sequence[View], board: Board, K: np.ndarray, setup: str,
                 hand_eye: np.ndarray | None) -> CellParameters | None:
    """Start values with camera ``K``: per-view PnP, then SM (or the given hand-eye)."""
    P = np.stack([v.T_base_tcp for v in views])
    try:
        C = np.stack([solve_pnp(board.points(v.ids), v.corners, K)[0] for v in views])
        if hand_eye is not None:
            X = np.asarray(hand_eye, dtype=float)
        else:
            X = _screw_hand_eye(P, C, setup)
        Y = average_transform(target_from_station(P, X, C, setup))
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not (np.isfinite(X).all() and np.isfinite(Y).all()):
        return None
    return CellParameters(K=K, dist=np.zeros(5), nu=1.0, kappa=1.0, hand_eye=X, target_pose=Y)


def _screw_hand_eye(P: np.ndarray, C: np.ndarray, setup: str) -> np.ndarray:
    """The hand-eye by SM, or by Park's solver (OpenCV) when SM finds the motions' rotations
    too small against their noise (a few degrees seen from far away)."""
    try:
        return calibrate_hand_eye(P, C, setup=setup, method="sm").hand_eye
    except ValueError:
        X, _ = solve_opencv(robot_chain(P, setup), C, "park")
        return X


def camera_position(T_base_tcp: np.ndarray, hand_eye: np.ndarray, setup: str) -> np.ndarray:
    """Where the camera is in the base frame, (3,): ``P X`` eye-in-hand, ``X`` eye-to-hand."""
    if setup == "eye_in_hand":
        return (robot_chain(T_base_tcp, setup) @ hand_eye)[:3, 3]
    return np.asarray(hand_eye, dtype=float)[:3, 3]
