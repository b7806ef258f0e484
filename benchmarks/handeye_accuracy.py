"""Hand-eye accuracy and speed: SM (ours) and our refinement against OpenCV's methods.

Reproduces the trends of Zhao & Liu Fig. 2 (errors vs noise, 20 motions) and Fig. 3 (errors vs
number of motions), then a realistic eye-in-hand scene (15 stations, robot noise 0.05 deg /
0.25 mm per reading, camera poses from PnP on 0.15 px corner noise) with RMS errors over many
seeds, and the solver speed on 20 stations.

    python -m benchmarks.handeye_accuracy            # full run (a few minutes)
    python -m benchmarks.handeye_accuracy --quick    # smoke run

Prints tables and writes benchmarks/results/handeye_accuracy.png.
"""

from __future__ import annotations

import argparse
import time

import cv2
import matplotlib
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from calib import (
    OPENCV_HAND_EYE_METHODS,
    POSE_METHODS,
    calibrate_hand_eye,
    invert,
    make_transform,
    pose_error,
    solve_sm,
    station_motions,
)
from mocks.posesim import default_cell, simulate

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import results_dir

OPENCV = [m for m in POSE_METHODS if m not in ("sm", "refine")]
OUT = results_dir()


def noisy_motion(T: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Zhao & Liu's noise model: absolute on the unit quaternion, relative on the translation."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat() + rng.normal(0.0, sigma, 4)
    t = T[:3, 3] * (1.0 + rng.normal(0.0, sigma, 3))
    return make_transform(Rotation.from_quat(q / np.linalg.norm(q)).as_matrix(), t)


def paper_stations(n_motions: int, sigma: float, rng: np.random.Generator):
    """A chain of n_motions noisy hand and camera motions turned into n_motions + 1 stations."""
    X = default_cell().hand_eye
    P, C = [np.eye(4)], [make_transform(np.eye(3), [0.0, 0.0, 0.5])]
    for _ in range(n_motions):
        rotvec = Rotation.random(random_state=rng).as_rotvec()
        rotvec *= np.deg2rad(rng.uniform(20.0, 60.0)) / np.linalg.norm(rotvec)
        M = make_transform(Rotation.from_rotvec(rotvec).as_matrix(), rng.uniform(-0.2, 0.2, 3))
        N = invert(X) @ M @ X  # camera motion: A X = X B with A = M (hand)
        P.append(P[-1] @ noisy_motion(M, sigma, rng))
        C.append(invert(noisy_motion(N, sigma, rng)) @ C[-1])
    return np.stack(P), np.stack(C), X


def paper_errors(methods, n_motions, sigma, trials, seed):
    """e_q (eq. 19) and relative e_t (eq. 20) per method."""
    eq = {m: [] for m in methods}
    et = {m: [] for m in methods}
    rng = np.random.default_rng(seed)
    for _ in range(trials):
        P, C, X = paper_stations(n_motions, sigma, rng)
        q_true = Rotation.from_matrix(X[:3, :3]).as_quat()
        for m in methods:
            try:
                est = calibrate_hand_eye(P, C, method=m).hand_eye
            except (ValueError, cv2.error):
                est = np.full((4, 4), np.nan)
            if not np.isfinite(est).all():
                eq[m].append(np.nan)
                et[m].append(np.nan)
                continue
            q = Rotation.from_matrix(est[:3, :3]).as_quat()
            q = q if q @ q_true >= 0 else -q
            eq[m].append(np.sum((q - q_true) ** 2))
            et[m].append(np.sum((est[:3, 3] - X[:3, 3]) ** 2))
    tn = np.linalg.norm(default_cell().hand_eye[:3, 3])
    return ({m: float(np.sqrt(np.nanmean(v))) for m, v in eq.items()},
            {m: float(np.sqrt(np.nanmean(v)) / tn) for m, v in et.items()})


def realistic(setup: str, seeds: int, stations: int = 15):
    cell = default_cell(setup)
    err = {m: [] for m in POSE_METHODS}
    yerr = {m: [] for m in POSE_METHODS}
    for seed in tqdm(range(seeds), desc=f"realistic {setup}", leave=False):
        P, C = simulate(cell, stations, np.random.default_rng(seed))
        for m in POSE_METHODS:
            r = calibrate_hand_eye(P, C, setup=setup, method=m)
            err[m].append(pose_error(r.hand_eye, cell.hand_eye))
            yerr[m].append(pose_error(r.target_pose, cell.target_pose))

    def rms(v):
        a = np.array(v)
        return np.degrees(np.sqrt(np.mean(a[:, 0] ** 2))), 1e3 * np.sqrt(np.mean(a[:, 1] ** 2))
    return {m: (*rms(err[m]), *rms(yerr[m])) for m in POSE_METHODS}


def speed(repeats: int = 300):
    """Median seconds per solve on 20 stations: SM (motions + solve) vs cv2 Park."""
    P, C = simulate(default_cell(), 20, np.random.default_rng(0))

    def sm():
        mot = station_motions(P, C)
        length = float(np.median(np.linalg.norm(mot.A[:, :3, 3], axis=1)))
        solve_sm(mot.A, mot.B, length_scale=length)

    Rg, tg, Rc, tc = list(P[:, :3, :3]), list(P[:, :3, 3:]), list(C[:, :3, :3]), list(C[:, :3, 3:])

    def park():
        cv2.calibrateHandEye(Rg, tg, Rc, tc, method=OPENCV_HAND_EYE_METHODS["park"])

    def api(method):
        return lambda: calibrate_hand_eye(P, C, method=method)

    out = {}
    for name, fn in [("sm core", sm), ("opencv park core", park), ("sm via API", api("sm")),
                     ("park via API", api("park")), ("refine via API", api("refine"))]:
        fn()
        times = []
        for _ in range(repeats if "refine" not in name else max(repeats // 20, 5)):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[name] = float(np.median(times))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few trials, for a smoke run")
    ap.add_argument("--seeds", type=int, default=200, help="seeds for the realistic scene")
    ap.add_argument("--trials", type=int, default=200, help="trials per point for Fig. 2/3")
    args = ap.parse_args()
    seeds, trials = (10, 10) if args.quick else (args.seeds, args.trials)
    fig_methods = ["sm", *OPENCV]

    print(f"# Fig. 2 (Zhao & Liu): errors vs noise level, 20 motions, {trials} trials per point")
    levels = [0.0, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1]  # 0: exactness check (table only)
    fig2 = [paper_errors(fig_methods, 20, s, trials, 1) for s in tqdm(levels, desc="fig2")]
    _table("noise", levels, fig2, fig_methods)

    print(f"\n# Fig. 3: errors vs number of motions, noise 0.01, {trials} trials per point")
    counts = [2, 3, 4, 6, 8, 10, 15, 20]
    fig3 = [paper_errors(fig_methods, n, 0.01, trials, 2) for n in tqdm(counts, desc="fig3")]
    _table("motions", counts, fig3, fig_methods)

    scenes = {}
    for setup in ("eye_in_hand", "eye_to_hand"):
        print(f"\n# Realistic {setup} scene: 15 stations, robot 0.05 deg / 0.25 mm, PnP on "
              f"0.15 px corners, RMS over {seeds} seeds")
        res = realistic(setup, seeds)
        scenes[setup] = res
        best_r = min(res[m][0] for m in OPENCV)
        best_t = min(res[m][1] for m in OPENCV)
        print(f"{'method':<11} {'X rot deg':>10} {'X trans mm':>11} {'Y rot deg':>10} "
              f"{'Y trans mm':>11} {'rot/bestCV':>11} {'trans/bestCV':>13}")
        for m, (r, t, yr, yt) in res.items():
            print(f"{m:<11} {r:10.4f} {t:11.4f} {yr:10.4f} {yt:11.4f} {r / best_r:11.3f} "
                  f"{t / best_t:13.3f}")
        sm, refined = res["sm"], res["refine"]
        print(f"targets: SM rot <= 1.05x best OpenCV: {sm[0] / best_r:.3f} "
              f"[{'ok' if sm[0] <= 1.05 * best_r else 'MISS'}]; SM trans <= best OpenCV: "
              f"{sm[1] / best_t:.3f} [{'ok' if sm[1] <= best_t else 'MISS'}]; refine/SM rot "
              f"{refined[0] / sm[0]:.3f}, trans {refined[1] / sm[1]:.3f} "
              f"[{'ok' if refined[0] <= 1.05 * sm[0] and refined[1] <= 1.05 * sm[1] else 'MISS'}]")

    print("\n# Speed, 20 stations (median seconds per solve)")
    sp = speed(30 if args.quick else 300)
    for k, v in sp.items():
        print(f"{k:<18} {v * 1e3:8.3f} ms")
    print(f"SM core / OpenCV Park core = {sp['sm core'] / sp['opencv park core']:.2f} "
          f"(target <= 3); via API {sp['sm via API'] / sp['park via API']:.2f}")
    _plot((levels, fig2), (counts, fig3), scenes, fig_methods)


def _table(label, xs, results, methods):
    print(f"{label:>8} " + " ".join(f"{m:>11}" for m in methods) + "   (e_q | e_t)")
    for x, (eq, et) in zip(xs, results, strict=True):
        print(f"{x:>8} " + " ".join(f"{eq[m]:11.5f}" for m in methods))
        print(f"{'':>8} " + " ".join(f"{et[m]:11.5f}" for m in methods))


def _plot(noise_sweep, count_sweep, scenes, methods):
    """Fig. 2 (``noise_sweep`` = levels, results) and Fig. 3 (``count_sweep`` = motion counts,
    results) reproductions and the realistic ``scenes``, one PNG."""
    (levels, fig2), (counts, fig3) = noise_sweep, count_sweep
    OUT.mkdir(exist_ok=True)
    fig, ax = plt.subplots(2, 3, figsize=(16, 9))
    for col, (xs, res, xl) in enumerate([(levels[1:], fig2[1:], "noise level"),
                                         (counts, fig3, "number of motions")]):
        for row in range(2):
            for m in methods:
                ax[row, col].plot(xs, [r[row][m] for r in res], marker="o", label=m,
                                  lw=2.5 if m == "sm" else 1.0)
            ax[row, col].set_xlabel(xl)
            ax[row, col].set_ylabel("e_q (eq. 19)" if row == 0 else "e_t (eq. 20, relative)")
            ax[row, col].set_yscale("log")
            ax[row, col].grid(alpha=0.3)
    ax[0, 0].legend(fontsize=8)
    ax[0, 0].set_title("Fig. 2 reproduction: 20 motions")
    ax[0, 1].set_title("Fig. 3 reproduction: noise 0.01")
    for row, setup in enumerate(scenes):
        res = scenes[setup]
        names = list(res)
        xs = np.arange(len(names))
        a = ax[row, 2]
        a.bar(xs - 0.2, [res[m][0] for m in names], 0.4, label="X rot (deg)")
        a2 = a.twinx()
        a2.bar(xs + 0.2, [res[m][1] for m in names], 0.4, color="tab:orange",
               label="X trans (mm)")
        a.set_xticks(xs, names, rotation=45, fontsize=8)
        a.set_ylabel("rotation RMS (deg)")
        a2.set_ylabel("translation RMS (mm)")
        a.set_title(f"realistic {setup}, 15 stations")
        a.set_ylim(0, 3 * min(res[m][0] for m in names))
        a2.set_ylim(0, 3 * min(res[m][1] for m in names))
    fig.tight_layout()
    fig.savefig(OUT / "handeye_accuracy.png", dpi=90)
    print(f"\nplot: {OUT / 'handeye_accuracy.png'}")


if __name__ == "__main__":
    main()
