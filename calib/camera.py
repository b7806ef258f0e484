"""OpenCV pinhole camera with ``[k1, k2, p1, p2, k3]`` distortion and analytic Jacobians.

Conventions are in ``docs/conventions.md``: ``K`` is 3x3 (no skew), ``dist = [k1, k2, p1, p2, k3]``,
the camera frame is x right, y down, z along the optical axis. A point ``p`` in the target frame
goes to the camera frame as ``R(rvec) @ p + tvec``, i.e. ``(rvec, tvec)`` is ``T_cam_target``.
The distortion is the undistorted-to-distorted model of Strobl & Hirzinger, footnote 8 (as in
OpenCV), applied to normalised coordinates ``x = X/Z, y = Y/Z``::

    r² = x² + y²,  radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x_d = x radial + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy

``project`` is vectorised over points *and* poses (``pose_index`` maps points to poses), so a
bundle adjustment projects every observation of every image in one call.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib import so3
from calib.geometry import make_transform


@dataclass(frozen=True)
class ProjectionJacobian:
    """Derivatives of the pixel coordinates ``(u, v)`` of each of N points.

    Attributes
    ----------
    intrinsics : shape (N, 2, 4)
        w.r.t. ``fx, fy, cx, cy``.
    dist : shape (N, 2, 5)
        w.r.t. ``k1, k2, p1, p2, k3``.
    rvec, tvec : shape (N, 2, 3)
        w.r.t. the pose; zero when ``project`` was called without a pose.
    points : shape (N, 2, 3)
        w.r.t. the 3D point in the frame it was given in (target, or camera without a pose).
    """

    intrinsics: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class Pinhole:
    """The camera model of the module docstring.

    ``K`` (3, 3) is ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (a skew entry is ignored),
    ``dist`` (5,) is ``[k1, k2, p1, p2, k3]``.
    """

    K: np.ndarray
    dist: np.ndarray

    def project(self, points: np.ndarray, rvec: np.ndarray | None = None,
                tvec: np.ndarray | None = None, *, pose_index: np.ndarray | None = None,
                jacobian: bool = False) -> np.ndarray | tuple[np.ndarray, ProjectionJacobian]:
        """Project 3D points to distorted pixel coordinates (eq. 1 with U-D distortion).

        Parameters
        ----------
        points : shape (N, 3)
            Points in the target frame, or in the camera frame when ``rvec`` and ``tvec`` are None.
        rvec, tvec : shape (3,) or (P, 3), optional
            Pose(s) ``T_cam_target`` as rotation vector and translation (metres). Both or neither.
        pose_index : shape (N,), optional
            Index into the P poses for each point; required when P poses are given.
        jacobian : bool
            Also return the analytic :class:`ProjectionJacobian`.

        Returns
        -------
        uv : shape (N, 2)
            Pixel coordinates.
        jac : ProjectionJacobian
            Only when ``jacobian`` is true.
        """
        P = np.asarray(points, dtype=float).reshape(-1, 3)
        n = P.shape[0]
        if (rvec is None) != (tvec is None):
            raise ValueError("project: give both rvec and tvec, or neither")
        K = self.K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        k1, k2, p1, p2, k3 = np.asarray(self.dist, dtype=float)

        if rvec is None:
            Pc = P
        else:
            rvec = np.asarray(rvec, dtype=float).reshape(-1, 3)
            tvec = np.asarray(tvec, dtype=float).reshape(-1, 3)
            if pose_index is None:
                if len(rvec) != 1:
                    raise ValueError("project: pose_index is required with several poses")
                pose_index = np.zeros(n, dtype=int)
            R = so3.exp(rvec)[pose_index]  # (N, 3, 3)
            RP = _matmul_vec(R, P)
            Pc = RP + tvec[pose_index]

        iz = 1.0 / Pc[:, 2]
        x = Pc[:, 0] * iz
        y = Pc[:, 1] * iz
        xx, yy, xy = x * x, y * y, x * y
        r2 = xx + yy
        r4 = r2 * r2
        r6 = r4 * r2
        radial = 1.0 + k1 * r2 + k2 * r4 + k3 * r6
        xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
        yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
        uv = np.empty((n, 2))
        uv[:, 0] = fx * xd + cx
        uv[:, 1] = fy * yd + cy
        if not jacobian:
            return uv

        d_intr = np.zeros((n, 2, 4))
        d_intr[:, 0, 0] = xd
        d_intr[:, 1, 1] = yd
        d_intr[:, 0, 2] = d_intr[:, 1, 3] = 1.0
        d_dist = np.empty((n, 2, 5))
        d_dist[:, 0] = np.column_stack([x * r2, x * r4, 2.0 * xy, r2 + 2.0 * xx, x * r6]) * fx
        d_dist[:, 1] = np.column_stack([y * r2, y * r4, r2 + 2.0 * yy, 2.0 * xy, y * r6]) * fy

        # d uv / d Pc = d uv/d(x_d, y_d) . d(x_d, y_d)/d(x, y) . d(x, y)/d(X, Y, Z)
        drad = 2.0 * (k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4)  # d radial / d x = drad * x
        cross = drad * xy + 2.0 * p1 * x + 2.0 * p2 * y
        a = ((fx * (radial + drad * xx + 2.0 * p1 * y + 6.0 * p2 * x), fx * cross),
             (fy * cross, fy * (radial + drad * yy + 6.0 * p1 * y + 2.0 * p2 * x)))
        d_cam = np.empty((n, 2, 3))
        for k in range(2):
            d_cam[:, k, 0] = a[k][0] * iz
            d_cam[:, k, 1] = a[k][1] * iz
            d_cam[:, k, 2] = -(a[k][0] * x + a[k][1] * y) * iz

        if rvec is None:
            empty = np.zeros((n, 2, 3))
            return uv, ProjectionJacobian(d_intr, d_dist, empty, empty, d_cam)
        # d(R p)/d rvec = -[R p]x J_l(rvec), J_l the left Jacobian of SO(3); g [v]x = g x v.
        d_rvec = _matmul_rows(np.cross(RP[:, None, :], d_cam), so3.left_jacobian(rvec)[pose_index])
        return uv, ProjectionJacobian(d_intr, d_dist, d_rvec, d_cam, _matmul_rows(d_cam, R))


def solve_pnp(points_target: np.ndarray, image_points: np.ndarray, K: np.ndarray,
              dist: np.ndarray | None = None, *, guess: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose from known target points by ``cv2.solvePnP`` (iterative, Levenberg-Marquardt).

    Parameters
    ----------
    points_target : shape (N, 3), target frame, metres.
    image_points : shape (N, 2), the same points detected in the image, pixels.
    K : shape (3, 3); dist : shape (5,) or None (no distortion).
    guess : shape (4, 4), optional T_cam_target to start from (else OpenCV's own start).

    Returns
    -------
    T_cam_target : shape (4, 4)
    residuals : shape (N, 2), projected minus detected pixels.

    Raises
    ------
    ValueError
        When OpenCV finds no pose (too few or degenerate points, wrong K).
    """
    obj = np.asarray(points_target, dtype=float).reshape(-1, 3)
    img = np.asarray(image_points, dtype=float).reshape(-1, 2)
    K = np.asarray(K, dtype=float)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=float)
    if guess is None:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, so3.log(guess[:3, :3]).copy(),
                                      np.array(guess[:3, 3], dtype=float),
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError(f"solvePnP found no camera pose from {len(obj)} points: are K, dist "
                         "and the board right?")
    T_cam_target = make_transform(so3.exp(rvec.ravel()), tvec.ravel())
    return T_cam_target, Pinhole(K, dist).project(obj, rvec.ravel(), tvec.ravel()) - img


def image_corner_error(estimate: Pinhole, truth: Pinhole, image_size: tuple[int, int]) -> float:
    """Largest pixel error of ``estimate`` at the four image corners: the rays that ``truth``
    sees at those pixels, projected by ``estimate``. The image corners are where distortion
    is largest and whole-board views leave it least constrained."""
    w, h = image_size
    uv = np.array([[0.0, 0.0], [w - 1, 0.0], [0.0, h - 1], [w - 1, h - 1]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    xy = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), truth.K, truth.dist, None, None,
                                 criteria).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(4)])
    return float(np.linalg.norm(estimate.project(rays) - uv, axis=1).max())


def _matmul_vec(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Stacked ``M @ v``, shapes (N, 3, 3), (N, 3) -> (N, 3)."""
    return M[:, :, 0] * v[:, None, 0] + M[:, :, 1] * v[:, None, 1] + M[:, :, 2] * v[:, None, 2]


def _matmul_rows(G: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Stacked ``G @ M``, shapes (N, 2, 3), (N, 3, 3) -> (N, 2, 3)."""
    return (G[:, :, 0, None] * M[:, None, 0] + G[:, :, 1, None] * M[:, None, 1]
            + G[:, :, 2, None] * M[:, None, 2])
