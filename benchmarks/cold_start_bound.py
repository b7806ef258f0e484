"""How few stations could reach the tolerance at all: an oracle design on the blind cells.

Issue 17 asks that the 90th percentile of the cold start reach σ <= 0.5 mm / 0.05° with at most
18 stations. This benchmark asks whether any 18 stations inside the box can, on the cold-start
benchmark's blind cells (``mocks.blindcells.random_blind_scene``, eye-in-hand for even cell
numbers, as ``benchmarks.cold_start.one_cell`` draws them). Per cell, the planner's own
information model (``calib.joint``'s Fisher information with the station corrections
eliminated, as ``calib.viewselect`` predicts it) is evaluated at the *true* cell (camera,
distortion, board κ and ν, hand-eye, target pose) on a pool of feasible views:

* views around the board: any tilt up to ``MAX_TILT_DEG``, any azimuth and roll, a look-at
  point anywhere on the board, distances over all the box allows;
* views from anywhere in the box: eye-in-hand the camera placed anywhere in the box looking at
  a board point, eye-to-hand the tool (carrying the board) anywhere in the box facing the
  camera, each turned so the board lands anywhere in the image.

A view is feasible when, under the true camera, every corner lies ``IMAGE_MARGIN_PX`` inside
the image and the board is less oblique than ``CornerCell.MAX_DETECT_TILT_DEG``, and the tcp
(and, eye-in-hand, the camera) lies inside the box; chosen views are also checked to be within
the arm's reach. From the start view, a greedy A-optimal design adds one view at a time, the
one that most lowers ``calib.viewselect.choose_view``'s score (hand-eye rotation and
translation variance in tolerance units plus focal length and principal point in
``INTRINSICS_TOLERANCE`` units). Then, at ``--stations``, an exchange pass (Fedorov's: swap one
station for the pool view that lowers the larger of the two σ/tolerance ratios most, until no
swap helps) and the same from random starts test whether greedy left much on the table.

**Why it is a lower bound.** The formal σ of a design at the truth is the Cramér-Rao bound of
the joint model for those views. The honest σ the benchmark judges is never below the formal
one, and the box term (``calib.extrapolation``) and the jackknife only add. The noise is the
calibration's (``calibration_noise``): ``CornerCell``'s 0.1 px corners (the planner assumes
0.2 px, ``calib.viewselect.SIGMA_PX``) and ``calibrate``'s default robot noise, 0.05° / 0.25
mm, five times the readings' own noise (0.01° / 0.05 mm): the calibration's formal σ is a
sandwich at the noise its variance components find, and on these cells they find about the
default (the kinematic errors look like reading noise; cell 8: 0.039° / 0.24 mm). ``floor``
is the strict bound: the mock's own reading noise and κ, ν known (a selection that holds
them at 1 has a smaller formal σ). What neither excludes: a better design than greedy plus
exchange finds (neither is a global optimum).

    python -m benchmarks.cold_start_bound                 # 50 cells, table and figure
    python -m benchmarks.cold_start_bound --quick         # 4 cells, smaller pools
    python -m benchmarks.cold_start_bound --only 8,10 --validate 8   # and calibrate cell 8

Prints a table and writes benchmarks/results/cold_start_bound.png.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks import results_dir
from benchmarks.cold_start import _numbers
from benchmarks.cold_start_bound_report import (
    Row,
    count,
    plot,
    read_cold_start,
    read_rows,
    table,
    write_rows,
)
from benchmarks.cold_start_report import MAX_STATIONS, TOL_DEG, TOL_MM
from benchmarks.stationset import station_set
from calib import (
    Pinhole,
    SolverOptions,
    board_from_target,
    calibrate,
    look_at_view,
    pose_error,
    robot_from_camera,
    ur_pose_from_matrix,
)
from calib.boards import Board
from calib.chain import RobotNoise, camera_from_robot
from calib.joint import GLOBAL_PARAMS, CellParameters, JointOptions, JointProblem
from calib.viewselect import INTRINSICS_TOLERANCE, SIGMA_PX, hand_eye_sigma, prior_information
from mocks.blindcells import CornerCell, random_blind_scene
from mocks.scene import MockScene, true_tcp_pose

OUT = results_dir()
#: Candidate views drawn per family and round (around the board, from anywhere in the box),
#: the feasible views wanted, and the most rounds drawn for them.
DRAWS, POOL, ROUNDS = 4000, 4000, 5
#: Draws of a ``--quick`` run.
QUICK_DRAWS = 400
#: Largest tilt from the board normal of the views around the board.
MAX_TILT_DEG = 60.0
#: Free border of every corner in the image, px (``CornerCell`` detects from 4 px).
IMAGE_MARGIN_PX = 8.0
#: The tcp's and the camera's least margin inside the box, m.
BOX_MARGIN_M = 0.01
#: Exchange sweeps over the stations, and random starts of the exchange.
SWEEPS, RESTARTS = 4, 2
#: The start view's planning noise, for the check against ``calib.viewselect``.
PLANNER_NOISE = (SIGMA_PX, RobotNoise())
_ROT = slice(GLOBAL_PARAMS.index("hand_eye_rx"), GLOBAL_PARAMS.index("hand_eye_rx") + 3)
_TRANS = slice(_ROT.stop, _ROT.stop + 3)
_NU, _KAPPA = GLOBAL_PARAMS.index("nu"), GLOBAL_PARAMS.index("kappa")
_TOL = np.array([np.deg2rad(TOL_DEG), TOL_MM * 1e-3])


@dataclass(frozen=True)
class Truth:
    """A blind cell as the oracle knows it: the scene, the joint model's parameters at the
    truth, the nominal board, the box (lo, hi) and the start T_base_tcp (4, 4)."""

    scene: MockScene
    cell: CellParameters
    board: Board
    box: tuple[np.ndarray, np.ndarray]
    start: np.ndarray

    @property
    def setup(self) -> str:
        return self.scene.setup


def truth(k: int) -> Truth:
    """Blind cell ``k`` as ``benchmarks.cold_start.one_cell`` draws it, with its truth."""
    scene = random_blind_scene(k, ("eye_in_hand", "eye_to_hand")[k % 2])
    cam, target = scene.camera, scene.target
    cell = CellParameters(K=cam.k_matrix, dist=cam.dist_coeffs, nu=target.nu,
                          kappa=target.kappa, hand_eye=scene.hand_eye_matrix,
                          target_pose=scene.target_pose_matrix)
    return Truth(scene, cell, board_from_target(scene.nominal_target()),
                 (np.array(scene.workspace.lo), np.array(scene.workspace.hi)), scene.start_pose())


def mock_noise(scene: MockScene) -> tuple[float, RobotNoise]:
    """The noise the mock adds: ``CornerCell``'s corner σ (px) and the scene's readings'."""
    n = scene.noise
    return CornerCell(scene).pixel_noise, RobotNoise(np.deg2rad(n.robot_rot_deg),
                                                     n.robot_trans_mm * 1e-3)


def station_information(t: Truth, T_base_tcp: np.ndarray, noise: tuple[float, RobotNoise]
                        ) -> np.ndarray:
    """Reduced Fisher information (k, 23, 23) of each view T_base_tcp (k, 4, 4) at the truth:
    ``calib.viewselect.station_information`` with the noise (σ_px, robot) as an argument (the
    planner fixes it at its own), in chunks."""
    grid = t.board.points()[:, :2]
    options = JointOptions(sigma_px=noise[0], setup=t.setup, noise=noise[1])
    out = []
    for T in np.array_split(T_base_tcp, max(1, len(T_base_tcp) // 300)):
        problem = JointProblem([grid] * len(T), [np.zeros_like(grid)] * len(T), T, t.cell,
                               options)
        _, blocks = problem.evaluate(problem.x0())  # (m, 2, g + 6)
        A = np.add.reduceat(np.einsum("mki,mkj->mij", blocks, blocks), problem.starts, axis=0)
        g = problem.n_free_global
        V = A[:, g:, g:] + np.diag(1.0 / problem.prior_sigma ** 2)
        W = A[:, :g, g:]
        out.append(A[:, :g, :g] - W @ np.linalg.solve(V, np.swapaxes(W, 1, 2)))
    return np.concatenate(out)


def _turned(C: np.ndarray, rng: np.random.Generator, half_fov: float) -> np.ndarray:
    """Views C (n, 4, 4) turned about the camera centre across the optical axis, by up to
    ``half_fov`` in a random direction, so the board lands anywhere in the image."""
    turn = np.tile(np.eye(4), (len(C), 1, 1))
    angle = rng.uniform(0.0, 2.0 * np.pi, len(C))
    xy = half_fov * rng.uniform(0.0, 1.0, (len(C), 1)) * np.column_stack([np.cos(angle),
                                                                           np.sin(angle)])
    turn[:, :3, :3] = Rotation.from_rotvec(np.column_stack([xy, np.zeros(len(C))])).as_matrix()
    return turn @ C


def _around_board(t: Truth, rng: np.random.Generator, n: int, d0: float) -> np.ndarray:
    """T_cam_target (n, 4, 4) of views around the board (module docstring)."""
    grid = t.board.points()
    centre = grid[[0, -1]].mean(axis=0)
    look = centre + (grid[-1] - centre) * rng.uniform(-1.0, 1.0, (n, 3)) * [1, 1, 0]
    tilt = np.deg2rad(MAX_TILT_DEG) * np.sqrt(rng.uniform(0.0, 1.0, n))
    dist = rng.uniform(max(0.05, d0 - 0.45), d0 + 0.45, n)
    return np.stack([look_at_view(look[k], tilt[k], *rng.uniform(0, 2 * np.pi, 2), dist[k])
                     for k in range(n)])


def _look_from(eye: np.ndarray, at: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R_cam_base (n, 3, 3) of cameras at ``eye`` (n, 3) looking at ``at`` (n, 3), rolled."""
    z = at - eye
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, _other_axis(z))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    R = np.stack([x, np.cross(z, x), z], axis=2)  # columns: camera axes in the base frame
    return np.swapaxes(R @ Rotation.from_rotvec(np.outer(roll, [0, 0, 1])).as_matrix(), 1, 2)


def _other_axis(z: np.ndarray) -> np.ndarray:
    """An axis (n, 3) not parallel to each row of ``z`` (n, 3)."""
    return np.where(np.abs(z[:, 2:]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])


def _from_box(t: Truth, rng: np.random.Generator, n: int) -> np.ndarray:
    """T_cam_target (n, 4, 4) of views from anywhere in the box (module docstring)."""
    lo, hi = t.box
    X, Y = t.cell.hand_eye, t.cell.target_pose
    grid = t.board.points()
    on_board = grid[0] + (grid[-1] - grid[0]) * rng.uniform(0.0, 1.0, (n, 3))
    roll = rng.uniform(0.0, 2.0 * np.pi, n)
    if t.setup == "eye_in_hand":  # the camera anywhere in the box, looking at a board point
        eye = rng.uniform(lo, hi, (n, 3))
        R = _look_from(eye, on_board @ Y[:3, :3].T + Y[:3, 3], roll)  # R_cam_base
        C = np.tile(np.eye(4), (n, 1, 1))
        C[:, :3, :3] = R @ Y[:3, :3]
        C[:, :3, 3] = np.einsum("nij,nj->ni", R, Y[:3, 3] - eye)
        return C
    # eye-to-hand: the tool anywhere in the box, the board facing the camera; its centre's
    # line of sight depends on the board's turn, so two rounds settle it
    tcp = rng.uniform(lo, hi, (n, 3))
    tcp_cam = (tcp - X[:3, 3]) @ X[:3, :3]  # tool positions in the camera frame
    centre = on_board
    C = np.tile(np.eye(4), (n, 1, 1))
    tilt = np.deg2rad(MAX_TILT_DEG) * np.sqrt(rng.uniform(0.0, 1.0, n))
    tilt_turn = Rotation.from_rotvec(np.column_stack([np.cos(roll), np.sin(roll), 0 * roll])
                                     * tilt[:, None]).as_matrix()
    sight = tcp_cam
    for _ in range(2):
        R_cam_target = np.swapaxes(_look_from(np.zeros((n, 3)), sight,
                                              rng.uniform(0, 2 * np.pi, n)), 1, 2) @ tilt_turn
        # the tcp at tcp_cam: C = inv(X) P Y, so the board origin is tcp_cam + R_cam_tcp t_Y
        C[:, :3, :3] = R_cam_target
        C[:, :3, 3] = tcp_cam + (R_cam_target @ Y[:3, :3].T) @ Y[:3, 3]
        sight = np.einsum("nij,nj->ni", R_cam_target, centre) + C[:, :3, 3]
    return C


def feasible(t: Truth, C: np.ndarray) -> np.ndarray:
    """Which views C = T_cam_target (n, 4, 4) the cell detects and the box allows, (n,)."""
    p = np.einsum("nij,mj->nmi", C[:, :3, :3], t.scene.true_board_points()) + C[:, None, :3, 3]
    front = (p[..., 2] > 0.02).all(axis=1)
    uv = Pinhole(t.cell.K, t.cell.dist).project(np.where(p[..., 2:] > 0.02, p, 1.0)
                                                .reshape(-1, 3)).reshape(len(C), -1, 2)
    w, h = t.scene.camera.image_size
    m = IMAGE_MARGIN_PX
    inside = ((uv >= m) & (uv <= [w - m, h - m])).all(axis=(1, 2))
    facing = C[:, 2, 2] > np.cos(np.deg2rad(CornerCell.MAX_DETECT_TILT_DEG))
    P = robot_from_camera(C, t.cell.hand_eye, t.cell.target_pose, t.setup)
    ok = front & inside & facing & _in_box(t, P[:, :3, 3])
    if t.setup == "eye_in_hand":
        ok &= _in_box(t, (P @ t.cell.hand_eye)[:, :3, 3])
    return ok


def _in_box(t: Truth, p: np.ndarray) -> np.ndarray:
    lo, hi = t.box
    return ((p >= lo + BOX_MARGIN_M) & (p <= hi - BOX_MARGIN_M)).all(axis=1)


def pool(t: Truth, rng: np.random.Generator, draws: int = DRAWS) -> np.ndarray:
    """Feasible views of both families, as T_base_tcp (n, 4, 4): rounds of ``draws`` per
    family (the views from the box half of them turned) until ``POOL`` are feasible or
    ``ROUNDS`` rounds are drawn."""
    C0 = camera_from_robot(t.start, t.cell.hand_eye, t.cell.target_pose, t.setup)
    half_fov = float(np.arctan(t.scene.camera.image_size[0] / 2.0 / t.cell.K[0, 0]))
    found: list[np.ndarray] = []
    for _ in range(ROUNDS):
        box = _from_box(t, rng, draws)
        C = np.concatenate([
            _turned(_around_board(t, rng, draws, float(np.linalg.norm(C0[:3, 3]))), rng,
                    half_fov), box[: draws // 2], _turned(box[draws // 2:], rng, half_fov)])
        found.append(C[feasible(t, C)])
        if sum(len(c) for c in found) >= POOL:
            break
    C = np.concatenate(found)[:POOL]
    return robot_from_camera(C, t.cell.hand_eye, t.cell.target_pose, t.setup)


def _diag_of_inverse(S: np.ndarray) -> np.ndarray:
    """Diagonals (n, g) of the inverses of S (n, g, g), in chunks."""
    return np.concatenate([np.einsum("kii->ki", np.linalg.inv(s))
                           for s in np.array_split(S, max(1, len(S) // 2000))])


def _a_score(d: np.ndarray, f: float) -> np.ndarray:
    """``choose_view``'s score of covariance diagonals d (n, g)."""
    return (d[:, _ROT].sum(axis=1) / _TOL[0] ** 2 + d[:, _TRANS].sum(axis=1) / _TOL[1] ** 2
            + d[:, 0:4].sum(axis=1) / (INTRINSICS_TOLERANCE * f) ** 2)


def _ratio(d: np.ndarray) -> np.ndarray:
    """The larger of σ_rot / tolerance and σ_trans / tolerance (root-sum-square σ), (n,)."""
    return np.maximum(np.sqrt(d[:, _ROT].sum(axis=1)) / _TOL[0],
                      np.sqrt(d[:, _TRANS].sum(axis=1)) / _TOL[1])


def greedy(S0: np.ndarray, S_pool: np.ndarray, n: int, f: float,
           reachable: Callable[[int], bool]) -> tuple[list[int], np.ndarray]:
    """The pool views (indices) a greedy A-optimal design adds to the information S0 (g, g),
    one at a time, and the hand-eye σ (n, 2) (rad, m) after each; ``reachable(i)`` vets the
    pick (a view the arm does not reach is dropped and the next best taken)."""
    S, free = S0.copy(), np.ones(len(S_pool), dtype=bool)
    chosen, sigma = [], []
    while len(chosen) < n and free.any():
        idx = np.flatnonzero(free)
        best = idx[int(np.argmin(_a_score(_diag_of_inverse(S[None] + S_pool[idx]), f)))]
        free[best] = False
        if not reachable(best):
            continue
        S += S_pool[best]
        chosen.append(best)
        sigma.append(hand_eye_sigma(np.linalg.inv(S)))
    return chosen, np.array(sigma)


def exchange(S0: np.ndarray, S_pool: np.ndarray, chosen: list[int],
             reachable: Callable[[int], bool]) -> tuple[list[int], float]:
    """Fedorov's exchange on the design ``chosen`` (pool indices, added to S0): swap a station
    for the pool view that lowers :func:`_ratio` most, sweep after sweep, until none does or
    ``SWEEPS``; returns the design and its ratio."""
    chosen = list(chosen)
    S = S0 + S_pool[chosen].sum(axis=0)
    now = float(_ratio(_diag_of_inverse(S[None]))[0])
    for _ in range(SWEEPS):
        improved = False
        for i in range(len(chosen)):
            rest = S - S_pool[chosen[i]]
            r = _ratio(_diag_of_inverse(rest[None] + S_pool))
            r[chosen] = np.inf
            for j in np.argsort(r)[:5]:
                if r[j] < now - 1e-9 and reachable(int(j)):
                    chosen[i], S, now, improved = int(j), rest + S_pool[j], float(r[j]), True
                    break
        if not improved:
            break
    return chosen, now


def _first(sig: np.ndarray) -> int:
    """The first index at which σ (n, 2) (rad, m) is within the tolerance, -1 if none."""
    ok = np.flatnonzero((sig <= _TOL).all(axis=1))
    return int(ok[0]) if len(ok) else -1


def calibration_noise(scene: MockScene) -> tuple[float, RobotNoise]:
    """The noise the calibration's formal σ rests on: ``CornerCell``'s corner σ (the fit
    estimates it) and ``calibrate``'s default robot noise, about what its variance components
    make of the readings' noise plus the kinematic errors (module docstring)."""
    return mock_noise(scene)[0], RobotNoise()


def bound_cell(k: int, stations: int, *, draws: int = DRAWS) -> Row:
    """The oracle bound of blind cell ``k`` (module docstring)."""
    t = truth(k)
    rng = np.random.default_rng([k, 41])
    P = pool(t, rng, draws)
    cache: dict[int, bool] = {}

    def reachable(i: int) -> bool:
        if i not in cache:
            try:
                true_tcp_pose(t.scene, P[i])
                cache[i] = True
            except ValueError:
                cache[i] = False
        return cache[i]

    f = float(t.cell.K[0, 0])

    def design(noise: tuple[float, RobotNoise], prior: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, list[int], np.ndarray]:
        S0 = station_information(t, t.start[None], noise)[0] + prior
        S_pool = station_information(t, P, noise)
        chosen, sig = greedy(S0, S_pool, MAX_STATIONS, f, reachable)
        return S0, S_pool, chosen, np.vstack([hand_eye_sigma(np.linalg.inv(S0)), sig])

    S0, S_pool, chosen, sig = design(calibration_noise(t.scene), prior_information())
    n = min(stations, len(chosen))
    swapped, r_ex = exchange(S0, S_pool, chosen[:n], reachable)
    r_restart = min(exchange(S0, S_pool, list(rng.choice(len(P), n, replace=False)),
                             reachable)[1] for _ in range(RESTARTS))
    known = prior_information()
    known[[_NU, _KAPPA], [_NU, _KAPPA]] = 1e20  # ν and κ known: no σ left to them
    floor = design(mock_noise(t.scene), known)[3]
    C0 = camera_from_robot(t.start, t.cell.hand_eye, t.cell.target_pose, t.setup)
    return Row(cell=k, setup=t.setup, distance_m=float(np.linalg.norm(C0[:3, 3])),
               hfov_deg=float(np.degrees(2 * np.arctan(t.scene.camera.image_size[0] / 2 / f))),
               pool=len(P), sigma_deg=np.degrees(sig[:, 0]).tolist(),
               sigma_mm=(1e3 * sig[:, 1]).tolist(), first=_first(sig),
               ratio_greedy=float((sig[n] / _TOL).max()), ratio_exchange=r_ex,
               ratio_restart=r_restart, floor_first=_first(floor),
               poses=[t.start.tolist(), *[P[i].tolist() for i in swapped]])


def validate(row: Row) -> str:
    """Shoot the oracle's design (start view plus the exchanged stations) on the corner-level
    cell and calibrate it as the cold-start benchmark does; fills ``row.calibrated`` ({} if
    the calibration fails; else the
    calibration's formal and honest σ, its error against the true flange, the robot noise
    its variance components found and the σ predicted at that noise) and says it with the σ
    predicted at the calibration's and the mock's noise."""
    t = truth(row.cell)
    cell = CornerCell(t.scene)
    shots = [s for s in (cell.shoot(np.array(P)) for P in row.poses) if s.corners is not None]
    P = np.stack([s.T_base_tcp for s in shots])
    try:
        res = calibrate(station_set(
            [s.corners for s in shots], [ur_pose_from_matrix(p) for p in P], t.board,
            image_size=t.scene.camera.image_size, setup=t.setup),
            SolverOptions(workspace=(t.scene.workspace.lo, t.scene.workspace.hi)))
    except ValueError as exc:
        row.calibrated = {}
        return f"cell {row.cell}: the calibration of the design failed: {exc}"
    u = res.trust.uncertainty
    rot, trans = pose_error(res.hand_eye, t.scene.hand_eye_matrix)
    est = next(c.fit for c in res.trust.model_selection.candidates
               if c.model is not None and c.model.estimate_noise and c.fit)
    noises = {"estimated": (est.sigma_px, est.noise),
              "calibration": calibration_noise(t.scene), "mock": mock_noise(t.scene)}
    predicted = {}
    for name, noise in noises.items():
        S = station_information(t, P, noise).sum(axis=0) + prior_information()
        predicted[name] = np.array(hand_eye_sigma(np.linalg.inv(S))) * [np.degrees(1), 1e3]
    row.calibrated = dict(
        views=len(shots),
        formal_deg=float(np.degrees(np.linalg.norm(u.formal["hand_eye_rot_rad"]))),
        formal_mm=float(1e3 * np.linalg.norm(u.formal["hand_eye_trans_m"])),
        honest_deg=float(np.degrees(np.linalg.norm(res.sigmas["hand_eye_rot_rad"]))),
        honest_mm=float(1e3 * np.linalg.norm(res.sigmas["hand_eye_trans_m"])),
        error_deg=float(np.degrees(rot)), error_mm=float(1e3 * trans),
        noise_deg=float(np.degrees(est.noise.rot_rad)), noise_mm=1e3 * est.noise.trans_m,
        predicted_deg=float(predicted["estimated"][0]),
        predicted_mm=float(predicted["estimated"][1]))
    c = row.calibrated
    return (f"cell {row.cell}: {len(shots)} of {len(row.poses)} views detected; calibration "
            f"formal σ {c['formal_deg']:.4f} deg / {c['formal_mm']:.3f} mm, honest "
            f"{c['honest_deg']:.4f} / {c['honest_mm']:.3f}, error (true flange) "
            f"{c['error_deg']:.4f} / {c['error_mm']:.3f}, held at 1: {u.held}; its robot noise "
            f"{c['noise_deg']:.4f} deg / {c['noise_mm']:.3f} mm; predicted " + ", ".join(
                f"{v[0]:.4f} / {v[1]:.3f} at the {k} noise" for k, v in predicted.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help=f"4 cells and {QUICK_DRAWS} draws per family and round")
    parser.add_argument("--cells", type=int, default=50, help="cells 0 to CELLS - 1")
    parser.add_argument("--only", type=_numbers, default=None, metavar="K[,K...]")
    parser.add_argument("--stations", type=int, default=18, help="the acceptance's station count")
    parser.add_argument("--draws", type=int, default=DRAWS, help="candidate views per family")
    parser.add_argument("--validate", type=_numbers, default=[], metavar="K[,K...]",
                        help="calibrate the oracle's design of these cells on the mock")
    parser.add_argument("--from-log", action="store_true",
                        help="the designs of the last run's log instead of new ones")
    parser.add_argument("--cold-log", type=Path, default=OUT / "cold_start.jsonl",
                        help="a cold-start benchmark log to compare with")
    args = parser.parse_args()
    cells = args.only or list(range(4 if args.quick else args.cells))
    if args.from_log and not args.only:
        cells = sorted(r.cell for r in read_rows(OUT / "cold_start_bound.jsonl"))
    draws = QUICK_DRAWS if args.quick else args.draws
    OUT.mkdir(exist_ok=True)
    log = OUT / "cold_start_bound.jsonl"
    logged = {r.cell: r for r in read_rows(log)} if args.from_log else {}
    rows = []
    for k in cells:
        row = logged.get(k) or bound_cell(k, args.stations, draws=draws)
        print(f"cell {k:2d} {row.setup:11s} {row.distance_m:.2f} m, pool {row.pool}: within "
              f"after {count(row.first)}; ratio at {args.stations}: {row.ratio_greedy:.2f} "
              f"greedy, {row.ratio_exchange:.2f} exchange, {row.ratio_restart:.2f} restarts",
              flush=True)
        if k in args.validate:
            print(validate(row), flush=True)
        rows.append(row)
        write_rows(log, rows + [r for c, r in logged.items() if c not in cells[:len(rows)]])
    cold = read_cold_start(args.cold_log)
    print(table(rows, args.stations, cold))
    plot(rows, cold, args.stations, OUT / "cold_start_bound.png")
    print(f"wrote {OUT / 'cold_start_bound.png'}")


if __name__ == "__main__":
    main()
