"""ChArUco: detection speed against ``CharucoDetector.detectBoard``, and rendered station sets
against the truth, the Cramér-Rao bound and OpenCV's ChArUco pipeline (issue 9).

(a) Speed. cellcal's detection is OpenCV's ``CharucoDetector.detectBoard`` plus what makes its
corners a calibration input: every corner refined on the smoothed image, corners too near the
border dropped, the minimum-corner check and the quality figures (sharpness, coverage,
contrast). Target: at most 1.2x ``detectBoard`` alone on 1920x1200 images. Images: a 12x9-square
board (30 mm squares, 22 mm ``DICT_5X5_100`` markers) drawn by OpenCV (``generateImage``, 100 px
per square) and warped into a 1920x1200 frame by homographies of varied scale, rotation and
perspective, half of them cutting the board at the image border; Gaussian blur 0.8 px and noise
2 grey levels. Both detectors run on the same grey image, interleaved, the median of 9 runs
each; the figure is the median over images of the ratio.

(b) Rendered scenes (``mocks.scene.charuco_scene``: 1280x1024, the same board printed with
κ 1.004, ν 0.998; robot readings 0.05 deg / 0.25 mm as in ``benchmarks.kappa_nu``). Per seed, 15
stations of which 40 % cut the board at an image corner (``StationSpread.cut_fraction``), every
image rendered (``mocks.render``, blur 0.7 px, noise 2 grey levels) and read by
``Charuco.detect``; ``calibrate`` (the default, joint ML with κ, ν) on them gives

- κ and ν against the truth (targets 1e-3 and 2e-4 on every seed);
- the hand-eye error against the Cramér-Rao bound of the same stations and corners
  (``benchmarks.kappa_nu.scene_bound``; RMS over seeds, target <= 1.2);
- the projection error at the four image corners (``calib.image_corner_error``) against a
  calibration from 15 whole-board views of the same scene (RMS over seeds, target: the cut set
  at least 1.5x lower);
- the 5-fold cross-validated pixel error (``benchmarks.real_cv.cross_validate``: held-out
  stations predicted from their robot poses, against cellcal's detections) of cellcal and of
  OpenCV's ChArUco pipeline (its own ``CharucoDetector`` corners, ``calibrateCamera`` on the
  nominal board, ``calibrateHandEye`` PARK, Y averaged over the training stations), pooled over
  seeds; target cellcal <= OpenCV.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m benchmarks.charuco          # about 3 min idle
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m benchmarks.charuco --quick  # 2 seeds, 6 images

Prints tables and writes ``benchmarks/results/charuco.png`` / ``charuco.md`` (speed) and
``charuco_scenes.png`` / ``charuco_scenes.md`` (rendered scenes).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import matplotlib
import numpy as np

from benchmarks.kappa_nu import bench_scene, corner_noise, rendered_station_set, scene_bound
from benchmarks.real_cv import StationData, cross_validate, cv_rms
from benchmarks.stationset import station_set
from calib import (
    CalibrationResult,
    Charuco,
    Detection,
    Pinhole,
    calibrate,
    cuts_board_at_corner,
    image_corner_error,
    pose_error,
    ur_pose_from_matrix,
)
from calib.boards import MIN_CHARUCO_CORNERS
from mocks.scene import MockScene, StationSpread, camera_pose_for_tcp, charuco_scene

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import results_dir

OUT = results_dir()
BOARD = Charuco((12, 9), 0.03, 0.022, "DICT_5X5_100")
SIZE = (1920, 1200)
PX = 100  # print pixels per square
REPEATS = 9


# ---- (a) speed --------------------------------------------------------------------------------

def views(n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` grey 1920x1200 images of the board: random similarity + perspective, every
    other one shifted so the board runs off the image."""
    rng = np.random.default_rng(seed)
    cols, rows = BOARD.squares
    flat = BOARD.opencv_board().generateImage((cols * PX, rows * PX), marginSize=0)
    flat = cv2.copyMakeBorder(flat, PX // 2, PX // 2, PX // 2, PX // 2, cv2.BORDER_CONSTANT,
                              value=255)
    h, w = flat.shape
    out = []
    for k in range(n):
        scale = rng.uniform(0.7, 0.95) * SIZE[1] / h
        a = rng.uniform(-np.pi, np.pi)
        centre = np.array(SIZE) / 2 + (rng.uniform(-0.45, 0.45, 2) * SIZE if k % 2 else 0)
        S = np.array([[scale * np.cos(a), -scale * np.sin(a), 0.0],
                      [scale * np.sin(a), scale * np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        T0 = np.array([[1.0, 0.0, -w / 2], [0.0, 1.0, -h / 2], [0.0, 0.0, 1.0]])
        P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [*rng.normal(0.0, 1.5e-4, 2), 1.0]])
        T1 = np.array([[1.0, 0.0, centre[0]], [0.0, 1.0, centre[1]], [0.0, 0.0, 1.0]])
        image = cv2.warpPerspective(flat, T1 @ P @ S @ T0, SIZE, flags=cv2.INTER_AREA,
                                    borderValue=110)
        image = cv2.GaussianBlur(image, (0, 0), 0.8) + rng.normal(0.0, 2.0, image.shape)
        out.append(np.clip(image, 0, 255).astype(np.uint8))
    return out


def _median_ms(fn: Callable[[], object]) -> float:
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def speed(images: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
    """Per image: ms of ``detectBoard`` alone and of ``Charuco.detect``, corners found."""
    detector = cv2.aruco.CharucoDetector(BOARD.opencv_board())
    opencv, ours, n_cv, n_ours = [], [], [], []
    for image in images:
        detector.detectBoard(image)  # warm-up
        BOARD.detect(image)
        opencv.append(_median_ms(lambda im=image: detector.detectBoard(im)))
        ours.append(_median_ms(lambda im=image: BOARD.detect(im)))
        ids = detector.detectBoard(image)[1]
        n_cv.append(0 if ids is None else len(ids))
        det = BOARD.detect(image)
        n_ours.append(len(det.ids) if det.ok else 0)
    return {"opencv_ms": np.array(opencv), "cellcal_ms": np.array(ours),
            "opencv_corners": np.array(n_cv), "cellcal_corners": np.array(n_ours)}


def table(r: dict[str, np.ndarray]) -> str:
    ratio = r["cellcal_ms"] / r["opencv_ms"]
    rows = ["| image | detectBoard (ms) | Charuco.detect (ms) | ratio | corners OpenCV / cellcal |",
            "|---|---|---|---|---|"]
    for k, (a, b, q, m, n) in enumerate(zip(r["opencv_ms"], r["cellcal_ms"], ratio,
                                            r["opencv_corners"], r["cellcal_corners"],
                                            strict=True)):
        rows.append(f"| {k} | {a:.1f} | {b:.1f} | {q:.2f} | {m} / {n} |")
    rows.append(f"| **median** | {np.median(r['opencv_ms']):.1f} | "
                f"{np.median(r['cellcal_ms']):.1f} | **{np.median(ratio):.2f}** | |")
    return "\n".join(rows)


def plot(r: dict[str, np.ndarray], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 3.5))
    k = np.arange(len(r["opencv_ms"]))
    ax.bar(k - 0.2, r["opencv_ms"], 0.4, label="CharucoDetector.detectBoard")
    ax.bar(k + 0.2, r["cellcal_ms"], 0.4, label="cellcal Charuco.detect")
    ax.set_xlabel("image (odd: board cut by the image border)")
    ax.set_ylabel("ms per 1920x1200 image")
    ratio = np.median(r["cellcal_ms"] / r["opencv_ms"])
    ax.set_title(f"ChArUco detection: median ratio {ratio:.2f} (target <= 1.2)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


# ---- (b) rendered scenes ---------------------------------------------------------------------

#: The charuco scene with the benchmark's robot noise; κ, ν as issue 9 asks.
SCENE = bench_scene(charuco_scene(), kappa=1.004, nu=0.998)
STATIONS = 15
CUT = StationSpread(cut_fraction=0.4)
TOL_KAPPA, TOL_NU = 1e-3, 2e-4
OPENCV = "opencv-park"


def scene_board(scene: MockScene) -> Charuco:
    """The nominal board of a ChArUco scene, as the user enters it."""
    return scene.nominal_target().board()


@dataclass(frozen=True)
class RenderedSet:
    """One rendered station set: its detections, the noisy and the true robot poses (n, 4, 4)
    and how many stations cut the board at an image corner."""

    images: list[np.ndarray]
    detections: list[Detection]
    T_base_tcp: np.ndarray
    T_base_tcp_true: np.ndarray
    cut: int

    def calibrate(self, scene: MockScene) -> CalibrationResult:
        """cellcal's default calibration of the set."""
        return calibrate(station_set(self.detections, ur_pose_from_matrix(self.T_base_tcp),
                                     scene_board(scene), image_size=scene.camera.image_size))


def rendered_set(scene: MockScene, seed: int, spread: StationSpread) -> RenderedSet:
    """:data:`STATIONS` rendered stations of ``scene`` spread by ``spread``, read by
    ``Charuco.detect``."""
    rng = np.random.default_rng(seed)
    images, P, P_true = rendered_station_set(scene, STATIONS, rng, spread)
    camera = Pinhole(scene.camera.k_matrix, scene.camera.dist_coeffs)
    cut = sum(cuts_board_at_corner(
        camera.project(scene.true_board_points() @ C[:3, :3].T + C[:3, 3]),
        tuple(scene.camera.image_size), spread.min_cut_points)
        for C in camera_pose_for_tcp(scene, P_true))
    board = scene_board(scene)
    return RenderedSet(images, [board.detect(im) for im in images], P, P_true, int(cut))


def corner_error(scene: MockScene, res: CalibrationResult) -> float:
    """Largest projection error (px) of a calibration at the four image corners."""
    return image_corner_error(Pinhole(res.K, res.dist),
                              Pinhole(scene.camera.k_matrix, scene.camera.dist_coeffs),
                              tuple(scene.camera.image_size))


def opencv_station_data(scene: MockScene, s: RenderedSet) -> StationData:
    """The stations both cellcal and OpenCV's ``CharucoDetector`` read (at least
    :data:`MIN_CHARUCO_CORNERS` corners), with each detector's corners and ids."""
    board = scene_board(scene)
    detector = cv2.aruco.CharucoDetector(board.opencv_board())
    keep, corners_cv, ids_cv = [], [], []
    for k, (image, det) in enumerate(zip(s.images, s.detections, strict=True)):
        corners, ids, _, _ = detector.detectBoard(image)
        if det.ok and ids is not None and len(ids) >= MIN_CHARUCO_CORNERS:
            order = np.argsort(ids.ravel())
            keep.append(k)
            corners_cv.append(corners.reshape(-1, 2).astype(float)[order])
            ids_cv.append(ids.ravel()[order].astype(np.int64))
    return StationData("rendered", board, tuple(scene.camera.image_size),
                       [s.detections[k].corners for k in keep], corners_cv, s.T_base_tcp[keep],
                       ids=[s.detections[k].ids for k in keep], ids_cv=ids_cv)


def scene_run(seed: int, scene: MockScene = SCENE) -> dict:
    """Every figure of one seed (see the module docstring)."""
    cut_set = rendered_set(scene, seed, CUT)
    res = cut_set.calibrate(scene)
    ok = [d.ok for d in cut_set.detections]
    sigma_px = corner_noise(scene, cut_set.detections,
                            camera_pose_for_tcp(scene, cut_set.T_base_tcp_true))
    bound = scene_bound(scene, scene_board(scene), cut_set.T_base_tcp_true[ok], sigma_px,
                        [d.ids for d in cut_set.detections if d.ok])
    rot, trans = pose_error(res.hand_eye, scene.hand_eye_matrix)
    whole = rendered_set(scene, 10_000 + seed, StationSpread()).calibrate(scene)
    errors, _ = cross_validate(opencv_station_data(scene, cut_set), ["cellcal", OPENCV])
    t = scene.target
    return {"seed": seed, "cut": cut_set.cut, "used": len(res.stations),
            "partial": sum(len(d.ids) < len(scene.true_board_points())
                           for d in cut_set.detections if d.ok),
            "sigma_px": sigma_px, "kappa_err": res.kappa - t.kappa, "nu_err": res.nu - t.nu,
            "rot": rot, "trans": trans, "bound_rot": bound["rot"],
            "bound_trans": bound["trans"], "corner_cut": corner_error(scene, res),
            "corner_whole": corner_error(scene, whole), "cv": errors}


def summary(runs: Sequence[dict]) -> dict[str, float]:
    """The acceptance figures over seeds."""
    rms = lambda key: float(np.sqrt(np.mean([r[key] ** 2 for r in runs])))  # noqa: E731
    pooled = {m: cv_rms(np.concatenate([r["cv"][m] for r in runs])) for m in runs[0]["cv"]}
    return {"kappa_max": max(abs(r["kappa_err"]) for r in runs),
            "nu_max": max(abs(r["nu_err"]) for r in runs),
            "rot_ratio": rms("rot") / rms("bound_rot"),
            "trans_ratio": rms("trans") / rms("bound_trans"),
            "corner_cut": rms("corner_cut"), "corner_whole": rms("corner_whole"),
            "corner_ratio": rms("corner_whole") / rms("corner_cut"),
            "cv_cellcal": pooled["cellcal"], "cv_opencv": pooled[OPENCV],
            "cv_ratio": pooled["cellcal"] / pooled[OPENCV],
            "cut_share": sum(r["cut"] for r in runs) / (STATIONS * len(runs))}


def scenes_table(runs: Sequence[dict]) -> str:
    s = summary(runs)
    rows = ["| seed | cut / partial / used stations | corner σ (px) | κ error | ν error | "
            "X rot / bound (deg) | X trans / bound (mm) | image corners: cut / whole-board "
            "set (px) | CV px: cellcal / OpenCV |", "|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        rows.append(
            f"| {r['seed']} | {r['cut']} / {r['partial']} / {r['used']} | {r['sigma_px']:.3f} | "
            f"{r['kappa_err']:+.1e} | {r['nu_err']:+.1e} | {np.degrees(r['rot']):.4f} / "
            f"{np.degrees(r['bound_rot']):.4f} | {1e3 * r['trans']:.3f} / "
            f"{1e3 * r['bound_trans']:.3f} | {r['corner_cut']:.3f} / {r['corner_whole']:.3f} | "
            f"{cv_rms(r['cv']['cellcal']):.3f} / {cv_rms(r['cv'][OPENCV]):.3f} |")
    met = lambda ok: "met" if ok else "**not met**"  # noqa: E731
    rows += ["", "| acceptance (issue 9) | measured | target | |", "|---|---|---|---|",
             f"| stations cutting the board | {100 * s['cut_share']:.0f} % | >= 30 % | "
             f"{met(s['cut_share'] >= 0.3)} |",
             f"| largest κ error over seeds | {s['kappa_max']:.1e} | <= {TOL_KAPPA:g} | "
             f"{met(s['kappa_max'] <= TOL_KAPPA)} |",
             f"| largest ν error over seeds | {s['nu_max']:.1e} | <= {TOL_NU:g} | "
             f"{met(s['nu_max'] <= TOL_NU)} |",
             f"| hand-eye rotation RMS / Cramér-Rao | {s['rot_ratio']:.2f} | <= 1.2 | "
             f"{met(s['rot_ratio'] <= 1.2)} |",
             f"| hand-eye translation RMS / Cramér-Rao | {s['trans_ratio']:.2f} | <= 1.2 | "
             f"{met(s['trans_ratio'] <= 1.2)} |",
             f"| image-corner error: whole-board set / cut set | {s['corner_ratio']:.2f} "
             f"({s['corner_whole']:.3f} / {s['corner_cut']:.3f} px) | >= 1.5 | "
             f"{met(s['corner_ratio'] >= 1.5)} |",
             f"| CV px cellcal / OpenCV ChArUco pipeline | {s['cv_ratio']:.2f} "
             f"({s['cv_cellcal']:.3f} / {s['cv_opencv']:.3f} px) | <= 1 | "
             f"{met(s['cv_ratio'] <= 1.0)} |"]
    return "\n".join(rows)


def scenes_plot(runs: Sequence[dict], path: Path) -> None:
    fig, ax = plt.subplots(1, 4, figsize=(16, 3.8), layout="constrained")
    seeds = [r["seed"] for r in runs]
    ax[0].plot(seeds, [1e3 * r["kappa_err"] for r in runs], "o", label="κ error x 1e3")
    ax[0].plot(seeds, [1e4 * r["nu_err"] for r in runs], "s", label="ν error x 1e4")
    for y in (-1, 1):
        ax[0].axhline(y, color="r", ls="--", lw=0.8)
    ax[0].set(xlabel="seed", title="κ, ν error (targets: ±1e-3, ±2e-4 = dashed)")
    for key, marker in (("rot", "o"), ("trans", "s")):
        ax[1].plot(seeds, [r[key] / r["bound_" + key] for r in runs], marker,
                   label=f"X {key}: error / bound")
    ax[1].axhline(1.2, color="r", ls="--", lw=0.8, label="1.2")
    ax[1].set(xlabel="seed", title="hand-eye error / Cramér-Rao bound")
    ax[2].bar(np.arange(len(runs)) - 0.2, [r["corner_cut"] for r in runs], 0.4,
              label="40 % cut views")
    ax[2].bar(np.arange(len(runs)) + 0.2, [r["corner_whole"] for r in runs], 0.4,
              label="whole-board views")
    ax[2].set(xticks=np.arange(len(runs)), xticklabels=seeds, xlabel="seed",
              ylabel="px", title="projection error at the image corners")
    ax[3].bar(np.arange(len(runs)) - 0.2, [cv_rms(r["cv"]["cellcal"]) for r in runs], 0.4,
              label="cellcal")
    ax[3].bar(np.arange(len(runs)) + 0.2, [cv_rms(r["cv"][OPENCV]) for r in runs], 0.4,
              label="OpenCV ChArUco + calibrateCamera + Park")
    ax[3].set(xticks=np.arange(len(runs)), xticklabels=seeds, xlabel="seed", ylabel="px",
              title="5-fold CV error of held-out stations")
    for a in ax:
        a.legend(fontsize=7)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 seeds, 6 speed images")
    parser.add_argument("--images", type=int, default=None, help="speed images (12)")
    parser.add_argument("--seeds", type=int, default=None, help="rendered scenes (6)")
    part = parser.add_mutually_exclusive_group()
    part.add_argument("--speed-only", action="store_true")
    part.add_argument("--scenes-only", action="store_true")
    args = parser.parse_args(argv)
    OUT.mkdir(exist_ok=True)
    if not args.scenes_only:
        r = speed(views(args.images or (6 if args.quick else 12)))
        text = table(r)
        print(text)
        (OUT / "charuco.md").write_text(text + "\n")
        plot(r, OUT / "charuco.png")
    if not args.speed_only:
        runs = []
        for seed in range(args.seeds or (2 if args.quick else 6)):
            runs.append(scene_run(seed))
            print(f"seed {seed}: κ error {runs[-1]['kappa_err']:+.1e}, ν error "
                  f"{runs[-1]['nu_err']:+.1e}", flush=True)
        text = scenes_table(runs)
        print(text)
        (OUT / "charuco_scenes.md").write_text(text + "\n")
        scenes_plot(runs, OUT / "charuco_scenes.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
