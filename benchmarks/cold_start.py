"""Calibrating a blind cell from a cold start, against three ways of choosing stations (issue 17).

Random blind cells (``mocks.blindcells``: eye-in-hand and eye-to-hand alternately, HFOV 50-90°,
|k1| <= 0.3, principal point off centre, any hand-eye rotation at 5-20 cm, board 0.2-1.5 m
away anywhere in the start image, UR5e kinematic errors, box ±0.25 m around the start) are
simulated at corner level (``CornerCell``: the true flange pose, 0.1 px corner noise, a board
counts as detected when wholly in the image and less oblique than 70°). Every commanded pose
goes through the cell, which refuses (and counts) any outside the box. In the same run, per
cell:

* **cold start**: ``calib.ColdStart`` with the tolerance 0.5 mm / 0.05° and at most 40
  stations, as ``POST /runs {"tolerance_mm": 0.5, "tolerance_deg": 0.05}`` runs it: until the
  90 % bound (``calib.COVERAGE_90`` = 1.645 times the honest σ) is within the tolerance. The
  honest σ (``calibrate``: the σ a result reports, jackknife floor included;
  root-sum-square over the axes) is computed after a station once the planner's formal σ is
  within 1.3x the next aim (the honest σ is never below the formal one, so an earlier stop is
  impossible; the service computes it after every station from the 8th): first the
  tolerance, noting the stations at which σ <= tolerance first held, then the tolerance over
  1.645 (a check that misses its aim skips ahead, ``SKIP_FRACTION``);
* **easy_handeye**: its 17 fixed poses around the start (tool rotations of ±12.5° and ±25°
  about each tool axis, ±4 cm along tool x and y), poses outside the box skipped;
* **random**: random poses in the box (tool turned up to 30° from the start), until the honest
  σ meets the tolerance (checked at 12, 16, 20, 25, 30, 40 good stations) or 40 stations;
* **oracle**: today's one-shot planner (``calib.plan_stations``) handed the true hand-eye and
  focal length, 20 stations.

Success (the acceptance's): a result whose hand-eye error is at most 1 mm and 0.1° and at
most 2x its reported σ, the error taken against the hand-eye the arm's readings see
(``mocks.blindcells.readings_hand_eye`` with ``scale=True``): the part of the kinematic error
that is the same over the whole box moves the flange by a fixed transform and scales the
readings' translations by a common factor, which no calibration from the readings can see
(a scale only as the board's κ), and every use of the result through the readings wants them
included (the product's decision, issue 17). The error against the true hand-eye (the
physical flange), against the rigid fit (``scale=False``) and against the hand-eye the
readings see over the result's own stations (``readings_hand_eye(poses=...)``: the part of
the arm's kinematic errors that differs between where the stations are and the box is the
difference from the box's; a rough figure, for the readings' scale is ill-determined over
stations that cluster: on cell 14 the frame over the readings and over the commanded poses
differ by 0.45 mm) are reported beside it.
"σ <= tolerance first held" is found by bisection over the first images between the last
check that missed and the first that met it (``_first_within``). Planning compute is the CPU
time of a proposal plus the refit after its image.

    python -m benchmarks.cold_start            # 50 cells, two at a time
    python -m benchmarks.cold_start --quick    # 6 cells
    python -m benchmarks.cold_start --from-log # the table and figure of the cells logged
    python -m benchmarks.cold_start --only 8,10,12 --jobs 1  # some cells, as in a full run

Prints a table and writes benchmarks/results/cold_start.png.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks import interrupt_on_sigterm, results_dir
from benchmarks.cold_start_report import (
    FIRST_CHECK,
    MAX_STATIONS,
    METHODS,
    TOL_DEG,
    TOL_MM,
    Outcome,
    bound,
    plot,
    read_log,
    table,
)
from benchmarks.stationset import station_set
from calib import (
    COVERAGE_90,
    CellGuess,
    ColdStart,
    ColdStartScene,
    Pinhole,
    PlanOptions,
    SolverOptions,
    View,
    board_from_target,
    calibrate,
    camera_from_robot,
    hand_eye_rss,
    hand_eye_sigma,
    make_transform,
    plan_stations,
    pose_error,
    rough_target_from_image,
    ur_pose_from_matrix,
)
from mocks.blindcells import CornerCell, Shot, random_blind_scene, readings_hand_eye

OUT = results_dir()
#: Honest σ computed once the planner's formal σ is within this factor of the tolerance.
HONEST_GATE = 1.3
RANDOM_CHECKS = (12, 16, 20, 25, 30, 40)
#: After an honest σ that misses its aim (the tolerance, then the tolerance over 1.645), the
#: next one waits this fraction of the images it would still need if σ fell as
#: 1/sqrt(images), at least one and at most a quarter of the images so far (each check is a
#: whole calibration; waiting longer could overshoot the station where the aim first held).
SKIP_FRACTION = 0.5


def _calibrate(shots: list[Shot], cell: CornerCell, out: Outcome) -> bool:
    """Calibrate the good shots; fill the outcome's error and σ. False if it fails."""
    scene = cell.scene
    try:
        res = calibrate(station_set(
            [s.corners for s in shots], [ur_pose_from_matrix(s.T_base_tcp) for s in shots],
            board_from_target(scene.nominal_target()), image_size=scene.camera.image_size,
            setup=scene.setup), SolverOptions(workspace=(scene.workspace.lo, scene.workspace.hi),
                                              tolerance=(np.deg2rad(TOL_DEG), TOL_MM * 1e-3)))
    except ValueError:
        return False
    rot, trans = pose_error(res.hand_eye, scene.hand_eye_matrix)
    out.err_deg, out.err_mm = float(np.degrees(rot)), float(trans * 1e3)
    rot, trans = pose_error(res.hand_eye, readings_hand_eye(
        scene, scale=True, poses=np.stack([s.T_base_tcp for s in shots])))
    out.own_deg, out.own_mm = float(np.degrees(rot)), float(trans * 1e3)
    out.hand_eye = res.hand_eye.tolist()
    out.verdict = res.trust.quality.verdict
    rot, trans = hand_eye_rss(res.sigmas)
    out.sigma_deg, out.sigma_mm = float(np.degrees(rot)), trans * 1e3
    out.met = out.sigma_deg <= TOL_DEG and out.sigma_mm <= TOL_MM
    out.bound_met = bound(out.sigma_deg) <= TOL_DEG and bound(out.sigma_mm) <= TOL_MM
    return True


def cold_start(cell: CornerCell, seed: int) -> Outcome:
    scene, out, t0 = cell.scene, Outcome(), time.perf_counter()
    board = board_from_target(scene.nominal_target())
    box = (np.array(scene.workspace.lo), np.array(scene.workspace.hi))
    plan = ColdStart(ColdStartScene(board, scene.setup, scene.camera.image_size, box,
                                    (np.deg2rad(TOL_DEG), TOL_MM * 1e-3)), cell.start(),
                     seed=seed)
    good: list[Shot] = []
    while len(good) < MAX_STATIONS:
        c0 = time.process_time()
        proposal = plan.propose()
        if proposal is None:
            break
        shot = cell.shoot(proposal.T_base_tcp)
        view = None if shot.corners is None else View(shot.T_base_tcp, shot.corners, shot.ids)
        plan.record(proposal.T_base_tcp, view, shot.reason)
        out.plan_s.append(time.process_time() - c0)
        if view is None:
            out.lost += 1
            continue
        good.append(shot)
        out.stations += proposal.kind == "station"
        out.stations_at.append(out.stations)
        out.explore_at.append(plan.log.explore_moves)
        if _honest_check(plan, good, cell, out):
            break
    out.explore = plan.log.explore_moves
    if not out.bound_met:
        _calibrate(good, cell, out)
    out.refused, out.wall_s = cell.refused, time.perf_counter() - t0
    return out


def _honest_check(plan: ColdStart, good: list[Shot], cell: CornerCell, out: Outcome) -> bool:
    """After a good station: the honest σ once the planner's formal σ is near the next
    target (the tolerance, then the tolerance over ``COVERAGE_90``); notes the stations at
    which σ <= tolerance first held (``_first_within``); True when the 90 % bound is within
    the tolerance."""
    est = plan.estimate
    if len(good) < max(FIRST_CHECK, out.next_check) or est is None:
        return False
    aim = 1.0 if out.tol_stations < 0 else 1.0 / COVERAGE_90
    rot, trans = hand_eye_sigma(est.covariance)
    if not (np.degrees(rot) <= HONEST_GATE * aim * TOL_DEG
            and trans * 1e3 <= HONEST_GATE * aim * TOL_MM) or not _calibrate(good, cell, out):
        out.last_miss = len(good) if out.tol_stations < 0 else out.last_miss
        return False
    if out.tol_stations < 0 and out.met:
        first = _first_within(good, cell, out.last_miss, len(good))
        out.tol_stations, out.tol_explore = out.stations_at[first - 1], out.explore_at[first - 1]
        aim = 1.0 / COVERAGE_90
    elif out.tol_stations < 0:
        out.last_miss = len(good)
    # σ falls about as 1/sqrt(images): skip part of the way to where it would meet the aim
    need = max(out.sigma_deg / TOL_DEG, out.sigma_mm / TOL_MM) ** 2 / aim ** 2 * len(good)
    out.next_check = len(good) + int(np.clip(SKIP_FRACTION * (need - len(good)), 1,
                                             max(1, len(good) // 4)))
    return out.bound_met


def _first_within(good: list[Shot], cell: CornerCell, miss: int, hit: int) -> int:
    """The fewest images at which the honest σ is within the tolerance, between ``miss``
    images (a check that missed, or the images before the first check) and ``hit`` (one that
    met it), by bisection over the first images: exact when σ falls with every image, as it
    nearly always does; the skipped checks otherwise leave it an upper bound."""
    while hit - miss > 1:
        mid, probe = (hit + miss) // 2, Outcome()
        if _calibrate(good[:mid], cell, probe) and probe.met:
            hit = mid
        else:
            miss = mid
    return hit


def _tool_move(rotvec: tuple[float, float, float], move: tuple[float, float, float]
               ) -> np.ndarray:
    return make_transform(Rotation.from_rotvec(np.deg2rad(rotvec)).as_matrix(), move)


def easy_handeye(cell: CornerCell) -> Outcome:
    out, t0 = Outcome(), time.perf_counter()
    moves = [_tool_move((0, 0, 0), (0, 0, 0))]
    for axis in range(3):
        for angle in (12.5, -12.5, 25.0, -25.0):
            rv = [0.0, 0.0, 0.0]
            rv[axis] = angle
            moves.append(_tool_move(tuple(rv), (0, 0, 0)))
    moves += [_tool_move((0, 0, 0), m) for m in ((0.04, 0, 0), (-0.04, 0, 0), (0, 0.04, 0),
                                                 (0, -0.04, 0))]
    good = _visit(cell, [cell.start() @ M for M in moves], out)
    _calibrate(good, cell, out)
    out.stations, out.wall_s = len(good), time.perf_counter() - t0
    return out


def _visit(cell: CornerCell, poses: list[np.ndarray], out: Outcome) -> list[Shot]:
    """The good shots of ``poses``; poses outside the box are not commanded (counted)."""
    box, good = cell.scene.workspace, []
    for P in poses:
        cam = P @ cell.scene.hand_eye_matrix if cell.scene.setup == "eye_in_hand" else P
        if not (box.contains(P[:3, 3]) and box.contains(cam[:3, 3])):
            out.refused += 1
            continue
        shot = cell.shoot(P)
        if shot.corners is None:
            out.lost += 1
        else:
            good.append(shot)
    return good


def random_poses(cell: CornerCell, seed: int) -> Outcome:
    out, t0 = Outcome(), time.perf_counter()
    rng = np.random.default_rng([seed, 5])
    lo, hi = np.array(cell.scene.workspace.lo), np.array(cell.scene.workspace.hi)
    good: list[Shot] = []
    checks = list(RANDOM_CHECKS)
    for _ in range(600):
        P = cell.start().copy()
        P[:3, :3] = P[:3, :3] @ Rotation.from_rotvec(
            rng.normal(size=3) * np.deg2rad(30.0) / np.sqrt(3)).as_matrix()
        P[:3, 3] = rng.uniform(lo, hi)
        good += _visit(cell, [P], out)
        if checks and len(good) >= checks[0]:
            checks.pop(0)
            if (_calibrate(good, cell, out) and out.met) or not checks:
                break
    out.refused = 0  # random draws outside the box were never commanded
    out.stations, out.wall_s = len(good), time.perf_counter() - t0
    return out


def oracle(cell: CornerCell, seed: int) -> Outcome:
    scene, out, t0 = cell.scene, Outcome(), time.perf_counter()
    board = board_from_target(scene.nominal_target())
    w, h = scene.camera.image_size
    f = scene.camera.k_matrix[0, 0]
    pinhole = Pinhole(np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]]), np.zeros(5))
    start = cell.shoot(cell.start())
    guess = CellGuess(cell.start(), scene.hand_eye_matrix, setup=scene.setup)
    Y = rough_target_from_image(start.corners, pinhole, board, guess, start.ids)
    d0 = float(np.linalg.norm(camera_from_robot(cell.start(), scene.hand_eye_matrix, Y,
                                                scene.setup)[:3, 3]))
    c0 = time.process_time()
    try:
        plan = plan_stations(20, CellGuess(cell.start(), scene.hand_eye_matrix, Y, scene.setup),
                             pinhole, board, PlanOptions(
                                 image_size=(w, h), distance_band=(0.8 * d0, 1.3 * d0),
                                 workspace=(scene.workspace.lo, scene.workspace.hi), rng=seed))
    except ValueError:
        out.wall_s = time.perf_counter() - t0
        return out
    out.plan_s.append(time.process_time() - c0)
    good = _visit(cell, list(plan.tcp_poses), out)
    _calibrate(good, cell, out)
    out.stations, out.wall_s = len(good), time.perf_counter() - t0
    return out


def one_cell(k: int) -> dict[str, Outcome]:
    """Every method on blind cell ``k`` (eye-in-hand for even ``k``)."""
    setup = ("eye_in_hand", "eye_to_hand")[k % 2]
    scene = random_blind_scene(k, setup)
    out = {"cold start": cold_start(CornerCell(scene), k),
           "easy_handeye": easy_handeye(CornerCell(scene)),
           "random": random_poses(CornerCell(scene), k),
           "oracle": oracle(CornerCell(scene), k)}
    X_readings, X_rigid = readings_hand_eye(scene, scale=True), readings_hand_eye(scene)
    for o in out.values():
        o.cell = k
        if o.hand_eye is not None:
            rot, trans = pose_error(np.array(o.hand_eye), X_readings)
            o.rf_deg, o.rf_mm = float(np.degrees(rot)), float(trans * 1e3)
            rot, trans = pose_error(np.array(o.hand_eye), X_rigid)
            o.rigid_deg, o.rigid_mm = float(np.degrees(rot)), float(trans * 1e3)
    cs = out["cold start"]
    print(f"cell {k:2d} {setup:11s} cold start: {cs.stations:2d} stations + {cs.explore} "
          f"exploratory, {cs.err_deg:.3f} deg / {cs.err_mm:.2f} mm, σ {cs.sigma_deg:.3f} / "
          f"{cs.sigma_mm:.2f}, σ <= tolerance after {cs.tol_stations}, bound met "
          f"{cs.bound_met}, ok against the flange {cs.flange_success}; readings frame "
          f"{cs.rf_deg:.3f} deg / {cs.rf_mm:.2f} mm, ok {cs.success}; random "
          f"{out['random'].stations} stations", flush=True)
    return out


def run(cells: list[int], jobs: int, log: Path) -> dict[str, list[Outcome]]:
    """The blind cells numbered ``cells``, ``jobs`` at a time; each cell's outcomes appended to
    ``log`` (JSON lines) as it finishes, so a long run that is stopped still leaves its
    figures."""
    results: dict[str, list[Outcome]] = {m: [] for m in METHODS}
    log.write_text("")
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        for out in pool.imap_unordered(one_cell, cells):
            with log.open("a") as f:
                f.write(json.dumps({m: asdict(o) for m, o in out.items()}) + "\n")
            for m in METHODS:
                results[m].append(out[m])
    return results


def _numbers(text: str) -> list[int]:
    """Cell numbers from ``8,10,12``."""
    try:
        cells = [int(k) for k in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of cell numbers: {text!r}") from None
    if any(k < 0 for k in cells):
        raise argparse.ArgumentTypeError(f"cell numbers are 0 or more: {text!r}")
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="6 cells instead of 50")
    parser.add_argument("--cells", type=int, default=None, help="cells 0 to CELLS - 1")
    parser.add_argument("--only", type=_numbers, default=None, metavar="K[,K...]",
                        help="only these cells, by number (e.g. 8,10,12: the same cells and "
                             "seeds as in a full run)")
    parser.add_argument("--jobs", type=int, default=2, help="cells at a time (processes)")
    parser.add_argument("--from-log", action="store_true",
                        help="only tabulate the cells a previous run logged")
    args = parser.parse_args()
    interrupt_on_sigterm()  # the worker pool is terminated, not left running
    cells = args.only or list(range(args.cells or (6 if args.quick else 50)))
    OUT.mkdir(exist_ok=True)
    log = OUT / "cold_start.jsonl"
    t0 = time.perf_counter()
    results = read_log(log) if args.from_log else run(cells, args.jobs, log)
    print(table(results))
    plot(results, OUT / "cold_start.png")
    print(f"{len(results['cold start'])} cells in {time.perf_counter() - t0:.0f} s; wrote "
          f"{OUT / 'cold_start.png'}")


if __name__ == "__main__":
    main()
