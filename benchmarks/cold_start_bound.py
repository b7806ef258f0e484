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
    python -m benchmarks.cold_start_bound --from-log --honest   # the logged greedy designs,
                                                     # calibrated: stations to honest σ

Prints a table and writes benchmarks/results/cold_start_bound.png.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

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
from benchmarks.cold_start_report import FIRST_CHECK, MAX_STATIONS, TOL_DEG, TOL_MM
from benchmarks.cold_start_views import DRAWS, Truth, pool, truth
from benchmarks.stationset import station_set
from calib import (
    CalibrationResult,
    SolverOptions,
    calibrate,
    pose_error,
    ur_pose_from_matrix,
    viewselect,
)
from calib.chain import RobotNoise, camera_from_robot
from calib.joint import GLOBAL_PARAMS, JointOptions
from calib.viewselect import INTRINSICS_TOLERANCE, SIGMA_PX, hand_eye_sigma, prior_information
from mocks.blindcells import CornerCell, Shot
from mocks.scene import MockScene, true_tcp_pose

OUT = results_dir()
#: Draws of a ``--quick`` run.
QUICK_DRAWS = 400
#: Station counts at which a greedy design's honest σ is checked: from 8 images on, as the
#: service computes it (``FIRST_CHECK``), every count to 24, then a few more.
HONEST_CHECKS = (*range(FIRST_CHECK - 1, 25), 28, 32, 36, MAX_STATIONS)
#: Exchange sweeps over the stations, and random starts of the exchange.
SWEEPS, RESTARTS = 4, 2
#: The planner's noise (``calib.viewselect``), to check that the information is its own.
PLANNER_NOISE = (SIGMA_PX, RobotNoise())
_ROT = slice(GLOBAL_PARAMS.index("hand_eye_rx"), GLOBAL_PARAMS.index("hand_eye_rx") + 3)
_TRANS = slice(_ROT.stop, _ROT.stop + 3)
_NU, _KAPPA = GLOBAL_PARAMS.index("nu"), GLOBAL_PARAMS.index("kappa")
_TOL = np.array([np.deg2rad(TOL_DEG), TOL_MM * 1e-3])


def mock_noise(scene: MockScene) -> tuple[float, RobotNoise]:
    """The noise the mock adds: ``CornerCell``'s corner σ (px) and the scene's readings'."""
    n = scene.noise
    return CornerCell(scene).pixel_noise, RobotNoise(np.deg2rad(n.robot_rot_deg),
                                                     n.robot_trans_mm * 1e-3)


def station_information(t: Truth, T_base_tcp: np.ndarray, noise: tuple[float, RobotNoise]
                        ) -> np.ndarray:
    """Reduced Fisher information (k, 23, 23) of each view T_base_tcp (k, 4, 4) at the truth
    (``calib.viewselect.station_information`` at the noise (σ_px, robot)), in chunks of 300."""
    return np.concatenate([
        viewselect.station_information(t.cell, T, t.board, JointOptions(
            sigma_px=noise[0], setup=t.setup, noise=noise[1]))
        for T in np.array_split(T_base_tcp, max(1, len(T_base_tcp) // 300))])


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
               poses=[t.start.tolist(), *[P[i].tolist() for i in swapped]],
               greedy_poses=[t.start.tolist(), *[P[i].tolist() for i in chosen]])


def validate(row: Row) -> str:
    """Shoot the oracle's design (start view plus the exchanged stations) on the corner-level
    cell and calibrate it as the cold-start benchmark does; fills ``row.calibrated`` ({} if
    the calibration fails; else the
    calibration's formal and honest σ, its error against the true flange, the robot noise
    its variance components found and the σ predicted at that noise) and says it with the σ
    predicted at the calibration's and the mock's noise."""
    t = truth(row.cell)
    shots = _shots(t, row.poses)
    P = np.stack([s.T_base_tcp for s in shots])
    try:
        res = _calibrated(t, shots)
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


def _shots(t: Truth, poses: list) -> list[Shot]:
    """The views of ``poses`` (T_base_tcp lists) that ``CornerCell`` detects, in order."""
    cell = CornerCell(t.scene)
    return [s for s in (cell.shoot(np.array(P)) for P in poses) if s.corners is not None]


def _calibrated(t: Truth, shots: list[Shot]) -> CalibrationResult:
    """The calibration of ``shots`` as ``benchmarks.cold_start`` makes it (the box given)."""
    return calibrate(station_set(
        [s.corners for s in shots], [ur_pose_from_matrix(s.T_base_tcp) for s in shots],
        t.board, image_size=t.scene.camera.image_size, setup=t.setup),
        SolverOptions(workspace=(t.scene.workspace.lo, t.scene.workspace.hi)))


def honest_stations(row: Row) -> str:
    """The fewest stations of the greedy design whose calibration on the mock has its honest
    σ within the tolerance: the design's views shot once, the start view and the first n
    stations calibrated for each n of ``HONEST_CHECKS`` in turn (σ need not fall with every
    station: the robot noise the calibration finds grows as the stations spread). Fills
    ``row.honest_first`` (-1: not within at any)."""
    t = truth(row.cell)
    shots = _shots(t, row.greedy_poses or [])

    def within(n: int) -> bool:
        try:
            res = _calibrated(t, shots[:n + 1])
        except ValueError:
            return False
        sig = [np.linalg.norm(res.sigmas[k]) for k in ("hand_eye_rot_rad", "hand_eye_trans_m")]
        return bool((np.array(sig) <= _TOL).all())

    hit = next((n for n in HONEST_CHECKS if n < len(shots) and within(n)), None)
    row.honest_first = -1 if hit is None else hit
    return (f"cell {row.cell}: the greedy design calibrated on the mock: honest σ within the "
            f"tolerance from {count(row.honest_first)} stations ({len(shots)} views detected)")


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
    parser.add_argument("--honest", action="store_true",
                        help="the stations at which each greedy design's honest σ, calibrated "
                             "on the mock, is first within the tolerance")
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
        if args.honest:
            print(honest_stations(row), flush=True)
        rows.append(row)
        write_rows(log, rows + [r for c, r in logged.items() if c not in cells[:len(rows)]])
    cold = read_cold_start(args.cold_log)
    print(table(rows, args.stations, cold))
    plot(rows, cold, args.stations, OUT / "cold_start_bound.png")
    print(f"wrote {OUT / 'cold_start_bound.png'}")


if __name__ == "__main__":
    main()
