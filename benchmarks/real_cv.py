"""Real data: how well does a calibration predict what it has not seen? cellcal vs OpenCV.

Sets (``../shared/data``, read in place): ``rwhe-kuka_1`` (a KUKA industrial arm, 30
eye-in-hand stations, 1928x1208, a precise 28x17 board of 20 mm squares), the two real UR
eye-in-hand sets ``ur-kinect-*`` (21 stations each, 11x8 board printed about 10 % larger than
its nominal 30 mm squares) and OpenCV's ``opencv-left`` images (13 views of a 9x6 board, no
robot: intrinsics only). ``--cache DIR`` keeps the detections (a minute for the KUKA images).

Hand-eye sets, k-fold cross-validation over stations (k = 5, the same folds for every method):
each method is fitted on the other folds and predicts each held-out station's board corners
from its robot pose alone, ``cam_T_target = inv(X) inv(P_k) Y``, with the fold's camera model
(and for cellcal its κ and ν). The error of a station is the RMS pixel distance to the
detected corners (cellcal's detections, the common reference); the figure of a method is the
RMS over stations of those per-station errors.

- ``cellcal`` — the default pipeline (``calibrate``, joint ML with κ, ν);
- ``opencv-<m>`` — OpenCV's pipeline: ``findChessboardCornersSB`` (NORMALIZE | EXHAUSTIVE |
  ACCURACY, or the default flags where those find nothing, as on most KUKA images; its
  corners put in cellcal's corner order so the origin is consistent — a favour to the peer),
  ``calibrateCamera`` on the nominal board, ``calibrateHandEye`` with Park, Tsai or
  Daniilidis, and Y = base_T_target averaged over the training stations (rotation mean by
  ``scipy Rotation.mean``, translation mean).

Uncertainty: cellcal's reported 1σ of the hand-eye (full set) against the delete-a-group
jackknife spread of the k fold estimates, ``sqrt((k-1)/k Σ (θ_i - θ̄)²)`` per axis.

Intrinsics only (``opencv-left``): k-fold over images; the fold's camera model (cellcal's
``calibrate`` without robot poses, or ``calibrateCamera``) and a held-out image's pose
from ``solvePnP`` on half of its corners (the (i + j) even checkerboard half) predict the other
half; the figure is the RMS over images of those errors.

Board check (hand-eye sets): the default run's verdict and ``board_scale`` finding, then the
run a user makes after measuring the board — the measured square size (to the mm) entered,
``kappa 'fixed'`` — and its hand-eye against the default's.

    python -m benchmarks.real_cv            # about 2 min on 2 idle cores
    python -m benchmarks.real_cv --quick    # one UR set and opencv-left

Prints a table and writes ``benchmarks/results/real_cv.png`` and ``real_cv.md``.
"""

from __future__ import annotations

import argparse
import json
import pickle
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import matplotlib
import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.stationset import station_set
from calib.boards import Board, Checkerboard, Detection, detect_checkerboard
from calib.calibration import calibrate
from calib.chain import camera_from_robot
from calib.geometry import check_ur_poses, make_transform
from calib.options import SolverOptions
from calib.peers import solve_opencv
from calib.pipeline import CalibrationResult

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import results_dir

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
OUT = results_dir()
#: The robot station sets: the KUKA cell with a precise board, the UR cell with a rough print.
ROBOT_SETS = ("rwhe-kuka_1", "ur-kinect-highR_highT", "ur-kinect-lowR_highT")
PEERS = ("park", "tsai", "daniilidis")
K_FOLDS = 5
SB_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY


@dataclass(frozen=True)
class StationData:
    """One set's usable stations: both detectors read the board in each.

    ``ids`` / ``ids_cv``: the board point ids of each station's ``corners`` / ``corners_cv``
    (partial views, e.g. ChArUco); None when every station shows the whole board in point id
    order.
    """

    name: str
    target: Board
    image_size: tuple[int, int]
    corners: list[np.ndarray]  # cellcal's detections, (N, 2) each
    corners_cv: list[np.ndarray]  # OpenCV's, in cellcal's corner order
    T_base_tcp: np.ndarray | None  # (n, 4, 4), None for intrinsics-only sets
    ids: list[np.ndarray] | None = None
    ids_cv: list[np.ndarray] | None = None

    def observations(self, stations: np.ndarray) -> list[np.ndarray | Detection]:
        """cellcal's input for ``stations``: whole-board corners, or corners with ids."""
        if self.ids is None:
            return [self.corners[i] for i in stations]
        return [Detection(ok=True, corners=self.corners[i], ids=self.ids[i]) for i in stations]

    def seen(self, grid: np.ndarray, k: int, *, opencv: bool = False) -> np.ndarray:
        """The rows of ``grid`` (all board points, (N, ...)) that station ``k`` shows in
        cellcal's (or OpenCV's) detection."""
        ids = self.ids_cv if opencv else self.ids
        return grid if ids is None else grid[ids[k]]


@dataclass(frozen=True)
class Fit:
    """What a method needs to predict a held-out station."""

    K: np.ndarray
    dist: np.ndarray
    grid: np.ndarray  # board corners at the method's scale, (N, 3)
    X: np.ndarray | None = None
    Y: np.ndarray | None = None
    robot_map: np.ndarray | None = None  # cellcal's map of the robot's translations, (3, 3)


def folds(n: int, k: int = K_FOLDS) -> list[np.ndarray]:
    """Held-out station indices of each fold: station i in fold i mod k (interleaved, so
    every fold spans the capture order)."""
    return [np.arange(f, n, k) for f in range(min(k, n))]


# ---- data --------------------------------------------------------------------------------------

def _in_our_order(cv_corners: np.ndarray, ours: np.ndarray, board: tuple[int, int]) -> np.ndarray:
    """OpenCV's grid (N, 2) re-indexed to cellcal's order (the closest of the grid flips)."""
    cols, rows = board
    g = cv_corners.reshape(rows, cols, 2)
    candidates = [g, g[::-1, ::-1], g[::-1], g[:, ::-1]]
    errs = [np.abs(c.reshape(-1, 2) - ours).max() for c in candidates]
    return candidates[int(np.argmin(errs))].reshape(-1, 2)


def _opencv_corners(grey: np.ndarray, board: tuple[int, int]) -> tuple[bool, np.ndarray]:
    """``findChessboardCornersSB`` with the first flag set that reads the board: the accurate
    ``SB_FLAGS``, then the default flags (on large industrial images the exhaustive search
    finds 4 of 30 boards that the default call reads)."""
    for flags in (SB_FLAGS, 0):
        found, raw = cv2.findChessboardCornersSB(grey, board, flags=flags)
        if found:
            return True, raw
    return False, None


def _detect_both(images: Sequence[np.ndarray], board: tuple[int, int]
                 ) -> tuple[list[int], list[np.ndarray], list[np.ndarray]]:
    keep, ours, theirs = [], [], []
    for k, grey in enumerate(images):
        det = detect_checkerboard(grey, board)
        found, cv_raw = _opencv_corners(grey, board)
        if det.ok and found:
            keep.append(k)
            ours.append(det.corners)
            theirs.append(_in_our_order(cv_raw.reshape(-1, 2).astype(float), det.corners,
                                        board))
    return keep, ours, theirs


def load_station_set(name: str, cache: Path | None = None) -> StationData:
    """A station set of ``DATA`` with both detectors' corners; kept in ``cache`` (a directory)
    when given, since detecting the KUKA images takes a minute."""
    path = None if cache is None else cache / f"{name}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    data = _load_station_set(name)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(data))
    return data


def _load_station_set(name: str) -> StationData:
    doc = json.loads((DATA / name / "stations.json").read_text())
    board = tuple(doc["target"]["inner_corners"])
    images = [cv2.imread(str(DATA / name / s["image"]), cv2.IMREAD_GRAYSCALE)
              for s in doc["stations"]]
    keep, ours, theirs = _detect_both(images, board)
    P = check_ur_poses([doc["stations"][k]["tcp_pose"] for k in keep], "tcp_pose")
    h, w = images[0].shape
    return StationData(name, Checkerboard(board, doc["target"]["square_size_m"]), (w, h), ours,
                       theirs, P)


def load_opencv_left() -> StationData:
    files = sorted((DATA / "opencv-left").glob("left*.jpg"))
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    _, ours, theirs = _detect_both(images, (9, 6))
    h, w = images[0].shape
    # The square size is unknown and irrelevant to intrinsics; 1 unit.
    return StationData("opencv-left", Checkerboard((9, 6), 1.0), (w, h), ours, theirs, None)


# ---- fits ----------------------------------------------------------------------------------------

def fit_cellcal(data: StationData, train: np.ndarray):
    """cellcal's default on the training stations: (Fit, the CalibrationResult)."""
    poses = None if data.T_base_tcp is None else [
        np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])
        for T in data.T_base_tcp[train]]
    res = calibrate(station_set(data.observations(train), poses, data.target,
                                image_size=data.image_size))
    grid = data.target.points(kappa=res.kappa, nu=res.nu)
    return Fit(res.K, res.dist, grid, res.hand_eye, res.target_pose, res.robot_map), res


def _opencv_camera(data: StationData, train: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    grid = data.target.points().astype(np.float32)
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [data.seen(grid, i, opencv=True) for i in train],
        [data.corners_cv[i].astype(np.float32) for i in train], data.image_size, None, None)
    C = np.stack([make_transform(cv2.Rodrigues(r)[0], t.ravel())
                  for r, t in zip(rvecs, tvecs, strict=True)])
    return K, dist.ravel()[:5], grid.astype(float), C


def fit_opencv(data: StationData, train: np.ndarray, method: str) -> Fit:
    """OpenCV's pipeline on the training stations; Y averaged over them."""
    K, dist, grid, C = _opencv_camera(data, train)
    if data.T_base_tcp is None:
        return Fit(K, dist, grid)
    P = data.T_base_tcp[train]
    X, _ = solve_opencv(P, C, method)
    Y_each = P @ X @ C
    Y = make_transform(Rotation.from_matrix(Y_each[:, :3, :3]).mean().as_matrix(),
                       Y_each[:, :3, 3].mean(axis=0))
    return Fit(K, dist, grid, X, Y)


# ---- prediction errors -----------------------------------------------------------------------

def _project(fit: Fit, T_cam_target: np.ndarray, points: np.ndarray) -> np.ndarray:
    rvec = Rotation.from_matrix(T_cam_target[:3, :3]).as_rotvec()
    return cv2.projectPoints(points, rvec, T_cam_target[:3, 3], fit.K, fit.dist)[0].reshape(-1, 2)


def chain_errors(data: StationData, fit: Fit, held: np.ndarray) -> np.ndarray:
    """Per held-out station RMS px of the corners predicted from the robot pose alone."""
    out = []
    for i in held:
        C = camera_from_robot(data.T_base_tcp[i], fit.X, fit.Y, "eye_in_hand", fit.robot_map)
        uv = _project(fit, C, data.seen(fit.grid, i))
        out.append(np.sqrt(np.mean(np.sum((uv - data.corners[i]) ** 2, axis=1))))
    return np.array(out)


def half_board_errors(data: StationData, fit: Fit, held: np.ndarray) -> np.ndarray:
    """Per held-out image RMS px on the odd checkerboard half, pose by PnP on the even half."""
    cols, rows = data.target.inner_corners
    j, i = np.mgrid[0:rows, 0:cols]
    even = ((i + j) % 2 == 0).ravel()
    out = []
    for k in held:
        m = data.corners[k]
        _, rvec, tvec = cv2.solvePnP(fit.grid[even], m[even], fit.K, fit.dist)
        T = make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
        uv = _project(fit, T, fit.grid[~even])
        out.append(np.sqrt(np.mean(np.sum((uv - m[~even]) ** 2, axis=1))))
    return np.array(out)


def _delta(X: np.ndarray, X_ref: np.ndarray) -> np.ndarray:
    """Small rotation (left, rad) and translation (m) from X_ref to X, shape (6,)."""
    rot = Rotation.from_matrix(X[:3, :3] @ X_ref[:3, :3].T).as_rotvec()
    return np.concatenate([rot, X[:3, 3] - X_ref[:3, 3]])


def jackknife_sd(estimates: Sequence[np.ndarray], reference: np.ndarray) -> np.ndarray:
    """Delete-a-group jackknife standard deviation per axis (rot rad x3, trans m x3)."""
    d = np.array([_delta(X, reference) for X in estimates])
    g = len(d)
    return np.sqrt((g - 1) / g * np.sum((d - d.mean(axis=0)) ** 2, axis=0))


# ---- per set -----------------------------------------------------------------------------------

def cross_validate(data: StationData, methods: Sequence[str]
                   ) -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """k-fold CV error of each held-out station per method (``cellcal``, ``opencv-<m>``),
    and cellcal's hand-eye of each fold."""
    n = len(data.corners)
    errors: dict[str, np.ndarray] = {m: np.full(n, np.nan) for m in methods}
    predict = half_board_errors if data.T_base_tcp is None else chain_errors
    estimates = []
    for held in folds(n):
        train = np.setdiff1d(np.arange(n), held)
        for m in methods:
            if m == "cellcal":
                fit, _ = fit_cellcal(data, train)
                estimates.append(fit.X)
            else:
                fit = fit_opencv(data, train, m.removeprefix("opencv-"))
            errors[m][held] = predict(data, fit, held)
    return errors, estimates


def cv_rms(errors: np.ndarray) -> float:
    """A method's CV figure: the RMS over stations of the per-station RMS errors (px)."""
    return float(np.sqrt(np.mean(np.square(errors))))


def run_set(data: StationData, methods: Sequence[str]) -> dict:
    """CV errors per method (per-station arrays) and, for hand-eye sets, σ vs jackknife."""
    n = len(data.corners)
    errors, estimates = cross_validate(data, methods)
    out = {"n": n, "errors": errors, "cv_px": {m: cv_rms(e) for m, e in errors.items()}}
    if data.T_base_tcp is not None:
        full_fit, full = fit_cellcal(data, np.arange(n))
        reported = np.concatenate([full.sigmas["hand_eye_rot_rad"],
                                   full.sigmas["hand_eye_trans_m"]])
        jack = jackknife_sd(estimates, full_fit.X)
        out.update(kappa=full.kappa, reported=reported, jackknife=jack,
                   ratio_rot=float(np.linalg.norm(reported[:3]) / np.linalg.norm(jack[:3])),
                   ratio_trans=float(np.linalg.norm(reported[3:]) / np.linalg.norm(jack[3:])),
                   **measured_board_check(data, full))
    return out


def measured_board_check(data: StationData, auto: CalibrationResult) -> dict:
    """The verdict of the default run, and the run a user makes after measuring the board:
    the measured square size entered, ``kappa 'fixed'``; its hand-eye against the default's."""
    found = {f.code: f for f in auto.trust.quality.findings}
    measured = found["board_scale"].values["measured_square_size_m"] if "board_scale" in \
        found else None
    out = {"verdict": auto.trust.quality.verdict, "findings": sorted(found),
           "measured_square_m": measured}
    if measured is None:
        return out
    entered = round(measured, 3)  # what a calliper gives
    poses = [np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])
             for T in data.T_base_tcp]
    fixed = calibrate(station_set(data.observations(np.arange(len(poses))), poses,
                                  replace(data.target, square_size=entered),
                                  image_size=data.image_size), SolverOptions(kappa="fixed"))
    d = _delta(fixed.hand_eye, auto.hand_eye)
    out.update(entered_square_m=entered, fixed_kappa=fixed.kappa,
               fixed_vs_auto_rot_rad=float(np.linalg.norm(d[:3])),
               fixed_vs_auto_trans_m=float(np.linalg.norm(d[3:])))
    return out


# ---- output ------------------------------------------------------------------------------------

def table(results: dict[str, dict]) -> str:
    lines = ["| set | stations | method | CV px | / best OpenCV |", "|---|---|---|---|---|"]
    for name, r in results.items():
        best = min(v for m, v in r["cv_px"].items() if m != "cellcal")
        for m, v in r["cv_px"].items():
            lines.append(f"| {name} | {r['n']} | {m} | {v:.3f} | {v / best:.2f} |")
    lines += ["", "| set | κ | reported σ rot (deg) | jackknife rot (deg) | ratio | "
              "reported σ trans (mm) | jackknife trans (mm) | ratio |",
              "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        if "reported" not in r:
            continue
        rep, jk = r["reported"], r["jackknife"]
        lines.append(
            f"| {name} | {r['kappa']:.4f} | {np.rad2deg(np.linalg.norm(rep[:3])):.3f} | "
            f"{np.rad2deg(np.linalg.norm(jk[:3])):.3f} | {r['ratio_rot']:.2f} | "
            f"{1e3 * np.linalg.norm(rep[3:]):.2f} | {1e3 * np.linalg.norm(jk[3:]):.2f} | "
            f"{r['ratio_trans']:.2f} |")
    lines += ["", "| set | verdict | findings | board_scale: measured square (mm) | entered, "
              "--kappa fixed: κ | hand-eye fixed vs auto (deg, mm) |", "|---|---|---|---|---|---|"]
    for name, r in results.items():
        if "verdict" not in r:
            continue
        fixed = ("–" if r["measured_square_m"] is None else
                 f"{1e3 * r['entered_square_m']:g} mm: {r['fixed_kappa']:.4f}")
        delta = ("–" if r["measured_square_m"] is None else
                 f"{np.rad2deg(r['fixed_vs_auto_rot_rad']):.3f}, "
                 f"{1e3 * r['fixed_vs_auto_trans_m']:.2f}")
        measured = ("–" if r["measured_square_m"] is None
                    else f"{1e3 * r['measured_square_m']:.2f}")
        lines.append(f"| {name} | {r['verdict']} | {', '.join(r['findings'])} | {measured} | "
                     f"{fixed} | {delta} |")
    return "\n".join(lines)


def plot(results: dict[str, dict], path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), width_ratios=(2, 1),
                             layout="constrained")
    names = list(results)
    colours = {}
    for k, name in enumerate(names):
        methods = list(results[name]["cv_px"])
        width = 0.8 / len(methods)
        for j, m in enumerate(methods):
            first = m not in colours
            colours.setdefault(m, f"C{len(colours)}")
            axes[0].bar(k + (j - (len(methods) - 1) / 2) * width, results[name]["cv_px"][m],
                        width, color=colours[m], label=m if first else None)
    axes[0].set_xticks(np.arange(len(names)), names)
    axes[0].set_ylabel("k-fold CV RMS error (px)")
    axes[0].set_yscale("log")
    axes[0].set_title("held-out stations predicted from robot poses (opencv-left: half-board)")
    axes[0].legend(fontsize=8)
    he = [s for s in names if "reported" in results[s]]
    for k, (label, key) in enumerate((("rotation", "ratio_rot"), ("translation", "ratio_trans"))):
        axes[1].bar(np.arange(len(he)) + (k - 0.5) * 0.4, [results[s][key] for s in he], 0.4,
                    label=label)
    axes[1].axhline(1.0, color="k", lw=0.8)
    axes[1].axhline(0.7, color="r", lw=0.8, ls="--", label="target 0.7")
    axes[1].set_xticks(np.arange(len(he)), [s.removeprefix("ur-kinect-") for s in he])
    axes[1].set_title("cellcal reported σ / jackknife spread")
    axes[1].legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=[*ROBOT_SETS, "opencv-left"])
    parser.add_argument("--quick", action="store_true",
                        help="one UR set and opencv-left (a smoke run)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="keep the detections here (a directory), e.g. /tmp/real_cv")
    args = parser.parse_args(argv)
    methods = ["cellcal", *(f"opencv-{m}" for m in PEERS)]
    results = {}
    for name in [ROBOT_SETS[1], "opencv-left"] if args.quick else args.sets:
        data = (load_opencv_left() if name == "opencv-left"
                else load_station_set(name, args.cache))
        results[name] = run_set(data, methods if data.T_base_tcp is not None
                                else ["cellcal", "opencv-calibrateCamera"])
        print(f"{name}: " + ", ".join(f"{m} {v:.3f} px"
                                      for m, v in results[name]["cv_px"].items()), flush=True)
    text = table(results)
    print(text)
    OUT.mkdir(exist_ok=True)
    (OUT / "real_cv.md").write_text(text + "\n")
    plot(results, OUT / "real_cv.png")
    print(f"wrote {OUT / 'real_cv.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
