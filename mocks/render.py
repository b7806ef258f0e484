"""Synthetic camera images of the checkerboard or ChArUco board, geometrically exact and
anti-aliased.

Each output pixel is split into ``supersample``² sub-pixel samples (default 1). A sample's
pixel position is undistorted to a normalized camera ray (exactly on a coarse grid with OpenCV,
then a cubic spline; the result depends only on the camera and is cached), the ray is
intersected with the board plane (a homography from normalized coordinates to board grid
units), and the square colour is evaluated with an analytic box filter over the sample's
footprint: a linear ramp across each square edge, the product of the two axes' ramps near a
corner. Averaging the samples gives each pixel's area coverage. The ramps are exact for edges
and approximate only in the pixel that holds a corner, symmetrically, so corner positions are
unbiased; ``supersample=2`` makes those pixels exact too at 4x the cost. Pixel centres are at
integer coordinates (OpenCV), so pixel (u, v) covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5].

The board is the *true* geometry: corner (i, j) at (κν i s, κ j s, 0) in the target frame,
square (a, b) (a = 0..cols, b = 0..rows, square (0, 0) diagonally outside corner (0, 0)) black
when a + b is even, on a white plate with ``margin_squares`` of border, over a grey background.
A ChArUco board (``markers``) is the checkerboard of its inner corners with OpenCV's ArUco
markers in the white squares (``mocks.markers``), box-filtered the same way; its corner id k is
checkerboard corner k, so ``MockScene.true_board_points()[ids]`` are the true corners.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline

from mocks.markers import MarkerLayout, marker_coverage
from mocks.scene import CharucoTarget, MockScene

#: Pixel spacing of the grid on which rays are undistorted exactly before spline interpolation.
_RAY_GRID_STEP = 8


@dataclass(frozen=True)
class RenderParams:
    """Everything :func:`render_board` needs; build from a scene with :meth:`from_scene`."""

    image_size: tuple[int, int]
    K: tuple[float, ...]
    dist: tuple[float, ...]
    inner_corners: tuple[int, int]
    square_size: float
    kappa: float = 1.0
    nu: float = 1.0
    blur_px: float = 0.0
    image_noise: float = 0.0
    seed: int = 0
    margin_squares: float = 1.5
    black: float = 25.0
    white: float = 225.0
    background: float = 110.0
    supersample: int = 1
    markers: MarkerLayout | None = None

    @classmethod
    def from_scene(cls, scene: MockScene, **overrides: object) -> RenderParams:
        """Parameters of ``scene``'s camera, true board and image noise; ``overrides`` win."""
        t = scene.target
        fields: dict[str, object] = {
            "image_size": tuple(scene.camera.image_size),
            "K": tuple(scene.camera.k_matrix.ravel()),
            "dist": tuple(scene.camera.dist),
            "inner_corners": tuple(scene.target.inner_corners),
            "square_size": scene.target.square_size_m,
            "kappa": scene.target.kappa,
            "nu": scene.target.nu,
            "blur_px": scene.noise.blur_px,
            "image_noise": scene.noise.image_noise,
            "seed": scene.seed,
            "markers": MarkerLayout(tuple(t.squares), t.marker_size_m / t.square_size_m,
                                    t.dictionary, t.legacy_pattern)
            if isinstance(t, CharucoTarget) else None,
        }
        fields.update(overrides)
        return cls(**fields)  # type: ignore[arg-type]


def render_board(scene_or_params: MockScene | RenderParams, T_cam_target: np.ndarray, *,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """Grey image of the board seen from pose ``T_cam_target``, shape (H, W) uint8.

    Blur (Gaussian, sigma ``blur_px``) and sensor noise (Gaussian, sigma ``image_noise`` grey
    levels) are applied last; noise comes from ``rng`` or, if None, a generator seeded with
    the scene seed (the same noise in every call).
    """
    p = (scene_or_params if isinstance(scene_or_params, RenderParams)
         else RenderParams.from_scene(scene_or_params))
    T = np.asarray(T_cam_target, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"T_cam_target must be a finite 4x4 transform, got shape {T.shape}")
    w, h = p.image_size
    ss = p.supersample
    x, y = _sample_rays(p.K, p.dist, w, h, ss)
    img = _shade(p, _grid_from_rays(p, T), x, y)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if ss > 1 else img
    if p.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), p.blur_px, borderType=cv2.BORDER_REFLECT)
    if p.image_noise > 0:
        rng = np.random.default_rng(p.seed) if rng is None else rng
        img += p.image_noise * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _grid_from_rays(p: RenderParams, T_cam_target: np.ndarray) -> np.ndarray:
    """Homography from normalized rays (x, y, 1) to board grid units (gx, gy, 1), (3, 3).

    A ray hits the board where (x, y, 1) ∝ [r1 r2 t] (X, Y, 1); grid units divide X by κνs
    and Y by κs so that true corner (i, j) is at (i, j). The third output component is
    1 / depth: positive only for points in front of the camera.
    """
    M = T_cam_target[:3, [0, 1, 3]]
    scale = np.diag([1.0 / (p.kappa * p.nu * p.square_size), 1.0 / (p.kappa * p.square_size),
                     1.0])
    return scale @ np.linalg.inv(M)


def _shade(p: RenderParams, G: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Box-filtered intensity at every sample, shape of ``x`` (float32).

    Rays that miss the board plane in front of the camera become NaN, then background.
    """
    G = G.astype(np.float32)
    cols, rows = p.inner_corners
    m = p.margin_squares
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = G[2, 0] * x + G[2, 1] * y + G[2, 2]
        inv[inv <= 0] = np.nan
        np.reciprocal(inv, out=inv)
        gx = G[0, 0] * x + G[0, 1] * y + G[0, 2]
        gx *= inv
        gy = G[1, 0] * x + G[1, 1] * y + G[1, 2]
        gy *= inv
        fx = _footprint(gx)
        fy = _footprint(gy)
        plate = _box(gx, -1.0 - m, cols + m, fx)
        plate *= _box(gy, -1.0 - m, rows + m, fy)
        black = _box(gx, -1.0, cols, fx)
        black *= _box(gy, -1.0, rows, fy)
        wave = _square_wave(gx, fx)
        wave *= _square_wave(gy, fy)
        if p.markers is not None and p.markers.swapped_colours:
            np.negative(wave, out=wave)
        wave += 1.0
        black *= wave
        if p.markers is not None:
            black += 2.0 * marker_coverage(p.markers, gx, gy, fx, fy)
        black *= 0.5 * (p.white - p.black)
        plate *= p.white - p.background
        plate += p.background
        plate -= black
    return np.nan_to_num(plate, copy=False, nan=p.background)


def _footprint(g: np.ndarray) -> np.ndarray:
    """Extent of one sample along grid coordinate ``g``: |dg/du| + |dg/dv| (grid units)."""
    du, dv = np.gradient(g)
    np.abs(du, out=du)
    np.abs(dv, out=dv)
    du += dv
    du += np.float32(1e-6)
    return du


def _box(g: np.ndarray, lo: float, hi: float, width: np.ndarray) -> np.ndarray:
    """Fraction of a footprint of ``width`` centred at ``g`` that lies in [lo, hi]."""
    d = np.minimum(g - lo, hi - g)
    d /= width
    d += 0.5
    return np.clip(d, 0.0, 1.0, out=d)


def _square_wave(g: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Box-filtered square wave: +1 where floor(g) is even, -1 where odd, ramps at integers.

    With w = (g + 1/2) mod 2, the signed distance to the nearest integer is 1/2 - |w - 1|
    (positive on even cells); the box filter turns it into a clipped ramp.
    """
    w = g + 0.5
    w -= 2.0 * np.floor(w * 0.5)
    w -= 1.0
    np.abs(w, out=w)
    np.subtract(0.5, w, out=w)
    w *= 2.0
    w /= width
    return np.clip(w, -1.0, 1.0, out=w)


@lru_cache(maxsize=4)
def _sample_rays(K: tuple[float, ...], dist: tuple[float, ...], w: int, h: int,
                 ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalized undistorted rays (x, y) of all sub-pixel samples, each shape (h*ss, w*ss).

    Sample k of pixel u sits at u - 0.5 + (k + 0.5) / ss. Rays are undistorted exactly
    (iterated to 1e-12) on a grid every ``_RAY_GRID_STEP`` pixels and interpolated with a
    bicubic spline; the spline error is far below 1e-3 px for realistic lens distortion.
    """
    step = _RAY_GRID_STEP
    gu = np.arange(-step, w + 2 * step, step, dtype=float)
    gv = np.arange(-step, h + 2 * step, step, dtype=float)
    uu, vv = np.meshgrid(gu, gv)
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1)[:, None, :]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rays = cv2.undistortPointsIter(pts, np.asarray(K).reshape(3, 3), np.asarray(dist), None,
                                   None, criteria).reshape(len(gv), len(gu), 2)
    su = np.arange(w * ss) / ss - 0.5 + 0.5 / ss
    sv = np.arange(h * ss) / ss - 0.5 + 0.5 / ss
    x = RectBivariateSpline(gv, gu, rays[..., 0])(sv, su).astype(np.float32)
    y = RectBivariateSpline(gv, gu, rays[..., 1])(sv, su).astype(np.float32)
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y
