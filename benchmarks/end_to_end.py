"""Speed as a user meets it: whole processes, imports included, paired A B A B in one run.

    .venv/bin/python -m benchmarks.end_to_end          # 18 stations, 7 pairs, real sets, 200
    .venv/bin/python -m benchmarks.end_to_end --quick  # 3 pairs, one real set
    .venv/bin/python -m benchmarks.end_to_end --startup  # cellcal --version / --help alone

(a) ``cellcal calibrate DIR`` with its default options (detection, intrinsics, hand-eye, joint
fit, cross-validation and model selection) against ``benchmarks/opencv_pipeline.py DIR``
(``findChessboardCornersSB`` with default flags, ``calibrateCamera``, ``calibrateHandEye``) on
rendered 1280x1024 stations; (b) ``cellcal --version``; (c) detection alone on the real sets
(``../shared/data``): one process runs ``calib``'s detector over every image, its peer
``findChessboardCornersSB`` with default flags, each timing its own loop after reading the
images; (d) ``--startup``: ``cellcal --version`` and ``cellcal --help`` alone, 10 runs each,
best and median wall time (``startup.md``). Each pair runs its two processes one after the
other, the order alternating; CPU time is the process's and its children's (``getrusage``),
wall time the caller's clock. Medians over the pairs, and the median of the per-pair ratios.
Writes ``benchmarks/results/end_to_end.{md,png}``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import matplotlib
import numpy as np

from benchmarks import results_dir
from benchmarks.kappa_nu import bench_scene, rendered_station_set
from calib import ur_pose_from_matrix

matplotlib.use("Agg")
import matplotlib.pyplot as plt

ROOT = Path(__file__).resolve().parents[1]
OUT = results_dir()
DATA = ROOT.parent / "shared" / "data"
CELLCAL = str(Path(sys.executable).with_name("cellcal"))
REAL_SETS = ("rwhe-kuka_1", "ur-kinect-highR_highT", "ur-kinect-lowR_highT")


def write_rendered_set(directory: Path, n: int, seed: int = 1) -> None:
    """``n`` rendered 1280x1024 stations of the default cell (robot 0.05 deg / 0.25 mm)."""
    scene = bench_scene()
    images, P, _ = rendered_station_set(scene, n, np.random.default_rng(seed))
    stations = []
    for k, (image, pose) in enumerate(zip(images, ur_pose_from_matrix(P), strict=True)):
        cv2.imwrite(str(directory / f"{k:03d}.png"), image)
        stations.append({"id": f"{k:03d}", "tcp_pose": pose.tolist(), "image": f"{k:03d}.png"})
    t = scene.target
    (directory / "stations.json").write_text(json.dumps({
        "format": "cellcal/stations@1", "setup": scene.setup,
        "target": {"type": "checkerboard", "inner_corners": list(t.inner_corners),
                   "square_size_m": t.square_size_m}, "stations": stations}))


def timed(argv: Sequence[str]) -> tuple[float, float, str]:
    """Run ``argv`` to its end: (CPU s of it and its children, wall s, stdout)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall, done.stdout


def pairs(a: Sequence[str], b: Sequence[str], n: int) -> dict[str, np.ndarray]:
    """``n`` pairs, A first in even pairs and B first in odd ones: CPU and wall of each,
    shape (n,)."""
    out: dict[str, list[float]] = {"a_cpu": [], "a_wall": [], "b_cpu": [], "b_wall": []}
    for k in range(n):
        for side in ("ab" if k % 2 == 0 else "ba"):
            cpu, wall, _ = timed(a if side == "a" else b)
            out[f"{side}_cpu"].append(cpu)
            out[f"{side}_wall"].append(wall)
    return {key: np.array(v) for key, v in out.items()}


def detection_pairs(directory: Path, n: int) -> dict[str, np.ndarray]:
    """Detection loops of ``directory``'s images, cellcal against SB with default flags:
    each process reports its own loop's CPU and wall time (images already in memory)."""
    out: dict[str, list[float]] = {"a_cpu": [], "a_wall": [], "b_cpu": [], "b_wall": [],
                                   "a_read": [], "b_read": []}
    for k in range(n):
        for side in ("ab" if k % 2 == 0 else "ba"):
            who = "cellcal" if side == "a" else "opencv"
            _, _, text = timed([sys.executable, "-m", "benchmarks.end_to_end", "--detect-worker",
                                who, str(directory)])
            loop = json.loads(text)
            out[f"{side}_cpu"].append(loop["cpu"])
            out[f"{side}_wall"].append(loop["wall"])
            out[f"{side}_read"].append(loop["read"])
    return {key: np.array(v) for key, v in out.items()}


def detect_worker(who: str, directory: Path) -> None:
    """Read every image of ``directory``, then time detecting them all; print JSON."""
    doc = json.loads((directory / "stations.json").read_text())
    board = tuple(doc["target"]["inner_corners"])
    images = [cv2.imread(str(directory / s["image"]), cv2.IMREAD_GRAYSCALE)
              for s in doc["stations"]]
    if who == "cellcal":
        from calib.boards import detect_checkerboard

        def detect(grey: np.ndarray) -> bool:
            return detect_checkerboard(grey, board).ok
    else:
        def detect(grey: np.ndarray) -> bool:
            return bool(cv2.findChessboardCornersSB(grey, board)[0])
    c0, t0 = time.process_time(), time.perf_counter()
    read = sum(detect(g) for g in images)
    print(json.dumps({"cpu": time.process_time() - c0, "wall": time.perf_counter() - t0,
                      "read": read, "images": len(images)}))


def startup(runs: int = 10) -> str:
    """``cellcal --version`` and ``--help`` (and the bare interpreter), ``runs`` times each,
    interleaved: best and median wall and CPU time, as a table."""
    argvs = {"cellcal --version": [CELLCAL, "--version"], "cellcal --help": [CELLCAL, "--help"],
             "python -c pass": [sys.executable, "-c", "pass"]}
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in argvs}
    for _ in range(runs):
        for name, argv in argvs.items():
            cpu, wall, _ = timed(argv)
            times[name].append((cpu, wall))
    lines = [f"load average at start: {load()}; {runs} runs each, interleaved", "",
             "| command | best wall s | median wall s | best CPU s | median CPU s |",
             "|---|---|---|---|---|"]
    for name, t in times.items():
        cpu, wall = np.array(t).T
        lines.append(f"| `{name}` | **{wall.min():.3f}** | {np.median(wall):.3f} | "
                     f"{cpu.min():.3f} | {np.median(cpu):.3f} |")
    return "\n".join([*lines, "", f"load average at end: {load()}"])


def summary(r: dict[str, np.ndarray]) -> dict[str, float]:
    """Medians of each side and of the per-pair ratios A / B."""
    return {"a_cpu": float(np.median(r["a_cpu"])), "b_cpu": float(np.median(r["b_cpu"])),
            "a_wall": float(np.median(r["a_wall"])), "b_wall": float(np.median(r["b_wall"])),
            "cpu_ratio": float(np.median(r["a_cpu"] / r["b_cpu"])),
            "wall_ratio": float(np.median(r["a_wall"] / r["b_wall"]))}


def load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--stations", type=int, default=18)
    ap.add_argument("--pairs", type=int, default=7)
    ap.add_argument("--large", type=int, default=200,
                    help="stations of one more cellcal calibrate run, timed alone (0: none)")
    ap.add_argument("--startup", action="store_true",
                    help="only cellcal --version and --help, 10 runs each (startup.md)")
    ap.add_argument("--detect-worker", nargs=2, metavar=("WHO", "DIR"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.detect_worker:
        detect_worker(args.detect_worker[0], Path(args.detect_worker[1]))
        return
    if args.startup:
        text = startup()
        print(text)
        OUT.mkdir(exist_ok=True)
        (OUT / "startup.md").write_text(text + "\n")
        return
    n_pairs = 3 if args.quick else args.pairs
    lines = [f"load average at start: {load()} (1, 5, 15 min); {os.cpu_count()} cores", ""]
    results: dict[str, dict[str, np.ndarray]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        station_dir = Path(tmp, "stations")
        station_dir.mkdir()
        write_rendered_set(station_dir, args.stations)
        results[f"calibrate, {args.stations} stations"] = pairs(
            [CELLCAL, "calibrate", str(station_dir), "--out", str(Path(tmp, "result.json"))],
            [sys.executable, str(ROOT / "benchmarks" / "opencv_pipeline.py"), str(station_dir)],
            n_pairs)
        large = 0 if args.quick else args.large
        if large:
            big = Path(tmp, "large")
            big.mkdir()
            write_rendered_set(big, large, seed=2)
            cpu, wall, _ = timed([CELLCAL, "calibrate", str(big), "--out",
                                  str(Path(tmp, "r.json"))])
            lines += [f"cellcal calibrate on {large} rendered stations, one run: {cpu:.1f} CPU s, "
                      f"{wall:.1f} s wall (target < 30 s)", ""]
    results["--version"] = pairs([CELLCAL, "--version"], [sys.executable, "-c", "pass"], n_pairs)
    for name in REAL_SETS[:1] if args.quick else REAL_SETS:
        results[f"detection, {name}"] = detection_pairs(DATA / name, n_pairs)
    lines += ["| A / B | A CPU s | B CPU s | CPU ratio | A wall s | B wall s | wall ratio |",
              "|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        s = summary(r)
        peer = ("OpenCV script" if name.startswith("calibrate") else "python -c pass"
                if name == "--version" else "SB default flags")
        label = (f"cellcal {name} / {peer}" if not name.startswith("detection")
                 else f"{name}: cellcal / {peer} (images read {int(r['a_read'][0])} / "
                      f"{int(r['b_read'][0])})")
        lines.append(f"| {label} | {s['a_cpu']:.2f} | {s['b_cpu']:.2f} | "
                     f"**{s['cpu_ratio']:.2f}** | {s['a_wall']:.2f} | {s['b_wall']:.2f} | "
                     f"**{s['wall_ratio']:.2f}** |")
    lines += ["", f"load average at end: {load()}; {n_pairs} pairs each, medians"]
    text = "\n".join(lines)
    print(text)
    OUT.mkdir(exist_ok=True)
    (OUT / "end_to_end.md").write_text(text + "\n")
    plot(results)


def plot(results: dict[str, dict[str, np.ndarray]]) -> None:
    fig, axes = plt.subplots(1, len(results), figsize=(4 * len(results), 4))
    for ax, (name, r) in zip(np.atleast_1d(axes), results.items(), strict=True):
        k = np.arange(len(r["a_cpu"]))
        ax.plot(k, r["a_cpu"], "o-", color="tab:blue", label="cellcal CPU")
        ax.plot(k, r["a_wall"], "o--", color="tab:blue", label="cellcal wall")
        ax.plot(k, r["b_cpu"], "s-", color="tab:orange", label="peer CPU")
        ax.plot(k, r["b_wall"], "s--", color="tab:orange", label="peer wall")
        ax.set(title=name, xlabel="pair", ylabel="s", ylim=(0, None))
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "end_to_end.png", dpi=90)
    print(f"plot: {OUT / 'end_to_end.png'}")


if __name__ == "__main__":
    main()
