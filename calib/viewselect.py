"""The next station chosen by what it teaches: candidate views scored by predicted uncertainty.

Given the current estimate of the cell (``calib.coldstart``), candidate views are drawn within
a *reach* that grows as the estimate firms up (:class:`Reach`) in three families: views that
look at the board (``calib.planning.look_at_view``: tilt, azimuth, roll, distance, look-at
point), half of them turned about the camera centre so the board lands anywhere in the image
(:func:`turned_toward`); views from where the box lets the camera (eye-in-hand) or the board
(eye-to-hand) go (:func:`_in_box`); and small tool moves from the last good pose. A candidate
is feasible when, under the estimate, the whole board projects inside the image with a
margin, the view is not too oblique, its tcp (and, eye-in-hand, its camera, along the whole
move) stays inside the safety box by a margin, the move from the last good pose is within the
reach's step, and it is not near a view where the board was already lost. Rounds of
candidates are drawn until ``FEASIBLE_WANTED`` are feasible: on a far board 5-15 % of the
draws are, and the choice is only as good as the views it is offered.

Each feasible candidate is scored by the covariance the joint model (``calib.joint``) would
have with it added: the Fisher information of the joint problem with the station corrections
eliminated adds up over stations (``JointProblem.reduced_information``), so one evaluation of
all candidates' corner Jacobians and a 23 x 23 inverse per candidate predict
``(S_sofar + S_candidate + S_prior)⁻¹``. The score is the hand-eye's variance in units of the
tolerance (rotation and translation), plus the focal length and principal point's in units of
``INTRINSICS_TOLERANCE``: the A-optimal design criterion restricted to what the user asked
for. The candidate with the lowest score is visited; it is a fresh draw every step, not a
fixed pattern.

Why the board anywhere in the image and the camera anywhere in the box: a turn of the camera
across its optical axis is what fixes the hand-eye translation along it (the focal length and
the distance otherwise trade against each other), and for a far board the box keeps the camera
within about 10° of its first line of sight unless the board may leave the image centre. An
oracle design over such views at the true cell (``benchmarks.cold_start_bound``) reaches the
tolerance's formal σ after 10 stations at the 90th percentile.
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
#: Candidates are drawn in rounds until this many are feasible, or ``ROUNDS`` rounds.
FEASIBLE_WANTED, ROUNDS = 150, 4
#: Share of the views that look at the board turned so it lands on a random pixel.
PAN_SHARE = 0.5
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
    drawn, found = 0, []
    for _ in range(ROUNDS):
        P = np.concatenate([_candidates(cell, scene, reach, history.last_good, rng),
                            _nearby(history.last_good, reach, rng)])
        drawn += len(P)
        found.append(P[_feasible(P, cell, scene, reach, history)])
        if sum(len(f) for f in found) >= FEASIBLE_WANTED:
            break
    P_ok = np.concatenate(found)
    if not len(P_ok):
        return None
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
    return Choice(T_base_tcp=P_ok[best], predicted=hand_eye_sigma(cov[best]), drawn=drawn,
                  feasible=len(P_ok))


def _candidates(cell: CellParameters, scene: Scene, reach: Reach, last_good: np.ndarray,
                rng: np.random.Generator) -> np.ndarray:
    """``reach.draws`` candidate tcp poses (n, 4, 4): half views around the board in reach,
    half of those turned so the board lands anywhere in the image (``_panned``), and half
    from where the box lets the camera (eye-in-hand) or the board (eye-to-hand) go."""
    C = np.concatenate([_panned(_around_board(scene, reach, reach.draws // 2, rng), cell, scene,
                                rng), _in_box(cell, scene, reach, last_good, rng)])
    return robot_from_camera(C, cell.hand_eye, cell.target_pose, scene.setup)


def _panned(C: np.ndarray, cell: CellParameters, scene: Scene, rng: np.random.Generator
            ) -> np.ndarray:
    """Views C (n, 4, 4), ``PAN_SHARE`` of them turned about the camera centre so the board's
    centre lands on a random pixel."""
    pan = rng.uniform(0.0, 1.0, len(C)) < PAN_SHARE
    w, h = scene.image_size
    uv = rng.uniform(0.0, 1.0, (int(pan.sum()), 2)) * [w, h]
    ray = np.column_stack([(uv - cell.K[:2, 2]) / np.diag(cell.K)[:2], np.ones(len(uv))])
    C[pan] = turned_toward(C[pan], ray)
    return C


def _look_at(scene: Scene, reach: Reach, n: int, rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` look-at points near the board centre (n, 3, target frame), view tilts (n,) and
    rolls (n,) in reach."""
    grid = scene.board.points()
    centre = grid[[0, -1]].mean(axis=0)
    look = centre + 0.25 * (grid[-1] - centre) * rng.uniform(-1.0, 1.0, (n, 3))
    tilt = np.deg2rad(reach.max_tilt_deg) * np.sqrt(rng.uniform(0.0, 1.0, n))
    roll = scene.start_roll + np.deg2rad(reach.max_roll_deg) * rng.uniform(-1, 1, n)
    return look, tilt, roll


def _views(look: np.ndarray, tilt: np.ndarray, azimuth: np.ndarray, roll: np.ndarray,
           dist: np.ndarray) -> np.ndarray:
    """:func:`calib.planning.look_at_view` row by row, T_cam_target (n, 4, 4), also for n = 0."""
    return np.array([look_at_view(look[k], tilt[k], azimuth[k], roll[k], dist[k])
                     for k in range(len(tilt))]).reshape(-1, 4, 4)


def _around_board(scene: Scene, reach: Reach, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` views T_cam_target (n, 4, 4) that look at the board's centre from every side in
    reach."""
    look, tilt, roll = _look_at(scene, reach, n, rng)
    return _views(look, tilt, rng.uniform(0.0, 2.0 * np.pi, n), roll, rng.uniform(*reach.band, n))


def _in_box(cell: CellParameters, scene: Scene, reach: Reach, last_good: np.ndarray,
            rng: np.random.Generator) -> np.ndarray:
    """Up to ``reach.draws // 2`` views T_cam_target (k, 4, 4): eye-in-hand the camera's centre
    drawn in the box within a step of where it is, looking at a point near the board's centre
    and turned so it lands anywhere in the image; eye-to-hand the board's centre so drawn,
    seen by the fixed camera wherever it falls in the image, turned by a tilt in reach."""
    n = reach.draws // 2
    grid = scene.board.points()
    centre = np.append(grid[[0, -1]].mean(axis=0), 1.0)
    X, Y = cell.hand_eye, cell.target_pose
    lo, hi = (np.asarray(b, dtype=float) for b in scene.box)
    if scene.setup == "eye_in_hand":
        here = (last_good @ X)[:3, 3]
        lo, hi = lo + reach.camera_margin, hi - reach.camera_margin
    else:
        here = (last_good @ Y @ centre)[:3]
        lo, hi = lo + here - last_good[:3, 3], hi + here - last_good[:3, 3]
    a, b = np.maximum(lo, here - reach.step[1]), np.minimum(hi, here + reach.step[1])
    if (a >= b).any():
        return np.empty((0, 4, 4))
    at = np.column_stack([rng.uniform(a, b, (n, 3)), np.ones(n)])
    look, tilt, roll = _look_at(scene, reach, n, rng)
    if scene.setup == "eye_in_hand":
        sight = look - (np.linalg.inv(Y) @ at.T).T[:, :3]  # camera to look-at, target frame
        dist = np.linalg.norm(sight, axis=1)
        sight /= dist[:, None]
        tilt = np.arccos(np.clip(sight[:, 2], -1.0, 1.0))
        azimuth = np.arctan2(sight[:, 0], -sight[:, 1])
        k = tilt <= np.deg2rad(reach.max_tilt_deg)
        return _panned(_views(look[k], tilt[k], azimuth[k], roll[k], dist[k]), cell, scene, rng)
    q = (np.linalg.inv(X) @ at.T).T[:, :3]  # the board centre in the camera frame
    keep = q[:, 2] > 0.05
    q, tilt, roll = q[keep], tilt[keep], roll[keep]
    C = _views(np.tile(centre[:3], (len(q), 1)), tilt, rng.uniform(0.0, 2.0 * np.pi, len(q)),
               roll, np.linalg.norm(q, axis=1))
    return turned_toward(C, q)


def turned_toward(C: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """Views C (n, 4, 4) = T_cam_target turned about the camera centre so that what lay on
    the optical axis lies along ``ray`` (n, 3, camera frame) instead, (n, 4, 4)."""
    ray = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    axis = np.column_stack([-ray[:, 1], ray[:, 0], np.zeros(len(C))])  # z x ray
    sin = np.linalg.norm(axis, axis=1, keepdims=True)
    turn = np.tile(np.eye(4), (len(C), 1, 1))
    turn[:, :3, :3] = so3.exp(axis / np.maximum(sin, 1e-12) * np.arctan2(sin, ray[:, 2:]))
    return turn @ C


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
