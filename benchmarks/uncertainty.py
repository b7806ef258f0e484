"""Is the reported 1-sigma honest on an arm with systematic kinematic errors? (issue 8, part 3)

A simulated UR5e whose true DH parameters differ from the nominal ones by a few 0.01 deg and
0.1 mm (``mocks/scenes/ur5e_kinematic_errors.json``) besides per-reading noise: every seed
draws new stations, projects the board from the *true* flange poses (0.15 px corner noise),
records the *nominal* poses with reading noise, and runs the default calibration. Over the
seeds, the hand-eye errors (Monte Carlo) are compared with the reported σ, the formal σ alone
and the fold jackknife:

* **MC error / σ** (the acceptance figure): the RMS over seeds and axes of each calibration's
  error against the true hand-eye divided by the σ that calibration reported — 1 when the
  σ's are honest. The error includes the bias the arm's fixed kinematic errors cause, as it
  would for a user, and each seed is judged by its own σ (station sets differ: a seed whose
  stations pin the depth down poorly reports a larger σ and has a larger error).
* **σ / MC spread**: the RMS of the σ's over the standard deviation of the estimates across
  seeds (bias excluded); dominated by the seeds with the largest σ.

The same scene without kinematic errors is the control.

    python -m benchmarks.uncertainty            # 60 seeds per scene, about 5 min on 2 cores
    python -m benchmarks.uncertainty --quick    # 12 seeds

Prints a table and writes benchmarks/results/uncertainty.png.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from benchmarks.stationset import station_set
from calib import Checkerboard, calibrate
from mocks.cornersim import simulate_corners
from mocks.scene import MockScene, load_scene

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import results_dir

OUT = results_dir()
SCENE = Path(__file__).resolve().parents[1] / "mocks" / "scenes" / "ur5e_kinematic_errors.json"
PIXEL_NOISE = 0.15
#: The σ's compared: reported, formal, fold jackknife.
KINDS = ("sigma", "formal", "jk")
#: hand-eye parameters compared: (name, unit factor for the table)
PARAMS = (("hand_eye_rot_rad", np.degrees(1.0), "deg"), ("hand_eye_trans_m", 1e3, "mm"))


def monte_carlo(scene: MockScene, seeds: int, n: int = 20) -> dict[str, np.ndarray]:
    """Per seed: hand-eye errors against the truth (rotation vector, translation) and σ's."""
    X_true = scene.hand_eye_matrix
    out: dict[str, list] = {k: [] for k in ("rot", "trans", "sigma_rot", "sigma_trans",
                                            "formal_rot", "formal_trans", "jk_rot", "jk_trans")}
    t = scene.target
    label = "control" if scene.kinematics is None else "kinematic errors"
    for seed in tqdm(range(seeds), desc=label, leave=False):
        rng = np.random.default_rng(1000 + seed)
        corners, poses = simulate_corners(scene, n, rng, PIXEL_NOISE)
        r = calibrate(station_set(corners, poses,
                                  Checkerboard(tuple(t.inner_corners), t.square_size_m),
                                  image_size=scene.camera.image_size, setup=scene.setup))
        u = r.trust.uncertainty
        out["rot"].append(Rotation.from_matrix(r.hand_eye[:3, :3] @ X_true[:3, :3].T)
                          .as_rotvec())
        out["trans"].append(r.hand_eye[:3, 3] - X_true[:3, 3])
        for key, name in (("rot", "hand_eye_rot_rad"), ("trans", "hand_eye_trans_m")):
            out[f"sigma_{key}"].append(u.sigmas[name])
            out[f"formal_{key}"].append(u.formal[name])
            out[f"jk_{key}"].append(u.jackknife.get(name, np.full(3, np.nan)))
    return {k: np.array(v) for k, v in out.items()}


def ratios(mc: dict[str, np.ndarray]) -> dict[str, float]:
    """Per block (``rot``, ``trans``): ``z_<kind>`` the MC error / σ (RMS over seeds and axes
    of error / σ), ``<kind>`` the RMS σ / MC spread, for the reported, formal and jackknife
    σ; ``sigma_over_jk`` the median over seeds of |reported σ| / |jackknife|."""
    r = {}
    for key in ("rot", "trans"):
        spread = np.sqrt(np.mean(np.var(mc[key], axis=0, ddof=1)))
        for kind in KINDS:
            sigma = mc[f"{kind}_{key}"]
            r[f"z_{kind}_{key}"] = float(np.sqrt(np.nanmean((mc[key] / sigma) ** 2)))
            r[f"{kind}_{key}"] = float(np.sqrt(np.nanmean(sigma ** 2)) / spread)
        r[f"spread_{key}"] = float(spread)
        r[f"sigma_over_jk_{key}"] = float(np.nanmedian(
            np.linalg.norm(mc[f"sigma_{key}"], axis=1) / np.linalg.norm(mc[f"jk_{key}"], axis=1)))
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="12 seeds per scene")
    ap.add_argument("--seeds", type=int, default=60, help="seeds per scene (default 60)")
    args = ap.parse_args()
    seeds = 12 if args.quick else args.seeds
    scene = load_scene(SCENE)
    rows = {"kinematic errors": ratios(monte_carlo(scene, seeds)),
            "control (no kinematic errors)": ratios(monte_carlo(
                scene.model_copy(update={"kinematics": None}), seeds))}
    print(f"{seeds} seeds, 20 stations each (target: MC error / reported sigma 0.8-1.25, "
          f"reported / jackknife >= 0.7)")
    columns = [("MC error/σ rot", "z_sigma_rot"), ("MC error/σ trans", "z_sigma_trans"),
               ("formal: rot", "z_formal_rot"), ("formal: trans", "z_formal_trans"),
               ("jackknife: rot", "z_jk_rot"), ("jackknife: trans", "z_jk_trans"),
               ("σ/MC spread rot", "sigma_rot"), ("σ/MC spread trans", "sigma_trans"),
               ("σ/jackknife rot", "sigma_over_jk_rot"),
               ("σ/jackknife trans", "sigma_over_jk_trans")]
    print("| scene | MC spread rot (deg) | MC spread trans (mm) | "
          + " | ".join(c for c, _ in columns) + " |")
    print("|---" * (len(columns) + 3) + "|")
    for name, r in rows.items():
        print(f"| {name} | {np.degrees(r['spread_rot']):.4f} | {1e3 * r['spread_trans']:.3f} | "
              + " | ".join(f"{r[k]:.2f}" for _, k in columns) + " |")
    OUT.mkdir(exist_ok=True)
    fig, ax = plt.subplots(figsize=(9, 4.5))
    x = np.arange(len(rows))
    for k, (kind, label) in enumerate(zip(KINDS, ("reported", "formal", "jackknife"),
                                          strict=True)):
        for j, block in enumerate(("rot", "trans")):
            ax.bar(x * 3 + j * 1.4 + k * 0.4, [r[f"z_{kind}_{block}"] for r in rows.values()],
                   0.38, label=f"{label} ({block})", color=f"C{k}",
                   alpha=1.0 if block == "rot" else 0.55)
    ax.axhspan(0.8, 1.25, color="green", alpha=0.12, label="target 0.8-1.25")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks(x * 3 + 1.1, list(rows))
    ax.set_ylabel("RMS of error / sigma (1 = honest)")
    ax.set_title(f"Hand-eye errors over their 1-sigma, {seeds} simulated calibrations")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(OUT / "uncertainty.png", dpi=110)
    print(f"wrote {OUT / 'uncertainty.png'}")

if __name__ == "__main__":
    main()
