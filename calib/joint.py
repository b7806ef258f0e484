"""Joint maximum-likelihood calibration over every corner and every robot pose (default result).

The staged estimates (intrinsics with ν, Method #1 eq. 5; hand-eye and κ from the poses, eq. 6)
each treat the previous stage as exact. The joint estimate instead minimises, over all unknowns
at once, the negative log-likelihood of everything that was measured (Strobl & Hirzinger,
footnote 5; their Method #1 residuals plus the robot readings as noisy measurements):

* every detected corner ``m``, with the camera pose of station i implied by the robot chain
  (``docs/conventions.md``) instead of being free per image::

      eye-in-hand:  C_i = inv(X) inv(P_i E_i) Y          (X = T_tcp_cam, Y = T_base_target)
      eye-to-hand:  C_i = inv(X) (P_i E_i) Y             (X = T_base_cam, Y = T_tcp_target)

  with ``P_i`` the reading T_base_tcp and ``E_i = exp(δ_i)`` the unknown reading error applied
  on the right, in the tcp frame (as ``calib.geometry.perturb`` draws UR noise), and the true
  corner (i, j) at (κν i s, κ j s, 0) (eq. 4): residual ``(m̂ - m) / σ_px``;
* every robot reading, through its correction: residual ``δ_i / (σ_rot, σ_trans) · √3``.
  The noise levels mean what they mean in Strobl & Hirzinger section IV-A and
  ``calib.geometry.perturb``: the σ of the rotation *angle* about a random axis and of the
  translation *length* along a random direction, so each of the three components of the
  rotation vector (translation) has standard deviation σ / √3.

Unknowns: ``fx, fy, cx, cy, k1, k2, p1, p2, k3, ν, κ``, X and Y (small left rotations and
translations about a reference), and 6 per station. Levenberg-Marquardt with the station blocks
eliminated (``calib.schur``) runs on an analytic Jacobian (one 2 x (23 + 6) block per corner,
one diagonal entry per prior). On request (``JointOptions.robot_map``) the robot's translations
are mapped ``t + S t`` first (``calib.chain.corrected_readings``), S a traceless 3 x 3 matrix
of 8 more unknowns: an industrial arm's positions off by a linear map of a fraction of a
percent, which per-station noise cannot describe.
The covariance of the 23 global parameters comes from the Jacobian at the optimum with the
station blocks eliminated by a Schur complement, scaled by the residual variance factor.

Stations whose correction is implausible are dropped one at a time, worst first, and the problem
solved again: the distance ``sqrt((angle/σ_rot)² + (length/σ_trans)²)`` of δ_i (Mahalanobis in
the noise model above, a chi variable with 2 degrees of freedom) beyond ``outlier_sigma``.

The same model gives the Cramér-Rao bound (``calib.bounds``); ν by Method #2 is in ``calib.nu``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import csr_matrix

from calib import so3
from calib.boards import Board
from calib.camera import Pinhole
from calib.chain import RobotNoise, check_setup, robot_chain
from calib.geometry import check_transforms, invert
from calib.handeye import MIN_STATIONS
from calib.lsq import CachedProblem
from calib.options import OUTLIER_SIGMA
from calib.schur import BlockSolution, solve_blocks

#: Camera and board parameters, in the order of :attr:`JointResult.covariance`.
CAMERA_PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "nu", "kappa")
#: The robot translation map S (``calib.chain.corrected_readings``) as coefficients of a basis
#: (``_MAP_BASIS``): six skews and two traceless scales. Its isotropic scale is left out: it
#: is κ's (a robot 0.1 % long and a board 0.1 % small give the same images), and with κ held
#: at 1 it would take up any error of the entered square size.
MAP_PARAMS = tuple(f"robot_map_{a}" for a in ("xy", "xz", "yx", "yz", "zx", "zy", "xx_yy",
                                              "yy_zz"))
#: All global parameters: camera, then X and Y as (small left rotation, translation), then S.
GLOBAL_PARAMS = (*CAMERA_PARAMS,
                 *(f"hand_eye_{a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")),
                 *(f"target_pose_{a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")),
                 *MAP_PARAMS)
#: Parameters that ``fix=`` may hold at their start values (known intrinsics: the first nine).
FIXABLE = (*CAMERA_PARAMS,)

_N_CAM = len(CAMERA_PARAMS)
_N_POSE = 12
_N_GLOBAL = _N_CAM + _N_POSE  # the globals before the robot map
_MAP_BASIS = np.zeros((len(MAP_PARAMS), 3, 3))
for _k, (_a, _b) in enumerate(((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))):
    _MAP_BASIS[_k, _a, _b] = 1.0
_MAP_BASIS[6], _MAP_BASIS[7] = np.diag([1.0, -1.0, 0.0]), np.diag([0.0, 1.0, -1.0])
_NU, _KAPPA = CAMERA_PARAMS.index("nu"), CAMERA_PARAMS.index("kappa")
#: Median of the chi distribution with 2 degrees of freedom (the correction's distance): a
#: chi-square with 2 degrees of freedom is exponential with mean 2, so its median is 2 ln 2.
#: (Written out: importing scipy.stats costs every ``cellcal`` command half a second.)
_DISTANCE_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))


@dataclass(frozen=True)
class CornerStations:
    """What was measured at n stations: corners of a board and the robot readings.

    ``image_points`` holds n arrays (N_i, 2) of detected corners (pixels), ``T_base_tcp`` the
    readings (n, 4, 4) in metres, ``point_ids`` optionally n int arrays (N_i,) with the board's
    point id of each corner (partial views; default: all of the board's points in order).
    """

    image_points: Sequence[np.ndarray]
    T_base_tcp: np.ndarray
    board: Board
    point_ids: Sequence[np.ndarray] | None = None

    def ids(self) -> list[np.ndarray]:
        """Point ids (N_i,) int64 of every station's corners."""
        if self.point_ids is None:
            return [self.board.point_ids] * len(self.image_points)
        return [np.asarray(i, dtype=np.int64) for i in self.point_ids]

    def grids(self) -> list[np.ndarray]:
        """Nominal board coordinates (N_i, 2) of every station's corners."""
        grid = self.board.points()[:, :2]
        return [grid[i] for i in self.ids()]

    def subset(self, index: Sequence[int] | np.ndarray) -> CornerStations:
        """The stations ``index`` (in that order), ids included."""
        index = [int(i) for i in index]
        ids = None if self.point_ids is None else [self.point_ids[i] for i in index]
        return replace(self, image_points=[self.image_points[i] for i in index],
                       T_base_tcp=np.asarray(self.T_base_tcp)[index], point_ids=ids)


@dataclass(frozen=True)
class CellParameters:
    """The global unknowns of the joint model: start values, or the truth for a bound.

    ``K`` (3, 3), ``dist`` (5,) ``[k1, k2, p1, p2, k3]``, the board's ``nu`` and ``kappa``,
    ``hand_eye`` X and ``target_pose`` Y (4, 4) in the frames of the setup (module docstring);
    ``robot_map`` S (3, 3), the linear map of the robot's translations
    (``calib.chain.corrected_readings``), None where the model has none.
    """

    K: np.ndarray
    dist: np.ndarray
    nu: float
    kappa: float
    hand_eye: np.ndarray
    target_pose: np.ndarray
    robot_map: np.ndarray | None = field(default=None, kw_only=True)

    def camera_vector(self) -> np.ndarray:
        """The values of ``CAMERA_PARAMS``, shape (11,)."""
        K = np.asarray(self.K, dtype=float)
        return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                         *np.asarray(self.dist, dtype=float)[:5], self.nu, self.kappa])


@dataclass(frozen=True)
class JointOptions:
    """How the joint problem is weighted and solved.

    ``sigma_px`` is the corner noise per coordinate (pixels, e.g. ``IntrinsicsResult.sigma_px``),
    ``noise`` the robot reading noise (the prior on δ_i), ``fix`` names from ``FIXABLE`` held at
    their start values, ``outlier_sigma`` the limit beyond which a station's correction drops
    it (in units of the configured robot noise, or of the observed spread when that is larger;
    None keeps all), ``max_nfev`` the evaluation budget per solve. ``robot_map``: estimate the
    linear map S of the robot's translations (traceless: its scale is κ's).
    """

    sigma_px: float
    setup: str = "eye_in_hand"
    noise: RobotNoise = field(default_factory=RobotNoise)
    fix: tuple[str, ...] = ()
    outlier_sigma: float | None = OUTLIER_SIGMA
    max_nfev: int = 100
    robot_map: bool = False

    def __post_init__(self) -> None:
        check_setup(self.setup)
        unknown = [f for f in self.fix if f not in FIXABLE]
        if unknown:
            raise ValueError(f"fix: unknown parameters {unknown}; choose from {FIXABLE}")
        if not self.sigma_px > 0:
            raise ValueError("sigma_px must be positive")


@dataclass(frozen=True)
class JointResult(CellParameters):
    """Joint maximum-likelihood estimate (the :class:`CellParameters` fields) and its uncertainty.

    Attributes (beyond the estimate)
    --------------------------------
    covariance : shape (31, 31)
        Over ``GLOBAL_PARAMS``, marginalised over the station corrections; rotations of X and Y
        are small rotations on the left (axes of the frame named first, e.g. tcp for
        T_tcp_cam), translations in metres in that frame. Fixed parameters have zero rows.
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


def solve_joint(stations: CornerStations, start: CellParameters,
                options: JointOptions) -> JointResult:
    """Joint ML estimate of camera, ν, κ, X, Y and the robot corrections, from start values.

    ``start`` holds e.g. the intrinsics by Method #1 and X, Y, κ by the eq. (6) refinement.
    Stations whose correction is implausible are dropped one at a time (module docstring).
    """
    T_base_tcp = check_transforms(stations.T_base_tcp, "tcp_pose")
    n = len(T_base_tcp)
    if len(stations.image_points) != n:
        raise ValueError(f"{len(stations.image_points)} corner sets but {n} robot poses")
    grids = stations.grids()
    pts = [np.asarray(p, dtype=float).reshape(-1, 2) for p in stations.image_points]
    if any(len(p) != len(g) for p, g in zip(pts, grids, strict=True)):
        raise ValueError("every station needs one point id per corner (point_ids)")

    keep = list(range(n))
    rejected: list[tuple[int, str]] = []
    while True:
        problem = JointProblem([grids[k] for k in keep], [pts[k] for k in keep],
                               T_base_tcp[keep], start, options)
        # the station blocks eliminated exactly (calib.schur): an iterative sparse solver
        # needs hundreds of products per step on these ill-conditioned problems
        sol = solve_blocks(problem, problem.x0(), max_nfev=options.max_nfev, ftol=1e-12)
        start, delta = problem.unpack(sol.x)
        d = _distance(delta, options.noise)
        scale = max(1.0, float(np.median(d)) / _DISTANCE_MEDIAN)
        worst = int(np.argmax(d))
        limit = options.outlier_sigma
        if limit is None or d[worst] <= limit * scale or len(keep) <= MIN_STATIONS:
            break
        rejected.append((keep[worst], (
            f"robot pose inconsistent with the image: it needs a correction of "
            f"{np.degrees(np.linalg.norm(delta[worst, :3])):.3f} deg / "
            f"{1e3 * np.linalg.norm(delta[worst, 3:]):.2f} mm, {d[worst] / scale:.1f} sigma "
            f"(limit {limit:g})")))
        del keep[worst]
    return problem.result(sol, np.array(keep), tuple(rejected))


class JointProblem(CachedProblem):
    """Residuals and sparse Jacobian of the joint problem for a fixed set of stations.

    ``x = [free global parameters, n x δ_i]``; the global rotations and translations of X and Y
    are offsets from the reference ``start.hand_eye``, ``start.target_pose`` (left rotation
    vector and added translation, :func:`calib.so3.left_update`). Residual rows: 2 per corner
    (station by station), then 6 per station.

    ``grid`` and ``img`` hold per station the nominal board coordinates (N_i, 2) of its corners
    and their detections (N_i, 2); ``T_base_tcp`` (n, 4, 4) the robot readings.
    """

    def __init__(self, grid: list[np.ndarray], img: list[np.ndarray], T_base_tcp: np.ndarray,
                 start: CellParameters, options: JointOptions) -> None:
        counts = np.array([len(g) for g in grid])
        self.obj, self.img = np.concatenate(grid), np.concatenate(img)
        self.counts, self.starts = counts, np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.station = np.repeat(np.arange(len(counts)), counts)
        self.M = invert(robot_chain(T_base_tcp, options.setup))  # T_tcp_base, or T_base_tcp
        self.t_read = np.asarray(T_base_tcp, dtype=float)[:, :3, 3]  # readings' translations
        self.S0 = np.zeros((3, 3)) if start.robot_map is None else np.asarray(start.robot_map)
        self.has_map = options.robot_map or start.robot_map is not None
        self.eye_in_hand = options.setup == "eye_in_hand"
        self.cam0 = start.camera_vector()
        self.X0 = np.asarray(start.hand_eye, dtype=float)
        self.Y0 = np.asarray(start.target_pose, dtype=float)
        map_free = [options.robot_map] * len(MAP_PARAMS)
        self.free = np.array([name not in options.fix for name in CAMERA_PARAMS]
                             + [True] * _N_POSE + map_free)
        self.sigma_px = options.sigma_px
        self.noise = options.noise
        # per component: the angle (length) σ spread over three directions
        self.prior_sigma = np.array([options.noise.rot_rad] * 3
                                    + [options.noise.trans_m] * 3) / np.sqrt(3.0)
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

    def x0(self) -> np.ndarray:
        g = np.concatenate([self.cam0, np.zeros(_N_POSE + len(MAP_PARAMS))])
        return np.concatenate([g[self.free], np.zeros(6 * self.n_stations)])

    def _globals(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = np.concatenate([self.cam0, np.zeros(_N_POSE + len(MAP_PARAMS))])
        g[self.free] = x[:self.n_free_global]
        return g, g[_N_CAM:], x[self.n_free_global:].reshape(-1, 6)

    def _unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Camera parameters (11,), X, Y (4, 4) and corrections δ (n, 6) of ``x``."""
        g, xy, delta = self._globals(x)
        X, Y = so3.left_update(self.X0, xy[:6]), so3.left_update(self.Y0, xy[6:_N_POSE])
        return g[:_N_CAM], X, Y, delta

    def _map(self, x: np.ndarray) -> np.ndarray:
        """The robot translation map S (3, 3) of ``x``."""
        _, xy, _ = self._globals(x)
        return self.S0 + np.einsum("k,kab->ab", xy[_N_POSE:], _MAP_BASIS)

    def _map_link(self, x: np.ndarray) -> np.ndarray:
        """Translations (n, 3) of the robot link ``M`` with the readings mapped by S."""
        t = self.t_read + self.t_read @ self._map(x).T
        if self.eye_in_hand:  # M = inv(T_base_tcp): translation -Rᵀ t
            return -np.einsum("nij,nj->ni", self.M[:, :3, :3], t)
        return t

    def unpack(self, x: np.ndarray) -> tuple[CellParameters, np.ndarray]:
        """The global parameters of ``x`` and the corrections δ (n, 6)."""
        cam, X, Y, delta = self._unpack(x)
        return CellParameters(K=_camera_matrix(cam), dist=cam[4:9].copy(), nu=float(cam[_NU]),
                              kappa=float(cam[_KAPPA]), hand_eye=X, target_pose=Y,
                              robot_map=self._map(x) if self.has_map else None), delta

    def _compute(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised residuals (2m + 6n,) and corner blocks (m, 2, n_free + 6)."""
        cam, X, Y, delta = self._unpack(x)
        _, xy, _ = self._globals(x)
        s = self.station
        nu, kappa = cam[_NU], cam[_KAPPA]
        p = np.column_stack([self.obj[:, 0] * kappa * nu, self.obj[:, 1] * kappa,
                             np.zeros(len(self.obj))])
        # The chain as links applied to the board point in turn: name -> (R, t, inverse?, J_l);
        # J_l (the left Jacobian of the link's rotation parameters) is None for the readings.
        E_R, E_J = so3.exp(delta[:, :3])[s], so3.left_jacobian(delta[:, :3])[s]
        links = {"Y": (Y[:3, :3], Y[:3, 3], False, so3.left_jacobian(xy[6:9])),
                 "M": (self.M[s, :3, :3], (self._map_link(x) if self.has_map
                                            else self.M[:, :3, 3])[s], False, None),
                 "E": (E_R, delta[s, 3:], self.eye_in_hand, E_J),
                 "X": (X[:3, :3], X[:3, 3], True, so3.left_jacobian(xy[0:3]))}
        order = ("Y", "M", "E", "X") if self.eye_in_hand else ("Y", "E", "M", "X")
        inputs = {}
        v = p
        for name in order:
            R, t, inverse, _ = links[name]
            inputs[name] = v
            v = _apply(R, t, v, inverse)
        uv, J = Pinhole(_camera_matrix(cam), cam[4:9]).project(v, jacobian=True)

        # Back-propagate d uv / d(point) through the links, collecting (rotation, translation)
        # parameter blocks: R v + t moves by -[R v]x J_l da and dt; Rᵀ(v - t) by
        # Rᵀ [v - t]x J_l da and -Rᵀ dt. (A row g times [w]x is g x w.)
        H = J.points
        blocks = {}
        for name in reversed(order):
            R, t, inverse, Jl = links[name]
            if name == "M" and self.has_map:
                blocks["S"] = self._map_block(H, s)[:, :, self.free[-len(MAP_PARAMS):]]
            if inverse:
                HRt = _rows_times(H, np.swapaxes(R, -1, -2))
                if Jl is not None:
                    lever = inputs[name] - t
                    blocks[name] = (_rows_times(np.cross(HRt, lever[:, None, :]), Jl), -HRt)
                H = HRt
            else:
                if Jl is not None:
                    lever = _apply(R, np.zeros(3), inputs[name], False)
                    blocks[name] = (_rows_times(-np.cross(H, lever[:, None, :]), Jl), H)
                H = _rows_times(H, R)
        # H is now d uv / d p with p = (κν x, κ y, 0).
        d_nu = H[:, :, 0] * (kappa * self.obj[:, None, 0])
        d_kappa = H[:, :, 0] * (nu * self.obj[:, None, 0]) + H[:, :, 1] * self.obj[:, None, 1]
        d_glob = np.concatenate([J.intrinsics, J.dist, d_nu[..., None], d_kappa[..., None],
                                 *blocks["X"], *blocks["Y"]], axis=2)[:, :, self.free[:_N_GLOBAL]]
        if "S" in blocks:
            d_glob = np.concatenate([d_glob, blocks["S"]], axis=2)
        corner = np.concatenate([d_glob, *blocks["E"]], axis=2) / self.sigma_px
        r = np.concatenate([((uv - self.img) / self.sigma_px).ravel(),
                            (delta / self.prior_sigma).ravel()])
        return r, corner

    def _map_block(self, H: np.ndarray, s: np.ndarray) -> np.ndarray:
        """d uv / d(map coefficients), (m, 2, 8), from ``H`` = d uv / d(output of link M)
        (m, 2, 3): the link's translation moves by D B_k t, D = -R_M eye-in-hand, I else."""
        G = np.einsum("mki,mij->mkj", H, -self.M[s, :3, :3]) if self.eye_in_hand else H
        Bt = np.einsum("kab,mb->mka", _MAP_BASIS, self.t_read[s])  # (m, 8, 3)
        return np.einsum("mja,mka->mjk", G, Bt)

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        corner = self.evaluate(x)[1]
        prior = np.tile(1.0 / self.prior_sigma, self.n_stations)
        return csr_matrix((np.concatenate([corner.ravel(), prior]), self.indices, self.indptr),
                          shape=self.shape)

    def covariance(self, x: np.ndarray, variance_factor: float) -> np.ndarray:
        """Covariance (31, 31) over ``GLOBAL_PARAMS``, zero for fixed ones.

        The station blocks are eliminated by a Schur complement: with JᵀJ = [[U, W], [Wᵀ, V]]
        and V block diagonal (6 x 6 per station), cov = s² (U - Σ_i W_i V_i⁻¹ W_iᵀ)⁻¹.
        """
        cov = np.zeros((len(GLOBAL_PARAMS), len(GLOBAL_PARAMS)))
        cov[np.ix_(self.free, self.free)] = variance_factor * np.linalg.inv(
            self.reduced_information(x))
        return cov

    def reduced_information(self, x: np.ndarray) -> np.ndarray:
        """Fisher information (g, g) of the free globals with the station blocks eliminated:
        ``U - Σ_i W_i V_i⁻¹ W_iᵀ`` (see :meth:`covariance`). It adds up over stations, which
        is what lets a planner score one more station cheaply (``calib.viewselect``)."""
        J = self.jacobian(x)
        g = self.n_free_global
        JtJ = (J.T @ J).toarray()
        n = self.n_stations
        U = JtJ[:g, :g]
        W = JtJ[:g, g:].reshape(g, n, 6).transpose(1, 0, 2)  # (n, g, 6)
        V = JtJ[g:, g:].reshape(n, 6, n, 6)[np.arange(n), :, np.arange(n), :]  # (n, 6, 6)
        WV = W @ np.linalg.inv(V)
        return U - np.einsum("nij,nkj->ik", WV, W)

    def result(self, sol: BlockSolution, stations: np.ndarray,
               rejected: tuple[tuple[int, str], ...]) -> JointResult:
        x = sol.x
        r, _ = self.evaluate(x)
        est, delta = self.unpack(x)
        m, n = self.shape
        variance_factor = float(r @ r) / max(m - n, 1)
        cov = self.covariance(x, variance_factor)
        sigmas = sigmas_from_covariance(cov)
        residuals_px = r[:2 * len(self.obj)].reshape(-1, 2) * self.sigma_px
        sq = np.sum(residuals_px ** 2, axis=1)
        return JointResult(
            **vars(est), covariance=cov, sigmas=sigmas, stations=stations,
            corrections=delta.copy(), mahalanobis=_distance(delta, self.noise),
            rms_px_per_station=np.sqrt(np.add.reduceat(sq, self.starts) / self.counts),
            rms_px=float(np.sqrt(sq.mean())), residuals_px=residuals_px, rejected=rejected,
            sigma_px=self.sigma_px, robot_noise_rot=self.noise.rot_rad,
            robot_noise_trans=self.noise.trans_m, variance_factor=variance_factor,
            nfev=int(sol.nfev), converged=bool(sol.status > 0))


def sigmas_from_covariance(cov: np.ndarray) -> dict[str, float | np.ndarray]:
    """``JointResult.sigmas`` of a covariance (31, 31) over ``GLOBAL_PARAMS`` (camera, X, Y)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    sigmas: dict[str, float | np.ndarray] = {
        name: float(sd[i]) for i, name in enumerate(CAMERA_PARAMS)}
    sigmas.update(hand_eye_rot_rad=sd[11:14], hand_eye_trans_m=sd[14:17],
                  target_pose_rot_rad=sd[17:20], target_pose_trans_m=sd[20:23])
    return sigmas


def _distance(delta: np.ndarray, noise: RobotNoise) -> np.ndarray:
    """Mahalanobis distance of corrections (n, 6) under angle/length noise σ, shape (n,)."""
    return np.hypot(np.linalg.norm(delta[:, :3], axis=1) / noise.rot_rad,
                    np.linalg.norm(delta[:, 3:], axis=1) / noise.trans_m)


def _camera_matrix(cam: np.ndarray) -> np.ndarray:
    """K (3, 3) from the camera parameter vector ``fx, fy, cx, cy, ...``."""
    return np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])


def _apply(R: np.ndarray, t: np.ndarray, v: np.ndarray, inverse: bool) -> np.ndarray:
    """``R v + t``, or ``Rᵀ (v - t)`` when ``inverse``; R (3, 3) or (m, 3, 3), v (m, 3)."""
    if inverse:
        return np.einsum("...ji,...j->...i", R, v - t)
    return np.einsum("...ij,...j->...i", R, v) + t


def _rows_times(G: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Stacked ``G @ M``, (m, 2, 3) by (3, 3) or (m, 3, 3) -> (m, 2, 3): one (2m, 3) product
    for a shared M, else one per row pair (both several times faster than ``einsum`` here)."""
    return (G.reshape(-1, 3) @ M).reshape(G.shape) if M.ndim == 2 else G @ M
