"""Intrinsic calibration with an unknown board aspect ratio ν (Strobl & Hirzinger, Method #1).

A printed checkerboard is the nominal grid scaled by κ, with an extra factor ν along x (eq. 4):
the true corner (i, j) lies at (κν i s, κ j s, 0) in the target frame (``docs/conventions.md``).
ν changes the board's *shape*, which the images see, so it is estimated together with the camera
in the bundle adjustment of eq. (5). κ only changes its *size*: a board κ times larger seen from
κ times farther projects to the same pixels, so κ trades exactly against the translations of the
N poses and the image-only problem is rank deficient in it. We fix κ = 1 here; every pose
``T_cam_target`` is therefore expressed in the *nominal-scale* target frame (true translations
are κ times those), and κ is estimated later against the robot's metric motion (eq. 6).

Pipeline: :func:`initial_intrinsics` (section III-A: homographies, reduced closed form with only
the orthogonality constraint, poses and ν from the homographies), then
:func:`calibrate_intrinsics` (eq. 5: Levenberg-Marquardt with an analytic Jacobian, the poses
eliminated by the Schur complement, ``calib.schur``: 5-9 evaluations and a 10 x 10 solve each,
where ``least_squares`` with its sparse ``lsmr`` solver took 9x the time; the covariance of the
camera parameters is marginalised over the poses the same way).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from calib import so3
from calib.boards import Board
from calib.camera import Pinhole
from calib.geometry import make_transform
from calib.lsq import CachedProblem
from calib.schur import solve_blocks
from calib.stations import MIN_IMAGES

#: Order of the camera parameters in :attr:`IntrinsicsResult.covariance`.
PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "nu")
#: Parameters that ``fix=`` may hold: the principal point at the image centre, distortion at 0.
FIXABLE = ("cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: The joint closed form's fx and fy are used when each is within this factor of the median
#: of the views' own focal lengths (``_median_focal``); else that median, for both. The joint
#: fit can rest on one view: with the principal point off the image centre (which the closed
#: form assumes) by (-24, +19) px, one view near a corner of the image took fx to 2.2x the
#: truth (no noise) or to a negative 1/fx² (0.1 px noise) on cold-start cell 13's 21 views,
#: where the median was 6 % off. The median is the start value the refinement needs, not more.
FOCAL_AGREE = 1.25
#: A view's own focal length counts in that median when ``|r31 r32|`` of its board rotation
#: (about ``|r1| |r2|`` projected on the image plane) exceeds this: a tilt of about 6° about
#: the board's diagonal.
SELF_TILT = 0.005
#: Fewest corners per image the calibration accepts (fewest images: ``MIN_IMAGES``).
MIN_POINTS = 4
#: Largest square size we accept as metres; anything beyond is almost surely millimetres.
MAX_SQUARE_M = 1.0

_N_CAM = len(PARAM_NAMES)
_NU = PARAM_NAMES.index("nu")


@dataclass(frozen=True)
class InitialIntrinsics:
    """Closed-form starting point of section III-A.

    Attributes
    ----------
    K : shape (3, 3)
        Camera matrix, principal point at the image centre, no skew.
    nu : float
        Median over images of ``|A⁻¹h1| / |A⁻¹h2|``.
    rvecs, tvecs : shape (N, 3)
        Per-image ``T_cam_target`` (κ = 1, the board scaled by ``nu`` in x).
    """

    K: np.ndarray
    nu: float
    rvecs: np.ndarray
    tvecs: np.ndarray


@dataclass(frozen=True)
class IntrinsicsResult:
    """Result of the eq. (5) bundle adjustment.

    Attributes
    ----------
    K : shape (3, 3)
    dist : shape (5,)
        ``[k1, k2, p1, p2, k3]``.
    nu : float
        Board aspect ratio: true corner (i, j) at (ν i s, j s, 0) times κ.
    rms_px : float
        RMS over all corners of the reprojection error norm, pixels.
    rms_px_per_image : shape (N,)
    residuals : tuple of N arrays, shape (N_i, 2)
        Observed minus predicted pixel coordinates.
    T_cam_target : shape (N, 4, 4)
        ``T_cam_target`` per image in the nominal-scale target frame (κ = 1).
    image_size : tuple[int, int]
        ``(width, height)``.
    covariance : shape (10, 10)
        Covariance of ``PARAM_NAMES`` marginalised over the poses, σ² (JᵀJ)⁻¹ with
        σ² = SSR / (m - n); rows and columns of fixed parameters are zero.
    sigmas : dict[str, float]
        Standard deviation per name in ``PARAM_NAMES`` (0 when fixed).
    pose_covariance : shape (N, 6, 6)
        Covariance of ``[rvec, tvec]`` of each ``T_cam_target`` (marginal, same σ²).
    sigma_px : float
        Residual standard deviation per coordinate, ``sqrt(SSR / (m - n))``.
    fixed : tuple[str, ...]
        Parameters held fixed (``nu`` when not estimated).
    n_points : int
        Number of corners used.
    nfev : int
        Residual evaluations of the optimiser.
    converged : bool
        False when ``max_nfev`` ran out before the optimiser's tolerances were met.
    """

    K: np.ndarray
    dist: np.ndarray
    nu: float
    rms_px: float
    rms_px_per_image: np.ndarray
    residuals: tuple[np.ndarray, ...]
    T_cam_target: np.ndarray
    image_size: tuple[int, int]
    covariance: np.ndarray
    sigmas: dict[str, float]
    pose_covariance: np.ndarray
    sigma_px: float
    fixed: tuple[str, ...]
    n_points: int
    nfev: int
    converged: bool


def initial_intrinsics(object_points_2d: Sequence[np.ndarray], image_points: Sequence[np.ndarray],
                       image_size: tuple[int, int]) -> InitialIntrinsics:
    """Closed-form K, ν and poses robust to an unknown ν (section III-A).

    Skew is 0 and the principal point at the image centre; only fx, fy are unknown and come
    from the orthogonality constraint ``h1ᵀ ω h2 = 0`` alone, which eq. (4) leaves untouched by
    ν and κ (the normalisation constraint would be biased by ν). Per image then
    ``r1 ∝ A⁻¹h1``, ``r2 ∝ A⁻¹h2``, ``t ∝ A⁻¹h3`` (κ = 1), R orthonormalised by SVD, and
    ν = median of ``|A⁻¹h1| / |A⁻¹h2|``. Where that joint fit of fx, fy disagrees with the
    median of the views' own focal lengths (``FOCAL_AGREE``), the median stands for both.
    Inputs are trusted (see :func:`calibrate_intrinsics`).

    Parameters
    ----------
    object_points_2d : sequence of N arrays, shape (N_i, 2)
        Nominal board coordinates in metres.
    image_points : sequence of N arrays, shape (N_i, 2)
        Detected corners in pixels (distortion is ignored here).
    image_size : (width, height)

    Returns
    -------
    InitialIntrinsics
    """
    cx, cy = (image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0
    # Homographies from the board to centred pixels, so that A = diag(fx, fy, 1).
    Hs = np.stack([_homography(o, np.asarray(m, float) - [cx, cy])
                   for o, m in zip(object_points_2d, image_points, strict=True)])
    h1, h2, h3 = Hs[:, :, 0], Hs[:, :, 1], Hs[:, :, 2]
    # h1ᵀ diag(1/fx², 1/fy², 1) h2 = 0, linear in (1/fx², 1/fy²); rows normalised to unit length.
    rows = np.stack([h1[:, 0] * h2[:, 0], h1[:, 1] * h2[:, 1], h1[:, 2] * h2[:, 2]], axis=1)
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    (a, b), *_ = np.linalg.lstsq(rows[:, :2], -rows[:, 2], rcond=None)
    single = _median_focal(h1, h2)
    if not (a > 0 and b > 0 and np.all(np.abs(np.log([a, b]) / 2 + np.log(single))
                                       < np.log(FOCAL_AGREE))):
        if not np.isfinite(single):
            raise ValueError(
                "initial intrinsics failed: the views do not constrain fx and fy "
                "(board orientations too similar or too fronto-parallel; tilt the board about "
                "different axes)")
        a = b = single ** -2.0
    fx, fy = 1.0 / np.sqrt(a), 1.0 / np.sqrt(b)
    A_inv = np.diag([1.0 / fx, 1.0 / fy, 1.0])
    a1, a2, a3 = h1 @ A_inv, h2 @ A_inv, h3 @ A_inv
    n1, n2 = np.linalg.norm(a1, axis=1), np.linalg.norm(a2, axis=1)
    nu = float(np.median(n1 / n2))
    # |a1| = λν and |a2| = λ for κ = 1; the sign puts the board in front of the camera.
    lam = np.sqrt(n1 * n2 / nu) * np.sign(a3[:, 2])
    r1 = a1 / (n1 * np.sign(a3[:, 2]))[:, None]
    r2 = a2 / (n2 * np.sign(a3[:, 2]))[:, None]
    U, _, Vt = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], axis=2))
    D = np.ones((len(Hs), 3))
    D[:, 2] = np.linalg.det(U @ Vt)
    R = (U * D[:, None, :]) @ Vt
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return InitialIntrinsics(K, nu, so3.log(R), a3 / lam[:, None])


def _median_focal(h1: np.ndarray, h2: np.ndarray) -> float:
    """The median over the views of each one's own focal length (fx = fy) from the
    orthogonality constraint ``(h11 h21 + h12 h22) / f² + h13 h23 = 0``, over the views that
    determine it (``SELF_TILT``) and give a positive 1/f²; nan when none does. ``h1``, ``h2``
    (n, 3): the homographies' first two columns, to centred pixels.

    ``h11 h21 + h12 h22 = -f² r31 r32`` (r the board's rotation): a board facing the camera, or
    turned about one of its own axes only, leaves f out of its constraint."""
    across = h1[:, 0] * h2[:, 0] + h1[:, 1] * h2[:, 1]
    tilt = np.abs(across) / (np.linalg.norm(h1[:, :2], axis=1) * np.linalg.norm(h2[:, :2], axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_f2 = -h1[:, 2] * h2[:, 2] / across
    ok = (tilt > SELF_TILT) & np.isfinite(inv_f2) & (inv_f2 > 0)
    return float(np.median(1.0 / np.sqrt(inv_f2[ok]))) if ok.any() else float("nan")


@dataclass(frozen=True)
class IntrinsicsOptions:
    """Options of :func:`calibrate_intrinsics`.

    ``estimate_nu``: estimate ν (Method #1); False gives the traditional calibration with ν
    held. ``nu``: start value of ν when estimated (default: from the homographies), the held
    value otherwise (default 1). ``fix``: names from ``FIXABLE`` to hold (``cx``, ``cy`` at the
    image centre, distortion terms at 0). ``max_nfev``: budget of residual evaluations.
    """

    estimate_nu: bool = True
    nu: float | None = None
    fix: tuple[str, ...] = ()
    max_nfev: int = 200


def calibrate_intrinsics(image_points: Sequence[np.ndarray], board: Board,
                         image_size: Sequence[int], options: IntrinsicsOptions | None = None, *,
                         point_ids: Sequence[np.ndarray] | None = None) -> IntrinsicsResult:
    """Calibrate K, distortion and the board aspect ratio ν from board corners (eq. 5).

    Minimises the reprojection error over fx, fy, cx, cy, k1, k2, p1, p2, k3, ν and a 6-vector
    pose per image, with the true corner (i, j) at (ν i s, j s, 0); κ = 1 (see module docstring).

    Parameters
    ----------
    image_points : sequence of N arrays, shape (N_i, 2) or (N_i, 1, 2)
        Detected corners in pixels, one array per image (N ≥ 3).
    board : the printed target (:class:`calib.boards.Board`), nominal geometry.
    image_size : (width, height)
        Pixels.
    options : :class:`IntrinsicsOptions` (default: estimate ν, nothing held).
    point_ids : sequence of N integer arrays, shape (N_i,), optional
        The board's point id of each corner, for partial detections. Without it every image
        must hold all the board's points in id order.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    ValueError
        On fewer than 3 images, too few or non-finite points, wrong shapes, bad ids, an invalid
        image size or square size, unknown ``fix`` names, or views that do not constrain K.
    """
    options = IntrinsicsOptions() if options is None else options
    width, height = _check_image_size(image_size)
    _check_square_size(board.square_size)
    grid = board.points()[:, :2]
    fixed = _check_fix(options.fix)
    pts, ids = _check_points(image_points, point_ids, len(grid), (width, height))
    nu, estimate_nu = options.nu, options.estimate_nu
    if nu is not None and not (np.isfinite(nu) and 0.5 < nu < 2.0):
        raise ValueError(f"nu must be a finite aspect ratio near 1, got {nu}")
    if not estimate_nu:
        fixed = (*fixed, "nu")

    obj = [grid[i] for i in ids]
    init = initial_intrinsics(obj, pts, (width, height))
    cam0 = np.zeros(_N_CAM)
    cam0[:4] = init.K[0, 0], init.K[1, 1], init.K[0, 2], init.K[1, 2]
    cam0[_NU] = init.nu if nu is None and estimate_nu else (1.0 if nu is None else nu)
    problem = IntrinsicsProblem(np.concatenate(obj), np.concatenate(pts), [len(p) for p in pts],
                       cam0, fixed)
    x0 = problem.pack(cam0, np.concatenate([init.rvecs, init.tvecs], axis=1))
    sol = solve_blocks(problem, x0, max_nfev=options.max_nfev, ftol=1e-12)
    return problem.result(sol.x, (width, height), int(sol.nfev), sol.status > 0)


class IntrinsicsProblem(CachedProblem):
    """Residuals and sparse Jacobian of eq. (5) over the free camera parameters and N poses.

    Observations are concatenated image by image; ``x = [free camera params, N x (rvec, tvec)]``.
    """

    def __init__(self, obj: np.ndarray, img: np.ndarray, counts: list[int], cam0: np.ndarray,
                 fixed: tuple[str, ...]) -> None:
        self.obj, self.img = obj, img
        self.counts = np.asarray(counts)
        self.starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.image = np.repeat(np.arange(len(counts)), counts)
        self.cam0 = cam0
        self.fixed = fixed
        self.free = np.array([n not in fixed for n in PARAM_NAMES])
        self.n_free = int(self.free.sum())
        self.shape = (2 * len(obj), self.n_free + 6 * len(counts))
        # for ``calib.schur.solve_blocks``: the camera is global, each image's pose a station
        self.n_free_global, self.n_stations = self.n_free, len(counts)
        self.prior_sigma = np.full(6, np.inf)  # no prior rows

    def pack(self, cam: np.ndarray, poses: np.ndarray) -> np.ndarray:
        return np.concatenate([cam[self.free], poses.ravel()])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cam = self.cam0.copy()
        cam[self.free] = x[:self.n_free]
        return cam, x[self.n_free:].reshape(-1, 6)

    def _compute(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted-minus-observed residuals (2M,) and dense blocks (M, 2, n_free + 6)."""
        cam, poses = self.unpack(x)
        K = np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])
        pts = np.column_stack([self.obj[:, 0] * cam[_NU], self.obj[:, 1], np.zeros(len(self.obj))])
        uv, J = Pinhole(K, cam[4:9]).project(pts, poses[:, :3], poses[:, 3:],
                                             pose_index=self.image, jacobian=True)
        d_nu = J.points[:, :, :1] * self.obj[:, None, :1]
        d_cam = np.concatenate([J.intrinsics, J.dist, d_nu], axis=2)[:, :, self.free]
        blocks = np.concatenate([d_cam, J.rvec, J.tvec], axis=2)
        r = (uv - self.img).ravel()
        return r, blocks

    def result(self, x: np.ndarray, image_size: tuple[int, int], nfev: int,
               converged: bool) -> IntrinsicsResult:
        r, blocks = self.evaluate(x)
        cam, poses = self.unpack(x)
        m, n = self.shape
        sigma2 = float(r @ r) / max(m - n, 1)
        cov_free, pose_cov = self._covariance(blocks, sigma2)
        cov = np.zeros((_N_CAM, _N_CAM))
        cov[np.ix_(self.free, self.free)] = cov_free
        sq = np.sum(r.reshape(-1, 2) ** 2, axis=1)
        per_image = np.sqrt(np.add.reduceat(sq, self.starts) / self.counts)
        residuals = tuple(np.split(-r.reshape(-1, 2), self.starts[1:]))
        K = np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])
        return IntrinsicsResult(
            K=K, dist=cam[4:9].copy(), nu=float(cam[_NU]), rms_px=float(np.sqrt(sq.mean())),
            rms_px_per_image=per_image, residuals=residuals,
            T_cam_target=make_transform(so3.exp(poses[:, :3]), poses[:, 3:]),
            image_size=image_size, covariance=cov,
            sigmas={k: float(np.sqrt(cov[i, i])) for i, k in enumerate(PARAM_NAMES)},
            pose_covariance=pose_cov, sigma_px=float(np.sqrt(sigma2)), fixed=self.fixed,
            n_points=len(self.obj), nfev=nfev, converged=converged)

    def _covariance(self, blocks: np.ndarray, sigma2: float) -> tuple[np.ndarray, np.ndarray]:
        """σ²(JᵀJ)⁻¹ for the camera block (Schur complement over poses) and per-pose blocks.

        With JᵀJ = [[U, W], [Wᵀ, V]] and V block diagonal (6x6 per image):
        S = U - Σ W_n V_n⁻¹ W_nᵀ, cov_cam = σ² S⁻¹ and
        cov_pose_n = σ² (V_n⁻¹ + V_n⁻¹ W_nᵀ S⁻¹ W_n V_n⁻¹).
        """
        f = self.n_free
        JtJ = np.add.reduceat(np.einsum("mki,mkj->mij", blocks, blocks), self.starts)
        U = JtJ[:, :f, :f].sum(axis=0)
        W = JtJ[:, :f, f:]
        V_inv = np.linalg.inv(JtJ[:, f:, f:])
        WV = W @ V_inv  # (N, f, 6)
        S_inv = np.linalg.inv(U - np.einsum("nij,nkj->ik", WV, W))
        pose_cov = V_inv + np.swapaxes(WV, 1, 2) @ S_inv @ WV
        return sigma2 * S_inv, sigma2 * pose_cov


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised DLT homography with ``dst ∝ H [src, 1]``, shapes (N, 2), (N, 2) -> (3, 3)."""
    Ts, Td = _normaliser(src), _normaliser(dst)
    s = src @ Ts[:2, :2].T + Ts[:2, 2]
    d = dst @ Td[:2, :2].T + Td[:2, 2]
    n = len(s)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:2], A[0::2, 2] = s, 1.0
    A[1::2, 3:5], A[1::2, 5] = s, 1.0
    A[0::2, 6:8] = -d[:, :1] * s
    A[0::2, 8] = -d[:, 0]
    A[1::2, 6:8] = -d[:, 1:] * s
    A[1::2, 8] = -d[:, 1]
    H = np.linalg.svd(A)[2][-1].reshape(3, 3)
    H = np.linalg.solve(Td, H @ Ts)
    return H / np.linalg.norm(H)


def _normaliser(p: np.ndarray) -> np.ndarray:
    """Similarity moving points (N, 2) to zero mean and mean distance √2, shape (3, 3)."""
    c = p.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.linalg.norm(p - c, axis=1).mean(), 1e-12)
    return np.array([[scale, 0.0, -scale * c[0]], [0.0, scale, -scale * c[1]], [0.0, 0.0, 1.0]])


def _check_image_size(image_size: Sequence[int]) -> tuple[int, int]:
    size = np.asarray(image_size)
    if size.shape != (2,) or not np.all(np.isfinite(size)) or np.any(size != np.round(size)) \
            or np.any(size < 2):
        raise ValueError(f"image_size must be (width, height) in whole pixels, got {image_size!r}")
    return int(size[0]), int(size[1])


def _check_square_size(square_size: float) -> float:
    s = float(square_size)
    if not (np.isfinite(s) and 0.0 < s <= MAX_SQUARE_M):
        raise ValueError(
            f"square_size must be in metres, 0 < s <= {MAX_SQUARE_M:g}, got {square_size!r} "
            "(was it given in millimetres?)")
    return s


def _check_fix(fix: Iterable[str]) -> tuple[str, ...]:
    fixed = tuple(fix)
    unknown = [f for f in fixed if f not in FIXABLE]
    if unknown:
        raise ValueError(f"fix: unknown or unfixable parameters {unknown}; choose from {FIXABLE}")
    return fixed


def _check_points(image_points: Sequence[np.ndarray], point_ids: Sequence[np.ndarray] | None,
                  n_grid: int, image_size: tuple[int, int]
                  ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Validate the corners and ids; return lists of (N_i, 2) float and (N_i,) int arrays."""
    if len(image_points) < MIN_IMAGES:
        raise ValueError(f"need at least {MIN_IMAGES} images, got {len(image_points)}")
    if point_ids is not None and len(point_ids) != len(image_points):
        raise ValueError(f"point_ids has {len(point_ids)} entries for {len(image_points)} images")
    pts, ids = [], []
    for k, p in enumerate(image_points):
        p = _check_image_points(k, p, image_size)
        pts.append(p)
        ids.append(_check_point_ids(k, None if point_ids is None else point_ids[k], len(p),
                                    n_grid))
    return pts, ids


def _check_image_points(k: int, points: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Image ``k``'s corners as float (N, 2), or ``ValueError`` saying what is wrong."""
    p = np.asarray(points, dtype=float)
    if p.ndim == 3 and p.shape[1] == 1:
        p = p[:, 0]
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"image_points[{k}]: expected shape (N, 2), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"image_points[{k}] contains NaN or inf")
    if len(p) < MIN_POINTS:
        raise ValueError(f"image_points[{k}] has {len(p)} corners; need at least {MIN_POINTS}")
    outside = (p < -0.5).any(axis=1) | (p[:, 0] > image_size[0] - 0.5) \
        | (p[:, 1] > image_size[1] - 0.5)
    if outside.any():
        raise ValueError(
            f"image_points[{k}] has corners outside the {image_size[0]}x{image_size[1]} "
            "image (is image_size (width, height)?)")
    return p


def _check_point_ids(k: int, point_ids: np.ndarray | None, n_points: int,
                     n_grid: int) -> np.ndarray:
    """Image ``k``'s grid indices (N,) int: the full grid when ``point_ids`` is None."""
    if point_ids is None:
        if n_points != n_grid:
            raise ValueError(
                f"image_points[{k}] has {n_points} corners but the board has {n_grid}; "
                "pass point_ids for partial detections")
        return np.arange(n_grid)
    i = np.asarray(point_ids)
    if i.shape != (n_points,) or not np.issubdtype(i.dtype, np.integer):
        raise ValueError(f"point_ids[{k}]: expected {n_points} integers, got {i.shape}")
    if i.min() < 0 or i.max() >= n_grid or len(np.unique(i)) != len(i):
        raise ValueError(f"point_ids[{k}] must be distinct grid indices in [0, {n_grid})")
    return i
