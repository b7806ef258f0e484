"""The next station chosen by what it teaches: candidate views scored by predicted uncertainty.

Given the current estimate of the cell (``calib.coldstart``), candidate views are drawn around
the board (``calib.planning.look_at_view``: tilt, azimuth, roll, distance, look-at point)
within a *reach* that grows as the estimate firms up (:class:`Reach`), and as small tool moves
from the last good pose. A candidate is feasible
when, under the estimate, the whole board projects inside the image with a margin, the view is
not too oblique, its tcp (and, eye-in-hand, its camera, along the whole move) stays inside the
safety box by a margin, the move from the last good pose is within the reach's step, and it is
not near a view where the board was already lost.

Each feasible candidate is scored by the covariance the joint model (``calib.joint``) would
have with it added: the Fisher information of the joint problem with the station corrections
eliminated adds up over stations (``JointProblem.reduced_information``), so one evaluation of
all candidates' corner Jacobians and a 23 x 23 inverse per candidate predict
``(S_sofar + S_candidate + S_prior)⁻¹``. The score is the hand-eye's variance in units of the
tolerance (rotation and translation), plus the focal length and principal point's in units of
``INTRINSICS_TOLERANCE``: the A-optimal design criterion restricted to what the user asked
for. The candidate with the lowest score is visited; it is a fresh draw every step, not a
fixed pattern.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib import so3
from calib.boards import Board
from calib.camera import Pinhole
from calib.chain import camera_from_robot, robot_from_camera
from calib.geometry import rotation_angle
from calib.joint import GLOBAL_PARAMS, CellParameters, JointOptions, JointProblem
from calib.planning import look_at_view

#: Corner noise the predictions assume, px per coordinate.
SIGMA_PX = 0.2
#: Weak prior σ per global parameter, so few stations give a finite covariance: fx fy cx cy
#: (px), k1 k2 p1 p2 k3, ν, κ, then hand-eye and target pose (rad, m).
_PRIOR_SIGMA = np.array([2000.0, 2000.0, 300.0, 300.0, 1.0, 1.0, 0.05, 0.05, 0.05, 0.02, 0.02,
                         *[3.0] * 3, *[2.0] * 3, *[3.0] * 3, *[2.0] * 3])
#: Relative focal-length / principal-point σ that counts as much as the hand-eye tolerance.
INTRINSICS_TOLERANCE = 1e-3
#: Views closer than this to a view where the board was lost are not tried (rad, m).
FAILED_NEAR = (np.deg2rad(6.0), 0.03)
#: The camera's least margin inside the safety box (its position comes from the estimate), m.
CAMERA_MARGIN_M = 0.03
#: Points of a move at which the camera's position is checked.
PATH_SAMPLES = 6
_HAND_EYE = slice(GLOBAL_PARAMS.index("hand_eye_rx"), GLOBAL_PARAMS.index("hand_eye_rx") + 3)
_HAND_EYE_T = slice(_HAND_EYE.stop, _HAND_EYE.stop + 3)


@dataclass(frozen=True)
class Reach:
    """How bold the next view may be: ``max_tilt_deg`` from the board normal, ``band`` the
    (near, far) camera distance (m), ``max_roll_deg`` about the optical axis from the start
    view, ``step`` the largest (rotation rad, translation m) tool move from the last good pose,
    ``margin_frac`` the free image border as a fraction of the smaller side,
    ``camera_margin`` (m) the camera's distance inside the box (eye-in-hand), ``draws`` the
    candidates drawn."""

    max_tilt_deg: float
    band: tuple[float, float]
    max_roll_deg: float
    step: tuple[float, float]
    margin_frac: float
    camera_margin: float = 0.03
    draws: int = 300


@dataclass(frozen=True)
class History:
    """Where the robot has been: ``visited`` (n, 4, 4) the readings T_base_tcp of the good
    views, ``last_good`` (4, 4) the last of them (moves are measured from it), ``failed``
    (k, 4, 4) commanded poses where the board was not detected."""

    visited: np.ndarray
    last_good: np.ndarray
    failed: np.ndarray


@dataclass(frozen=True)
class Scene:
    """What the choice needs that does not change: ``board``, ``setup``, ``image_size``
    (w, h), the safety box ``box`` (lo (3,), hi (3,)), the ``tolerance`` (rad, m) and the
    roll (rad) of the camera's x axis in the board plane at the start, ``start_roll``."""

    board: Board
    setup: str
    image_size: tuple[int, int]
    box: tuple[np.ndarray, np.ndarray]
    tolerance: tuple[float, float]
    start_roll: float = 0.0


@dataclass(frozen=True)
class Choice:
    """The chosen view: ``T_base_tcp`` (4, 4) to command, the ``predicted`` σ (rot rad,
    trans m, root-sum-square over the axes) of the hand-eye with it, and how many candidates
    were ``drawn`` and ``feasible``."""

    T_base_tcp: np.ndarray
    predicted: tuple[float, float]
    drawn: int
    feasible: int


def station_information(cell: CellParameters, T_base_tcp: np.ndarray, board: Board,
                        model: JointOptions) -> np.ndarray:
    """Reduced Fisher information of each station (k, 23, 23), the station's own correction
    eliminated, at the estimate ``cell`` under the joint ``model`` (setup, corner and robot
    noise; the planner's is ``SIGMA_PX`` and the default robot noise). The corner Jacobian
    does not depend on where the corners were seen, so none are needed."""
    T = np.asarray(T_base_tcp, dtype=float).reshape(-1, 4, 4)
    grid = board.points()[:, :2]
    problem = JointProblem([grid] * len(T), [np.zeros_like(grid)] * len(T), T, cell, model)
    _, blocks = problem.evaluate(problem.x0())  # (m, 2, 23 + 6)
    per_corner = np.einsum("mki,mkj->mij", blocks, blocks)
    A = np.add.reduceat(per_corner, problem.starts, axis=0)  # (k, 29, 29)
    g = problem.n_free_global
    V = A[:, g:, g:] + np.diag(1.0 / problem.prior_sigma ** 2)
    W = A[:, :g, g:]
    return A[:, :g, :g] - W @ np.linalg.solve(V, np.swapaxes(W, 1, 2))


def prior_information() -> np.ndarray:
    """The weak prior's information (23, 23) (``_PRIOR_SIGMA``)."""
    return np.diag(1.0 / _PRIOR_SIGMA ** 2)


def hand_eye_sigma(covariance: np.ndarray) -> tuple[float, float]:
    """Root-sum-square σ of the hand-eye rotation (rad) and translation (m) of a covariance
    (23, 23) over ``GLOBAL_PARAMS``."""
    d = np.clip(np.diag(covariance), 0.0, None)
    return float(np.sqrt(d[_HAND_EYE].sum())), float(np.sqrt(d[_HAND_EYE_T].sum()))


def choose_view(cell: CellParameters, scene: Scene, reach: Reach, history: History,
                rng: np.random.Generator) -> Choice | None:
    """The feasible candidate that most reduces the predicted uncertainty (module
    docstring), or None when no drawn candidate is feasible."""
    P = np.concatenate([_candidates(cell, scene, reach, rng),
                        _nearby(history.last_good, reach, rng)])
    keep = _feasible(P, cell, scene, reach, history)
    if not keep.any():
        return None
    P_ok = P[keep]
    model = JointOptions(sigma_px=SIGMA_PX, setup=scene.setup)
    S0 = station_information(cell, history.visited, scene.board, model).sum(axis=0) \
        + prior_information()
    S_c = station_information(cell, P_ok, scene.board, model)
    cov = np.linalg.inv(S0[None] + S_c)
    rot_tol, trans_tol = scene.tolerance
    d = np.einsum("kii->ki", cov)
    f = cell.K[0, 0]
    score = (d[:, _HAND_EYE].sum(axis=1) / rot_tol ** 2
             + d[:, _HAND_EYE_T].sum(axis=1) / trans_tol ** 2
             + d[:, 0:4].sum(axis=1) / (INTRINSICS_TOLERANCE * f) ** 2)
    best = int(np.argmin(score))
    return Choice(T_base_tcp=P_ok[best], predicted=hand_eye_sigma(cov[best]), drawn=len(P),
                  feasible=int(keep.sum()))


def _candidates(cell: CellParameters, scene: Scene, reach: Reach, rng: np.random.Generator
                ) -> np.ndarray:
    """``reach.draws`` candidate tcp poses (n, 4, 4) for views around the board in reach."""
    n = reach.draws
    grid = scene.board.points()
    centre = grid[[0, -1]].mean(axis=0)
    half = grid[-1] - centre
    tilt = np.deg2rad(reach.max_tilt_deg) * np.sqrt(rng.uniform(0.0, 1.0, n))
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    roll = scene.start_roll + np.deg2rad(reach.max_roll_deg) * rng.uniform(-1, 1, n)
    dist = rng.uniform(*reach.band, n)
    look = centre + 0.25 * half * rng.uniform(-1.0, 1.0, (n, 3))
    C = np.stack([look_at_view(look[k], tilt[k], azimuth[k], roll[k], dist[k])
                  for k in range(n)])
    return robot_from_camera(C, cell.hand_eye, cell.target_pose, scene.setup)


def _nearby(last_good: np.ndarray, reach: Reach, rng: np.random.Generator) -> np.ndarray:
    """``reach.draws // 2`` tcp poses (n, 4, 4) within a step of the last good pose: small
    tool rotations and translations, so a plan that must tread carefully still has views."""
    n = reach.draws // 2
    rot = rng.normal(size=(n, 3))
    rot *= (reach.step[0] * rng.uniform(0.2, 1.0, n) / np.linalg.norm(rot, axis=1))[:, None]
    move = rng.normal(size=(n, 3))
    move *= (reach.step[1] * rng.uniform(0.0, 1.0, n) / np.linalg.norm(move, axis=1))[:, None]
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = so3.exp(rot)
    T[:, :3, 3] = move
    return last_good @ T


def start_roll(C0: np.ndarray) -> float:
    """Roll (rad) of the camera x axis in the board plane of view C0 = T_cam_target (4, 4)."""
    x = C0[:3, :3].T[:, 0]
    return float(np.arctan2(x[1], x[0]))


def _feasible(P: np.ndarray, cell: CellParameters, scene: Scene, reach: Reach,
              history: History) -> np.ndarray:
    """Which candidates (k, 4, 4) satisfy every condition of the module docstring, (k,)."""
    C = camera_from_robot(P, cell.hand_eye, cell.target_pose, scene.setup)
    ok = _board_in_view(C, cell, scene, reach.margin_frac)
    lo, hi = scene.box
    margin = 0.01
    ok &= ((P[:, :3, 3] >= lo + margin) & (P[:, :3, 3] <= hi - margin)).all(axis=1)
    if scene.setup == "eye_in_hand":
        ok &= _camera_path_inside(P, history.last_good, cell.hand_eye, scene.box,
                                  reach.camera_margin)
    last = history.last_good
    ok &= rotation_angle(np.swapaxes(last[:3, :3], -1, -2) @ P[:, :3, :3]) <= reach.step[0]
    ok &= np.linalg.norm(P[:, :3, 3] - last[:3, 3], axis=1) <= reach.step[1]
    for F in history.failed:
        near_rot = rotation_angle(np.swapaxes(F[:3, :3], -1, -2) @ P[:, :3, :3]) < FAILED_NEAR[0]
        near_pos = np.linalg.norm(P[:, :3, 3] - F[:3, 3], axis=1) < FAILED_NEAR[1]
        ok &= ~(near_rot & near_pos)
    return ok


def _board_in_view(C: np.ndarray, cell: CellParameters, scene: Scene,
                   margin_frac: float) -> np.ndarray:
    """Whether the board's outline projects inside the image by the margin, (k,)."""
    front = (_outline_in_camera(C, scene)[..., 2] > 0.02).all(axis=1)
    facing = C[:, 2, 2] > np.cos(np.deg2rad(60.0))
    return front & facing & (image_margin(C, cell, scene) >= margin_frac)


def _outline_in_camera(C: np.ndarray, scene: Scene) -> np.ndarray:
    """The board outline in the camera frames of views C (k, 4, 4), shape (k, n, 3)."""
    outline = scene.board.outline()
    return np.einsum("kij,nj->kni", C[:, :3, :3], outline) + C[:, None, :3, 3]


def image_margin(C: np.ndarray, cell: CellParameters, scene: Scene) -> np.ndarray:
    """The free border around the board's projected outline in views C (k, 4, 4), as a
    fraction of the smaller image side (negative: the board leaves the image), (k,)."""
    p = _outline_in_camera(C, scene)
    uv = Pinhole(cell.K, cell.dist).project(np.where(p[..., 2:] > 0.02, p, 1.0).reshape(-1, 3))
    uv = uv.reshape(len(C), -1, 2)
    w, h = scene.image_size
    gap = np.minimum(uv, np.array([w, h]) - uv).min(axis=(1, 2))
    return gap / min(w, h)


def _camera_path_inside(P: np.ndarray, start: np.ndarray, hand_eye: np.ndarray,
                        box: tuple[np.ndarray, np.ndarray], margin: float) -> np.ndarray:
    """Whether the camera stays inside ``box`` along the linear tool moves start -> P, (k,).

    The tcp moves on a line and its rotation turns uniformly, so the camera position is
    sampled at ``PATH_SAMPLES`` points of each move. The end must lie ``margin`` (m) inside;
    on the way the camera may come no closer to a wall than that or than it starts (a camera
    that starts near a wall may move away from it)."""
    lo, hi = box
    rel = so3.log(np.swapaxes(start[:3, :3], -1, -2) @ P[:, :3, :3])  # (k, 3)
    t_cam = hand_eye[:3, 3]
    p0 = start[:3, :3] @ t_cam + start[:3, 3]
    on_way = np.minimum(margin, np.minimum(p0 - lo, hi - p0).min())
    ok = np.ones(len(P), dtype=bool)
    for s in np.linspace(0.0, 1.0, PATH_SAMPLES)[1:]:
        R = start[:3, :3] @ so3.exp(s * rel)
        pos = start[:3, 3] + s * (P[:, :3, 3] - start[:3, 3]) + R @ t_cam
        m = margin if s == 1.0 else on_way
        ok &= ((pos >= lo + m) & (pos <= hi - m)).all(axis=1)
    return ok
