"""Joint maximum-likelihood calibration over every corner and every robot pose (default result).

The staged estimates (intrinsics with ν, Method #1 eq. 5; hand-eye and κ from the poses, eq. 6)
each treat the previous stage as exact. The joint estimate instead minimises, over all unknowns
at once, the negative log-likelihood of everything that was measured (Strobl & Hirzinger,
footnote 5; their Method #1 residuals plus the robot readings as noisy measurements):

* every detected corner ``m``, with the camera pose of station i implied by the robot chain
  (``docs/conventions.md``) instead of being free per image::

      eye-in-hand:  C_i = inv(X) inv(P_i E_i) Y          (X = tcp_T_cam, Y = base_T_target)
      eye-to-hand:  C_i = inv(X) (P_i E_i) Y             (X = base_T_cam, Y = tcp_T_target)

  with ``P_i`` the reading base_T_tcp and ``E_i = exp(δ_i)`` the unknown reading error applied
  on the right, in the tcp frame (as ``calib.geometry.perturb`` draws UR noise), and the true
  corner (i, j) at (κν i s, κ j s, 0) (eq. 4): residual ``(m̂ - m) / σ_px``;
* every robot reading, through its correction: residual ``δ_i / (σ_rot, σ_trans) · √3``.
  The noise levels mean what they mean in Strobl & Hirzinger section IV-A and
  ``calib.geometry.perturb``: the σ of the rotation *angle* about a random axis and of the
  translation *length* along a random direction, so each of the three components of the
  rotation vector (translation) has standard deviation σ / √3.

Unknowns: ``fx, fy, cx, cy, k1, k2, p1, p2, k3, ν, κ``, X and Y (small left rotations and
translations about a reference), and 6 per station. ``scipy.optimize.least_squares`` runs with
an analytic sparse Jacobian (one 2 x (23 + 6) block per corner, one diagonal entry per prior).
The covariance of the 23 global parameters comes from the Jacobian at the optimum with the
station blocks eliminated by a Schur complement, scaled by the residual variance factor.

Stations whose correction is implausible are dropped one at a time, worst first, and the problem
solved again: the distance ``sqrt((angle/σ_rot)² + (length/σ_trans)²)`` of δ_i (Mahalanobis in
the noise model above, a chi variable with 2 degrees of freedom) beyond ``outlier_sigma``.

:func:`nu_from_extrinsics` implements Method #2: ν from the extrinsic residuals of eq. (6), by a
1-D search over ν around a start value with the intrinsic bundle adjustment at fixed ν.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import OptimizeResult, least_squares, minimize_scalar
from scipy.sparse import csr_matrix
from scipy.stats import chi2

from calib import so3
from calib.camera import project
from calib.chain import check_setup, robot_chain
from calib.geometry import check_transforms, invert
from calib.handeye import (
    DEFAULT_ROBOT_NOISE_ROT_RAD,
    DEFAULT_ROBOT_NOISE_TRANS_M,
    MIN_STATIONS,
    calibrate_hand_eye,
)
from calib.intrinsics import calibrate_intrinsics
from calib.refine import pose_residuals
from calib.target import board_points

#: Camera and board parameters, in the order of :attr:`JointResult.covariance`.
CAMERA_PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "nu", "kappa")
#: All global parameters: camera, then X and Y as (small left rotation, translation).
GLOBAL_PARAMS = (*CAMERA_PARAMS,
                 *(f"hand_eye_{a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")),
                 *(f"target_pose_{a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")))
#: Parameters that ``fix=`` may hold at their start values (known intrinsics: the first nine).
FIXABLE = (*CAMERA_PARAMS,)
#: Default outlier limit: Mahalanobis distance of a station's robot-pose correction.
OUTLIER_SIGMA = 5.0

_N_CAM = len(CAMERA_PARAMS)
_N_GLOBAL = len(GLOBAL_PARAMS)
_NU, _KAPPA = CAMERA_PARAMS.index("nu"), CAMERA_PARAMS.index("kappa")
#: Median of the chi distribution with 2 degrees of freedom (the correction's distance).
_DISTANCE_MEDIAN = float(np.sqrt(chi2.ppf(0.5, 2)))


@dataclass(frozen=True)
class JointResult:
    """Joint maximum-likelihood estimate with its uncertainty.

    Attributes
    ----------
    K : shape (3, 3)
    dist : shape (5,)
        ``[k1, k2, p1, p2, k3]``.
    nu, kappa : float
        Board aspect ratio and scale: true corner (i, j) at (κν i s, κ j s, 0).
    hand_eye, target_pose : shape (4, 4)
        X and Y (see module docstring for the frames per setup).
    covariance : shape (23, 23)
        Over ``GLOBAL_PARAMS``, marginalised over the station corrections; rotations of X and Y
        are small rotations on the left (axes of the frame named first, e.g. tcp for
        tcp_T_cam), translations in metres in that frame. Fixed parameters have zero rows.
    sigmas : dict[str, float | ndarray]
        Standard deviations: one float per name in ``CAMERA_PARAMS``; ``hand_eye_rot_rad``,
        ``hand_eye_trans_m``, ``target_pose_rot_rad``, ``target_pose_trans_m`` shape (3,).
    stations : shape (n,), int
        Indices (into the input) of the stations in the final solve.
    corrections : shape (n, 6)
        Estimated robot reading errors δ_i (rotation vector rad, translation m, tcp frame).
    mahalanobis : shape (n,)
        ``sqrt((angle/σ_rot)² + (length/σ_trans)²)`` of δ_i for the kept stations (chi with
        2 degrees of freedom when the noise levels are right).
    rms_px_per_station : shape (n,)
        Reprojection RMS (norm per corner) of each kept station, pixels.
    rms_px : float
        Over all corners of the kept stations.
    residuals_px : shape (m, 2)
        Projected minus detected corner (pixels), the kept stations' corners in turn.
    rejected : tuple of (int, str)
        Input index and reason of each dropped station, in the order they were dropped.
    sigma_px, robot_noise_rot, robot_noise_trans : float
        Noise levels assumed (px per coordinate; rad and m as angle and length, see the
        module docstring).
    variance_factor : float
        ``SSR / (m - n)`` of the normalised residuals; ≈ 1 when those noise levels are right.
        The covariance is scaled by it.
    nfev : int
    converged : bool
    """

    K: np.ndarray
    dist: np.ndarray
    nu: float
    kappa: float
    hand_eye: np.ndarray
    target_pose: np.ndarray
    covariance: np.ndarray
    sigmas: dict[str, float | np.ndarray]
    stations: np.ndarray
    corrections: np.ndarray
    mahalanobis: np.ndarray
    rms_px_per_station: np.ndarray
    rms_px: float
    residuals_px: np.ndarray
    rejected: tuple[tuple[int, str], ...]
    sigma_px: float
    robot_noise_rot: float
    robot_noise_trans: float
    variance_factor: float
    nfev: int
    converged: bool


def solve_joint(image_points: Sequence[np.ndarray], T_base_tcp: np.ndarray, *,
                inner_corners: Sequence[int], square_size: float, K: np.ndarray,
                dist: np.ndarray, nu: float, kappa: float, hand_eye: np.ndarray,
                target_pose: np.ndarray, setup: str = "eye_in_hand", sigma_px: float,
                point_ids: Sequence[np.ndarray] | None = None,
                robot_noise_rot: float = DEFAULT_ROBOT_NOISE_ROT_RAD,
                robot_noise_trans: float = DEFAULT_ROBOT_NOISE_TRANS_M,
                fix: Sequence[str] = (), outlier_sigma: float | None = OUTLIER_SIGMA,
                max_nfev: int = 100) -> JointResult:
    """Joint ML estimate of camera, ν, κ, X, Y and the robot corrections, from start values.

    Parameters
    ----------
    image_points : sequence of n arrays, shape (N_i, 2)
        Detected corners per station, pixels.
    T_base_tcp : shape (n, 4, 4)
        Robot readings base_T_tcp, metres.
    inner_corners : (cols, rows)
    square_size : float
        Nominal square size, metres.
    K, dist, nu, kappa, hand_eye, target_pose
        Start values (e.g. intrinsics by Method #1, X, Y, κ by the eq. 6 refinement).
    setup : ``eye_in_hand`` or ``eye_to_hand``.
    sigma_px : float
        Corner noise per coordinate, pixels (e.g. ``IntrinsicsResult.sigma_px``).
    point_ids : sequence of n int arrays, shape (N_i,), optional
        Grid index ``j * cols + i`` of each corner; default: the full grid, row-major.
    robot_noise_rot, robot_noise_trans : float
        Robot reading noise (rad, m), σ of the error's angle and length: the prior on δ_i.
    fix : names from ``FIXABLE`` held at their start values.
    outlier_sigma : float or None
        Drop stations whose correction lies beyond this Mahalanobis distance (in units of the
        configured robot noise, or of the observed spread when that is larger); None keeps all.
    max_nfev : int
        Evaluation budget per solve.
    """
    check_setup(setup)
    unknown = [f for f in fix if f not in FIXABLE]
    if unknown:
        raise ValueError(f"fix: unknown parameters {unknown}; choose from {FIXABLE}")
    if not (sigma_px > 0 and robot_noise_rot > 0 and robot_noise_trans > 0):
        raise ValueError("sigma_px, robot_noise_rot and robot_noise_trans must be positive")
    T_base_tcp = check_transforms(T_base_tcp, "tcp_pose")
    n = len(T_base_tcp)
    if len(image_points) != n:
        raise ValueError(f"{len(image_points)} corner sets but {n} robot poses")
    grid = board_points(tuple(inner_corners), square_size)[:, :2]
    ids = ([np.arange(len(grid))] * n if point_ids is None
           else [np.asarray(i, dtype=int) for i in point_ids])
    pts = [np.asarray(p, dtype=float).reshape(-1, 2) for p in image_points]
    if any(len(p) != len(i) for p, i in zip(pts, ids, strict=True)):
        raise ValueError("every station needs one grid index per corner (point_ids)")

    cam = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(dist, float)[:5], nu, kappa])
    X, Y = np.asarray(hand_eye, float), np.asarray(target_pose, float)
    keep = list(range(n))
    rejected: list[tuple[int, str]] = []
    while True:
        problem = _Problem([grid[ids[k]] for k in keep], [pts[k] for k in keep],
                           T_base_tcp[keep], setup, cam, X, Y, tuple(fix), sigma_px,
                           robot_noise_rot, robot_noise_trans)
        # lsmr needs more than its default min(m, n) iterations on small, ill-conditioned
        # problems (far cameras, eye-to-hand) to give Gauss-Newton steps.
        lsmr = {"atol": 1e-10, "btol": 1e-10, "maxiter": max(problem.shape[1], 1000)}
        sol = least_squares(problem.residuals, problem.x0(), jac=problem.jacobian,
                            method="trf", x_scale="jac", tr_solver="lsmr", tr_options=lsmr,
                            ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=max_nfev)
        cam, X, Y, delta = problem.unpack(sol.x)
        d = _distance(delta, robot_noise_rot, robot_noise_trans)
        scale = max(1.0, float(np.median(d)) / _DISTANCE_MEDIAN)
        worst = int(np.argmax(d))
        if outlier_sigma is None or d[worst] <= outlier_sigma * scale \
                or len(keep) <= MIN_STATIONS:
            break
        rejected.append((keep[worst], (
            f"robot pose inconsistent with the image: it needs a correction of "
            f"{np.degrees(np.linalg.norm(delta[worst, :3])):.3f} deg / "
            f"{1e3 * np.linalg.norm(delta[worst, 3:]):.2f} mm, {d[worst] / scale:.1f} sigma "
            f"(limit {outlier_sigma:g})")))
        del keep[worst]
    return problem.result(sol, np.array(keep), tuple(rejected))


def cramer_rao_bound(T_base_tcp: np.ndarray, *, inner_corners: Sequence[int],
                     square_size: float, K: np.ndarray, dist: np.ndarray, nu: float,
                     kappa: float, hand_eye: np.ndarray, target_pose: np.ndarray,
                     setup: str = "eye_in_hand", sigma_px: float,
                     robot_noise_rot: float = DEFAULT_ROBOT_NOISE_ROT_RAD,
                     robot_noise_trans: float = DEFAULT_ROBOT_NOISE_TRANS_M,
                     fix: Sequence[str] = ()) -> dict[str, float | np.ndarray]:
    """Cramér-Rao lower bound of the joint model at the truth, for benchmarks.

    The inverse Fisher information ``(JᵀJ)⁻¹`` of the normalised residuals (``_Problem``)
    at the true parameters, full board seen at every true robot pose ``T_base_tcp`` (n, 4, 4),
    station blocks eliminated as in :func:`solve_joint`. Returns the covariance (23, 23) over
    ``GLOBAL_PARAMS`` as ``covariance``, its 3x3 blocks ``hand_eye_rot``, ``hand_eye_trans``,
    ``target_pose_rot``, ``target_pose_trans``, and the standard deviation of each name in
    ``CAMERA_PARAMS``.
    """
    grid = board_points(tuple(inner_corners), square_size)[:, :2]
    n = len(T_base_tcp)
    cam = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(dist, float)[:5], nu, kappa])
    # the Jacobian does not depend on the observations: placeholders suffice
    problem = _Problem([grid] * n, [np.zeros_like(grid)] * n, np.asarray(T_base_tcp, float),
                       setup, cam, np.asarray(hand_eye, float), np.asarray(target_pose, float),
                       tuple(fix), sigma_px, robot_noise_rot, robot_noise_trans)
    cov = np.zeros((_N_GLOBAL, _N_GLOBAL))
    cov[np.ix_(problem.free, problem.free)] = problem.covariance(problem.x0(), 1.0)
    bound: dict[str, float | np.ndarray] = {
        name: float(np.sqrt(cov[i, i])) for i, name in enumerate(CAMERA_PARAMS)}
    for name, start in (("hand_eye_rot", 11), ("hand_eye_trans", 14), ("target_pose_rot", 17),
                        ("target_pose_trans", 20)):
        bound[name] = cov[start:start + 3, start:start + 3]
    bound["covariance"] = cov
    return bound


class _Problem:
    """Residuals and sparse Jacobian of the joint problem for a fixed set of stations.

    ``x = [free global parameters, n x δ_i]``; the global rotations and translations of X and Y
    are offsets from the reference ``X0``, ``Y0`` (left rotation vector, added translation).
    Residual rows: 2 per corner (station by station), then 6 per station.
    """

    def __init__(self, grid: list[np.ndarray], img: list[np.ndarray], T_base_tcp: np.ndarray,
                 setup: str, cam0: np.ndarray, X0: np.ndarray, Y0: np.ndarray,
                 fixed: tuple[str, ...], sigma_px: float, sigma_rot: float,
                 sigma_trans: float) -> None:
        counts = np.array([len(g) for g in grid])
        self.obj, self.img = np.concatenate(grid), np.concatenate(img)
        self.counts, self.starts = counts, np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.station = np.repeat(np.arange(len(counts)), counts)
        self.M = invert(robot_chain(T_base_tcp, setup))  # tcp_T_base, or base_T_tcp
        self.eye_in_hand = setup == "eye_in_hand"
        self.cam0, self.X0, self.Y0 = cam0, X0, Y0
        self.free = np.array([name not in fixed for name in CAMERA_PARAMS] + [True] * 12)
        self.sigma_px = sigma_px
        # per component: the angle (length) σ spread over three directions
        self.prior_sigma = np.array([sigma_rot] * 3 + [sigma_trans] * 3) / np.sqrt(3.0)
        self.n_stations = len(counts)
        nf = int(self.free.sum())
        m, n = len(self.obj), self.n_stations
        # CSR layout: corner rows hold the free globals and their station's 6 columns,
        # prior rows one diagonal entry each.
        cols = np.concatenate([np.broadcast_to(np.arange(nf), (m, nf)),
                               nf + 6 * self.station[:, None] + np.arange(6)], axis=1)
        self.indices = np.concatenate([np.repeat(cols, 2, axis=0).ravel(),
                                       nf + np.arange(6 * n)])
        self.indptr = np.concatenate([np.arange(2 * m + 1) * (nf + 6),
                                      2 * m * (nf + 6) + np.arange(1, 6 * n + 1)])
        self.shape = (2 * m + 6 * n, nf + 6 * n)
        self.n_free_global = nf
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def x0(self) -> np.ndarray:
        g = np.concatenate([self.cam0, np.zeros(12)])
        return np.concatenate([g[self.free], np.zeros(6 * self.n_stations)])

    def _globals(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = np.concatenate([self.cam0, np.zeros(12)])
        g[self.free] = x[:self.n_free_global]
        return g, g[_N_CAM:], x[self.n_free_global:].reshape(-1, 6)

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Camera parameters (11,), X, Y (4, 4) and corrections δ (n, 6) of ``x``."""
        g, xy, delta = self._globals(x)
        return g[:_N_CAM], so3.left_update(self.X0, xy[:6]), so3.left_update(self.Y0, xy[6:]), delta

    def _evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised residuals (2m + 6n,) and corner blocks (m, 2, n_free + 6)."""
        if self._cache is not None and np.array_equal(self._cache[0], x):
            return self._cache[1], self._cache[2]
        cam, X, Y, delta = self.unpack(x)
        _, xy, _ = self._globals(x)
        s = self.station
        nu, kappa = cam[_NU], cam[_KAPPA]
        p = np.column_stack([self.obj[:, 0] * kappa * nu, self.obj[:, 1] * kappa,
                             np.zeros(len(self.obj))])
        # The chain as links applied to the board point in turn: name -> (R, t, inverse?, J_l);
        # J_l (the left Jacobian of the link's rotation parameters) is None for the readings.
        E_R, E_J = so3.exp(delta[:, :3])[s], so3.left_jacobian(delta[:, :3])[s]
        links = {"Y": (Y[:3, :3], Y[:3, 3], False, so3.left_jacobian(xy[6:9])),
                 "M": (self.M[s, :3, :3], self.M[s, :3, 3], False, None),
                 "E": (E_R, delta[s, 3:], self.eye_in_hand, E_J),
                 "X": (X[:3, :3], X[:3, 3], True, so3.left_jacobian(xy[0:3]))}
        order = ("Y", "M", "E", "X") if self.eye_in_hand else ("Y", "E", "M", "X")
        inputs = {}
        v = p
        for name in order:
            R, t, inverse, _ = links[name]
            inputs[name] = v
            v = _apply(R, t, v, inverse)
        K = np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])
        uv, J = project(v, K, cam[4:9], jacobian=True)

        # Back-propagate d uv / d(point) through the links, collecting (rotation, translation)
        # parameter blocks: R v + t moves by -[R v]x J_l da and dt; Rᵀ(v - t) by
        # Rᵀ [v - t]x J_l da and -Rᵀ dt. (A row g times [w]x is g x w.)
        H = J.points
        blocks = {}
        for name in reversed(order):
            R, t, inverse, Jl = links[name]
            Rb = np.broadcast_to(R, (len(p), 3, 3))
            if inverse:
                HRt = np.einsum("mki,mji->mkj", H, Rb)
                if Jl is not None:
                    lever = inputs[name] - t
                    blocks[name] = (_rows_times(np.cross(HRt, lever[:, None, :]), Jl), -HRt)
                H = HRt
            else:
                if Jl is not None:
                    lever = _apply(R, np.zeros(3), inputs[name], False)
                    blocks[name] = (_rows_times(-np.cross(H, lever[:, None, :]), Jl), H)
                H = np.einsum("mki,mij->mkj", H, Rb)
        # H is now d uv / d p with p = (κν x, κ y, 0).
        d_nu = H[:, :, 0] * (kappa * self.obj[:, None, 0])
        d_kappa = H[:, :, 0] * (nu * self.obj[:, None, 0]) + H[:, :, 1] * self.obj[:, None, 1]
        d_glob = np.concatenate([J.intrinsics, J.dist, d_nu[..., None], d_kappa[..., None],
                                 *blocks["X"], *blocks["Y"]], axis=2)[:, :, self.free]
        corner = np.concatenate([d_glob, *blocks["E"]], axis=2) / self.sigma_px
        r = np.concatenate([((uv - self.img) / self.sigma_px).ravel(),
                            (delta / self.prior_sigma).ravel()])
        self._cache = (x.copy(), r, corner)
        return r, corner

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self._evaluate(x)[0]

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        corner = self._evaluate(x)[1]
        prior = np.tile(1.0 / self.prior_sigma, self.n_stations)
        return csr_matrix((np.concatenate([corner.ravel(), prior]), self.indices, self.indptr),
                          shape=self.shape)

    def covariance(self, x: np.ndarray, variance_factor: float) -> np.ndarray:
        """Covariance of the free globals (Schur complement over the station blocks).

        With JᵀJ = [[U, W], [Wᵀ, V]] and V block diagonal (6 x 6 per station):
        cov = s² (U - Σ_i W_i V_i⁻¹ W_iᵀ)⁻¹.
        """
        J = self.jacobian(x)
        g = self.n_free_global
        JtJ = (J.T @ J).toarray()
        n = self.n_stations
        U = JtJ[:g, :g]
        W = JtJ[:g, g:].reshape(g, n, 6).transpose(1, 0, 2)  # (n, g, 6)
        V = JtJ[g:, g:].reshape(n, 6, n, 6)[np.arange(n), :, np.arange(n), :]  # (n, 6, 6)
        WV = W @ np.linalg.inv(V)
        S = U - np.einsum("nij,nkj->ik", WV, W)
        return variance_factor * np.linalg.inv(S)

    def result(self, sol: OptimizeResult, stations: np.ndarray,
               rejected: tuple[tuple[int, str], ...]) -> JointResult:
        x = sol.x
        r, _ = self._evaluate(x)
        cam, X, Y, delta = self.unpack(x)
        m, n = self.shape
        variance_factor = float(r @ r) / max(m - n, 1)
        cov = np.zeros((_N_GLOBAL, _N_GLOBAL))
        cov[np.ix_(self.free, self.free)] = self.covariance(x, variance_factor)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        sigmas: dict[str, float | np.ndarray] = {
            name: float(sd[i]) for i, name in enumerate(CAMERA_PARAMS)}
        sigmas.update(hand_eye_rot_rad=sd[11:14], hand_eye_trans_m=sd[14:17],
                      target_pose_rot_rad=sd[17:20], target_pose_trans_m=sd[20:23])
        residuals_px = r[:2 * len(self.obj)].reshape(-1, 2) * self.sigma_px
        sq = np.sum(residuals_px ** 2, axis=1)
        K = np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])
        return JointResult(
            K=K, dist=cam[4:9].copy(), nu=float(cam[_NU]), kappa=float(cam[_KAPPA]),
            hand_eye=X, target_pose=Y, covariance=cov, sigmas=sigmas, stations=stations,
            corrections=delta.copy(),
            mahalanobis=_distance(delta, *(self.prior_sigma[[0, 3]] * np.sqrt(3.0))),
            rms_px_per_station=np.sqrt(np.add.reduceat(sq, self.starts) / self.counts),
            rms_px=float(np.sqrt(sq.mean())), residuals_px=residuals_px, rejected=rejected,
            sigma_px=self.sigma_px,
            robot_noise_rot=float(self.prior_sigma[0] * np.sqrt(3.0)),
            robot_noise_trans=float(self.prior_sigma[3] * np.sqrt(3.0)),
            variance_factor=variance_factor,
            nfev=int(sol.nfev), converged=bool(sol.status > 0))


def _distance(delta: np.ndarray, sigma_rot: float, sigma_trans: float) -> np.ndarray:
    """Mahalanobis distance of corrections (n, 6) under angle/length noise σ, shape (n,)."""
    return np.hypot(np.linalg.norm(delta[:, :3], axis=1) / sigma_rot,
                    np.linalg.norm(delta[:, 3:], axis=1) / sigma_trans)


def _apply(R: np.ndarray, t: np.ndarray, v: np.ndarray, inverse: bool) -> np.ndarray:
    """``R v + t``, or ``Rᵀ (v - t)`` when ``inverse``; R (3, 3) or (m, 3, 3), v (m, 3)."""
    if inverse:
        return np.einsum("...ji,...j->...i", R, v - t)
    return np.einsum("...ij,...j->...i", R, v) + t


def _rows_times(G: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Stacked ``G @ M``, shapes (m, 2, 3), (3, 3) or (m, 3, 3) -> (m, 2, 3)."""
    return np.einsum("mki,ij->mkj", G, M) if M.ndim == 2 else np.einsum("mki,mij->mkj", G, M)


def nu_from_extrinsics(image_points: Sequence[np.ndarray], T_base_tcp: np.ndarray, *,
                       inner_corners: Sequence[int], square_size: float,
                       image_size: Sequence[int], nu0: float, setup: str = "eye_in_hand",
                       point_ids: Sequence[np.ndarray] | None = None,
                       fix: Sequence[str] = (), half_width: float = 0.005,
                       robot_noise_rot: float = DEFAULT_ROBOT_NOISE_ROT_RAD,
                       robot_noise_trans: float = DEFAULT_ROBOT_NOISE_TRANS_M
                       ) -> tuple[float, float]:
    """ν from the extrinsic residuals, Strobl & Hirzinger Method #2; returns (ν, σ_ν).

    For each trial ν the intrinsic bundle adjustment runs with ν held (eq. 3 with the board
    model scaled by ν), then X, Y and κ are refined from the poses (eq. 6); the cost is the
    sum of squared pose residuals over the *configured* robot noise, so that costs at
    different ν compare. A bounded 1-D search within ``nu0 ± half_width`` (the paper's
    "very restricted local search" started from Method #1) finds the minimum; σ_ν follows
    from the cost's curvature (Δχ² = 1, scaled by the reduced χ² at the minimum).

    Parameters
    ----------
    image_points : sequence of n arrays, shape (N_i, 2)
    T_base_tcp : shape (n, 4, 4)
    inner_corners, square_size, image_size, point_ids, fix : as in ``calibrate_intrinsics``.
    nu0 : float
        Start, e.g. the Method #1 estimate.
    """
    weights = np.array([robot_noise_rot] * 3 + [robot_noise_trans] * 3)
    P = robot_chain(check_transforms(T_base_tcp, "tcp_pose"), setup)

    def cost(nu: float) -> float:
        intr = calibrate_intrinsics(image_points, inner_corners, square_size, image_size,
                                    point_ids=point_ids, estimate_nu=False, nu=nu, fix=fix)
        he = calibrate_hand_eye(T_base_tcp, intr.T_cam_target, setup=setup, method="joint",
                                estimate_kappa=True, robot_noise_rot=robot_noise_rot,
                                robot_noise_trans=robot_noise_trans)
        r = pose_residuals(P, intr.T_cam_target, he.hand_eye, he.target_pose, he.kappa,
                           inverted=setup == "eye_to_hand")
        return float(np.sum((r / weights) ** 2))

    sol = minimize_scalar(cost, bounds=(nu0 - half_width, nu0 + half_width), method="bounded",
                          options={"xatol": 1e-6})
    nu, f0 = float(sol.x), float(sol.fun)
    h = 1e-3 * half_width + 2e-4
    curvature = (cost(nu + h) + cost(nu - h) - 2.0 * f0) / (h * h)
    dof = max(6 * len(P) - 14, 1)
    sigma = float(np.sqrt(2.0 / curvature * f0 / dof)) if curvature > 0 else np.inf
    return nu, sigma

