"""Cramér-Rao lower bound of the joint measurement model (``calib.joint``), for benchmarks.

The bound is the inverse Fisher information ``(JᵀJ)⁻¹`` of the normalised residuals of
:class:`calib.joint.JointProblem` at the true parameters: every corner with σ_px per coordinate
and every robot reading with its noise prior, the station corrections eliminated by the same
Schur complement as the joint estimate's covariance. No unbiased estimator of that model can
do better, so a benchmark compares the reported σ and the actual errors against it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calib.boards import Board
from calib.joint import CAMERA_PARAMS, CellParameters, CornerStations, JointOptions, JointProblem

#: Offsets of the 3x3 blocks of X and Y in ``calib.joint.GLOBAL_PARAMS``.
_BLOCKS = (("hand_eye_rot", 11), ("hand_eye_trans", 14), ("target_pose_rot", 17),
           ("target_pose_trans", 20))


def cramer_rao_bound(T_base_tcp: np.ndarray, board: Board, truth: CellParameters,
                     options: JointOptions, point_ids: Sequence[np.ndarray] | None = None
                     ) -> dict[str, float | np.ndarray]:
    """Cramér-Rao bound with the board's points ``point_ids`` (default: all) seen at every
    true robot pose T_base_tcp (n, 4, 4).

    ``options`` gives the setup, σ_px, the robot noise and the fixed parameters (its outlier
    and budget fields are not used). Returns the covariance (23, 23) over
    ``calib.joint.GLOBAL_PARAMS`` as ``covariance``, its 3x3 blocks ``hand_eye_rot``,
    ``hand_eye_trans``, ``target_pose_rot``, ``target_pose_trans``, and the standard deviation
    of each name in ``CAMERA_PARAMS``.
    """
    grids = CornerStations([None] * len(T_base_tcp), T_base_tcp, board, point_ids).grids()
    # the Jacobian does not depend on the observations: placeholders suffice
    problem = JointProblem(grids, [np.zeros_like(g) for g in grids],
                           np.asarray(T_base_tcp, dtype=float), truth, options)
    cov = problem.covariance(problem.x0(), 1.0)
    bound: dict[str, float | np.ndarray] = {
        name: float(np.sqrt(cov[i, i])) for i, name in enumerate(CAMERA_PARAMS)}
    for name, start in _BLOCKS:
        bound[name] = cov[start:start + 3, start:start + 3]
    bound["covariance"] = cov
    return bound
