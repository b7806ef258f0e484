"""Unknown board dimensions (kappa, nu): what they cost the traditional pipeline, what we recover.

(a) Trends of Strobl & Hirzinger Fig. 2-4 on synthetic corners (truth nu = kappa = 1, 15 views,
    0.15 px corner noise, robot 0.05 deg / 0.25 mm): intrinsic errors, absolute-extrinsic errors
    and projection errors of the traditional calibration against the assumed nu and kappa.
(b) Our default (joint ML over corners and robot poses, with nu and kappa) against OpenCV's
    pipeline (``calibrateCamera`` on the nominal board + the best ``calibrateHandEye`` method) on
    rendered scenes (kappa = 1.005, nu = 0.9975), RMS over many seeds, with the Cramer-Rao lower
    bound of the same measurement model (``calib.bounds.cramer_rao_bound``) and our reported
    sigmas against the Monte-Carlo spread.
Speed, timed as whole processes, is ``benchmarks/end_to_end.py``.

    python -m benchmarks.kappa_nu            # full run (about 10 min on 2 cores)
    python -m benchmarks.kappa_nu --quick    # smoke run

Prints tables and writes benchmarks/results/kappa_nu.png.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import cv2
import matplotlib
import numpy as np
from tqdm import tqdm

from benchmarks.stationset import station_set
from calib import (
    OPENCV_HAND_EYE_METHODS,
    Board,
    CellParameters,
    Checkerboard,
    Detection,
    JointOptions,
    RobotNoise,
    board_points,
    calibrate,
    calibrate_hand_eye,
    camera_from_robot,
    cramer_rao_bound,
    detect_checkerboard,
    make_transform,
    perturb,
    pose_error,
    ur_pose_from_matrix,
)
from mocks.render import RenderParams, render_board
from mocks.scene import (
    MockScene,
    StationSpread,
    camera_pose_for_tcp,
    default_scene,
    sample_station_poses,
)

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import results_dir

OUT = results_dir()
ROBOT_ROT, ROBOT_TRANS = np.deg2rad(0.05), 0.25e-3
CV_METHODS = list(OPENCV_HAND_EYE_METHODS)


def bench_scene(scene: MockScene | None = None, *, kappa: float = 1.005,
                nu: float = 0.9975) -> MockScene:
    """``scene`` (default: the default scene) with UR-class robot noise and the given true
    board scale."""
    s = default_scene() if scene is None else scene
    return s.model_copy(update={
        "target": s.target.model_copy(update={"kappa": kappa, "nu": nu}),
        "noise": s.noise.model_copy(update={"robot_rot_deg": 0.05, "robot_trans_mm": 0.25})})


def _cv_poses(rvecs, tvecs) -> np.ndarray:
    return np.stack([make_transform(cv2.Rodrigues(r)[0], t.ravel())
                     for r, t in zip(rvecs, tvecs, strict=True)])


# ---- (a) trends of the paper's Fig. 2-4 --------------------------------------------------------

def trends(seeds: int) -> dict[str, np.ndarray]:
    """Traditional calibration with an assumed nu (kappa) while the truth is 1: errors."""
    scene = bench_scene(kappa=1.0, nu=1.0)
    cam = scene.camera
    K, dist, size = cam.k_matrix, cam.dist_coeffs, tuple(cam.image_size)
    grid_true = board_points(scene.target.inner_corners, scene.target.square_size_m)
    assumed = np.linspace(0.99, 1.01, 9)
    out = {k: np.zeros((seeds, len(assumed))) for k in
           ("fx_pct", "cx_pct", "ext_t_mm", "ext_r_deg", "proj_px", "he_t_mm", "chain_px")}
    for seed in tqdm(range(seeds), desc="trends", leave=False):
        rng = np.random.default_rng(100 + seed)
        P_true = sample_station_poses(scene, 15, rng)
        C_true = camera_pose_for_tcp(scene, P_true)
        uv = [cv2.projectPoints(grid_true, cv2.Rodrigues(C[:3, :3])[0], C[:3, 3], K, dist)[0]
              .reshape(-1, 2) + rng.normal(0, 0.15, (len(grid_true), 2)) for C in C_true]
        P = perturb(P_true, ROBOT_ROT, ROBOT_TRANS, rng)
        for a, value in enumerate(assumed):
            # nu sweep: the board assumed nu-scaled in x (kappa = 1)
            grid = board_points(scene.target.inner_corners, scene.target.square_size_m,
                                nu=value).astype(np.float32)
            _, K_est, d_est, rv, tv = cv2.calibrateCamera(
                [grid] * len(uv), [u.astype(np.float32) for u in uv], size, None, None)
            C_est = _cv_poses(rv, tv)
            out["fx_pct"][seed, a] = 100 * (K_est[0, 0] / K[0, 0] - 1)
            out["cx_pct"][seed, a] = 100 * (K_est[0, 2] / K[0, 2] - 1)
            er, et = pose_error(C_est, C_true)
            out["ext_t_mm"][seed, a] = 1e3 * np.sqrt(np.mean(et ** 2))
            out["ext_r_deg"][seed, a] = np.degrees(np.sqrt(np.mean(er ** 2)))
            # projection of the real board with the estimated camera and true extrinsics
            proj = [cv2.projectPoints(grid_true, cv2.Rodrigues(C[:3, :3])[0], C[:3, 3], K_est,
                                      d_est)[0].reshape(-1, 2) for C in C_true]
            out["proj_px"][seed, a] = np.sqrt(np.mean(np.concatenate(
                [np.sum((p - u) ** 2, axis=1) for p, u in zip(proj, uv, strict=True)])))
            # kappa sweep: correct nu, board assumed kappa-scaled
            _, K1, d1, rv, tv = cv2.calibrateCamera(
                [(grid_true * value).astype(np.float32)] * len(uv),
                [u.astype(np.float32) for u in uv], size, None, None)
            he = calibrate_hand_eye(P, _cv_poses(rv, tv), method="park").hand_eye
            out["he_t_mm"][seed, a] = 1e3 * pose_error(he, scene.hand_eye_matrix)[1]
            chain = camera_from_robot(P, he, scene.target_pose_matrix, scene.setup)
            proj = [cv2.projectPoints(grid_true, cv2.Rodrigues(C[:3, :3])[0], C[:3, 3], K1,
                                      d1)[0].reshape(-1, 2) for C in chain]
            out["chain_px"][seed, a] = np.sqrt(np.mean(np.concatenate(
                [np.sum((p - u) ** 2, axis=1) for p, u in zip(proj, uv, strict=True)])))
    out["assumed"] = assumed
    return out


# ---- (b) ours vs OpenCV with the Cramer-Rao bound ----------------------------------------------

def rendered_station_set(scene: MockScene, n: int, rng: np.random.Generator,
                         spread: StationSpread | None = None):
    """Rendered images, noisy robot readings (n, 4, 4) and the true robot poses; stations
    spread by ``spread`` (default: whole-board views)."""
    P_true = sample_station_poses(scene, n, rng, spread or StationSpread())
    params = RenderParams.from_scene(scene)
    images = [render_board(params, C, rng=rng) for C in camera_pose_for_tcp(scene, P_true)]
    P = perturb(P_true, ROBOT_ROT, ROBOT_TRANS, rng)
    return images, P, P_true


def corner_noise(scene: MockScene, detections: Sequence[Detection],
                 T_cam_target: np.ndarray) -> float:
    """RMS (px, per coordinate) of the usable detections' corners against the true
    projections of their points from the true camera poses (n, 4, 4): the σ_px of the
    Cramér-Rao bound."""
    cam = scene.camera
    truth = scene.true_board_points()
    err = np.concatenate([
        d.corners - cv2.projectPoints(truth[d.ids], cv2.Rodrigues(C[:3, :3])[0], C[:3, 3],
                                      cam.k_matrix, cam.dist_coeffs)[0].reshape(-1, 2)
        for d, C in zip(detections, T_cam_target, strict=True) if d.ok])
    return float(np.sqrt(np.mean(err ** 2)))


def scene_bound(scene: MockScene, board: Board, T_base_tcp: np.ndarray, sigma_px: float,
                point_ids: Sequence[np.ndarray] | None = None) -> dict[str, float]:
    """Cramér-Rao bound (``calib.bounds.cramer_rao_bound``) of the scene's truth seen from the
    true robot poses (n, 4, 4) with σ_px corner noise and the benchmark's robot noise: the
    hand-eye rotation (rad) and translation (m) as root traces, κ and ν."""
    t, cam = scene.target, scene.camera
    bound = cramer_rao_bound(
        T_base_tcp, board, CellParameters(cam.k_matrix, cam.dist_coeffs, t.nu, t.kappa,
                                          scene.hand_eye_matrix, scene.target_pose_matrix),
        JointOptions(sigma_px=sigma_px, noise=RobotNoise(ROBOT_ROT, ROBOT_TRANS)), point_ids)
    return {"rot": float(np.sqrt(np.trace(bound["hand_eye_rot"]))),
            "trans": float(np.sqrt(np.trace(bound["hand_eye_trans"]))),
            "kappa": bound["kappa"], "nu": bound["nu"]}


def comparison(seeds: int, stations: int = 15) -> dict[str, np.ndarray]:
    scene = bench_scene()
    t = scene.target
    cam = scene.camera
    board = Checkerboard(tuple(t.inner_corners), t.square_size_m)
    grid_nominal = board.points().astype(np.float32)
    X_true = scene.hand_eye_matrix
    rows = []
    for seed in tqdm(range(seeds), desc="rendered scenes", leave=False):
        rng = np.random.default_rng(seed)
        images, P, P_true = rendered_station_set(scene, stations, rng)
        dets = [detect_checkerboard(im, t.inner_corners) for im in images]
        ok = [d for d in dets if d.ok]
        sigma_px = corner_noise(scene, dets, camera_pose_for_tcp(scene, P_true))
        ours = calibrate(station_set(dets, ur_pose_from_matrix(P), board,
                                     image_size=cam.image_size))
        _, _, _, rv, tv = cv2.calibrateCamera(
            [grid_nominal] * len(ok), [d.corners.astype(np.float32) for d in ok],
            tuple(cam.image_size), None, None)
        P_ok = P[[d.ok for d in dets]]
        cv_err = [pose_error(calibrate_hand_eye(P_ok, _cv_poses(rv, tv), method=m).hand_eye,
                             X_true) for m in CV_METHODS]
        bound = scene_bound(scene, board, P_true, sigma_px)
        er, et = pose_error(ours.hand_eye, X_true)
        s = ours.sigmas
        rows.append([
            er, et, ours.kappa - t.kappa, ours.nu - t.nu,
            np.linalg.norm(s["hand_eye_rot_rad"]), np.linalg.norm(s["hand_eye_trans_m"]),
            s["kappa"], s["nu"],
            bound["rot"], bound["trans"], bound["kappa"], bound["nu"], sigma_px,
            *[e[0] for e in cv_err], *[e[1] for e in cv_err]])
    return np.array(rows)


def report_comparison(rows: np.ndarray) -> dict[str, float]:
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    n_cv = len(CV_METHODS)
    cv_rot = {m: rms(rows[:, 13 + i]) for i, m in enumerate(CV_METHODS)}
    cv_trans = {m: rms(rows[:, 13 + n_cv + i]) for i, m in enumerate(CV_METHODS)}
    best = min(CV_METHODS, key=lambda m: cv_trans[m])
    r = {
        "ours_rot_deg": np.degrees(rms(rows[:, 0])), "ours_trans_mm": 1e3 * rms(rows[:, 1]),
        "kappa_err": rms(rows[:, 2]), "nu_err": rms(rows[:, 3]),
        "sigma_rot_deg": np.degrees(rms(rows[:, 4])), "sigma_trans_mm": 1e3 * rms(rows[:, 5]),
        "sigma_kappa": rms(rows[:, 6]), "sigma_nu": rms(rows[:, 7]),
        "crlb_rot_deg": np.degrees(rms(rows[:, 8])), "crlb_trans_mm": 1e3 * rms(rows[:, 9]),
        "crlb_kappa": rms(rows[:, 10]), "crlb_nu": rms(rows[:, 11]),
        "sigma_px": float(np.mean(rows[:, 12])),
        "cv_best": best, "cv_rot_deg": np.degrees(cv_rot[best]),
        "cv_trans_mm": 1e3 * cv_trans[best]}
    print(f"corner noise of the detector on these renders: {r['sigma_px']:.3f} px RMS")
    print(f"{'':<28} {'X rot (deg)':>12} {'X trans (mm)':>13} {'kappa':>10} {'nu':>10}")
    print(f"{'ours (joint), RMS error':<28} {r['ours_rot_deg']:12.4f} {r['ours_trans_mm']:13.4f} "
          f"{r['kappa_err']:10.2e} {r['nu_err']:10.2e}")
    print(f"{'Cramer-Rao bound':<28} {r['crlb_rot_deg']:12.4f} {r['crlb_trans_mm']:13.4f} "
          f"{r['crlb_kappa']:10.2e} {r['crlb_nu']:10.2e}")
    print(f"{'ours, reported sigma (RMS)':<28} {r['sigma_rot_deg']:12.4f} "
          f"{r['sigma_trans_mm']:13.4f} {r['sigma_kappa']:10.2e} {r['sigma_nu']:10.2e}")
    for m in CV_METHODS:
        print(f"{'OpenCV ' + m + ' (nominal)':<28} {np.degrees(cv_rot[m]):12.4f} "
              f"{1e3 * cv_trans[m]:13.4f}")
    print(f"ratios: X rot / bound {r['ours_rot_deg'] / r['crlb_rot_deg']:.2f}, X trans / bound "
          f"{r['ours_trans_mm'] / r['crlb_trans_mm']:.2f} (target <= 1.2); kappa err / bound "
          f"{r['kappa_err'] / r['crlb_kappa']:.2f}, nu err / bound {r['nu_err'] / r['crlb_nu']:.2f}"
          f" (target <= 1.5)")
    print(f"Monte-Carlo RMS / reported sigma: X rot {r['ours_rot_deg'] / r['sigma_rot_deg']:.2f}, "
          f"X trans {r['ours_trans_mm'] / r['sigma_trans_mm']:.2f} (target 0.8-1.25)")
    print(f"best OpenCV ({best}) / ours: rot {r['cv_rot_deg'] / r['ours_rot_deg']:.2f}x, "
          f"trans {r['cv_trans_mm'] / r['ours_trans_mm']:.2f}x")
    return r


def plot(tr: dict[str, np.ndarray], rows: np.ndarray | None) -> None:
    OUT.mkdir(exist_ok=True)
    fig, ax = plt.subplots(2, 3, figsize=(16, 9))
    a = tr["assumed"]
    m = {k: v.mean(axis=0) for k, v in tr.items() if k != "assumed"}
    ax[0, 0].plot(a, m["fx_pct"], "o-", label="fx")
    ax[0, 0].plot(a, m["cx_pct"], "s-", label="cx")
    ax[0, 0].set(xlabel="assumed nu (true 1)", ylabel="error (%)",
                 title="Fig. 2a: intrinsics vs assumed nu")
    ax[0, 1].plot(a, m["he_t_mm"], "o-")
    ax[0, 1].set(xlabel="assumed kappa (true 1)", ylabel="hand-eye translation error (mm)",
                 title="Fig. 2b: hand-eye vs assumed kappa")
    ax[0, 2].plot(a, m["ext_t_mm"], "o-", label="translation (mm)")
    ax2 = ax[0, 2].twinx()
    ax2.plot(a, m["ext_r_deg"], "s--", color="tab:orange", label="rotation (deg)")
    ax[0, 2].set(xlabel="assumed nu (true 1)", ylabel="absolute extrinsics error (mm)",
                 title="Fig. 3: extrinsics vs assumed nu")
    ax2.set_ylabel("rotation error (deg)")
    ax[1, 0].plot(a, m["proj_px"], "o-", label="true extrinsics, vs assumed nu")
    ax[1, 0].plot(a, m["chain_px"], "s-", label="robot readings + hand-eye, vs assumed kappa")
    ax[1, 0].set(xlabel="assumed nu or kappa (true 1)", ylabel="projection RMS (px)",
                 title="Fig. 4: projection errors")
    for x in (ax[0, 0], ax[1, 0]):
        x.legend(fontsize=8)
    if rows is not None:
        n_cv = len(CV_METHODS)
        best = int(np.argmin(np.sqrt(np.mean(rows[:, 13 + n_cv:] ** 2, axis=0))))
        for col, (idx, cv_idx, bound_idx, label) in enumerate(
                [(0, 13 + best, 8, "X rotation error (deg)"),
                 (1, 13 + n_cv + best, 9, "X translation error (mm)")]):
            scale = np.degrees(1.0) if col == 0 else 1e3
            x = ax[1, 1 + col]
            x.hist(rows[:, idx] * scale, bins=20, alpha=0.6, label="ours (joint)")
            x.hist(rows[:, cv_idx] * scale, bins=20, alpha=0.6,
                   label=f"OpenCV {CV_METHODS[best]} (nominal board)")
            x.axvline(np.sqrt(np.mean(rows[:, bound_idx] ** 2)) * scale, color="k", ls="--",
                      label="Cramer-Rao (RMS)")
            x.set(xlabel=label, ylabel="seeds", title="rendered scenes, kappa 1.005, nu 0.9975")
            x.legend(fontsize=8)
    for x in ax.ravel():
        x.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT / "kappa_nu.png", dpi=90)
    print(f"\nplot: {OUT / 'kappa_nu.png'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=60)
    args = ap.parse_args()
    seeds = 4 if args.quick else args.seeds
    print("# (a) traditional calibration with a wrongly assumed board (truth nu = kappa = 1)")
    tr = trends(3 if args.quick else 10)
    print(f"{'assumed':>8} {'fx %':>8} {'cx %':>8} {'ext t mm':>9} {'ext r deg':>10} "
          f"{'proj px':>8} {'HE t mm':>8} {'chain px':>9}")
    for k, a in enumerate(tr["assumed"]):
        print(f"{a:8.4f} " + " ".join(f"{tr[c][:, k].mean():8.3f}" for c in (
            "fx_pct", "cx_pct", "ext_t_mm", "ext_r_deg", "proj_px", "he_t_mm", "chain_px")))
    print(f"\n# (b) rendered scenes (kappa 1.005, nu 0.9975, 15 stations, robot 0.05 deg / "
          f"0.25 mm), {seeds} seeds")
    rows = comparison(seeds)
    report_comparison(rows)
    plot(tr, rows)


if __name__ == "__main__":
    main()
