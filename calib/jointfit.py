"""Warm-started fits of the joint model: one estimator configuration, any subset of stations.

Cross-validation (``calib.crossval``) and model selection (``calib.selection``) refit the joint
maximum-likelihood model (``calib.joint``) many times: on the stations of each fold, and with
κ, ν held at 1 or the robot noise levels estimated. Each fit starts from a nearby solution
(the full one) and runs the block-eliminating solver of ``calib.schur``, so it converges in a
few cheap iterations to the minimum ``solve_joint`` would reach.

Noise levels estimated from the data (``JointModel.estimate_noise``) are variance components
(Förstner 1979; Koch, *Parameter estimation and hypothesis testing in linear models*, 3.6):
each group of residuals — corners, robot rotation priors, robot translation priors — gets the
σ that makes its squared normalised residuals equal their redundancy, by a few re-solves.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.chain import RobotNoise
from calib.foldspread import expected_jackknife
from calib.joint import (
    GLOBAL_PARAMS,
    CellParameters,
    CornerStations,
    JointOptions,
    JointProblem,
    JointResult,
    sigmas_from_covariance,
)
from calib.schur import BlockSolution, prior_redundancy, solve_blocks

#: Re-solves of the variance-component estimation; it stops earlier once the σ settle.
NOISE_ROUNDS = 4
#: The σ are settled when every variance factor is within this of 1.
NOISE_TOLERANCE = 0.05
#: Smallest noise levels a fit assumes (px, rad, m): keeps a collapsing group finite.
MIN_NOISE = (1e-6, np.deg2rad(1e-4), 1e-7)


@dataclass(frozen=True)
class JointModel:
    """One joint estimator: the parameters it holds at their start and the noise it assumes.

    ``fix`` names from ``calib.joint.FIXABLE``, held at their start values; ``noise`` the
    assumed robot reading noise (the prior), re-estimated from the data when
    ``estimate_noise``; ``robot_map`` estimates the linear map of the robot's translations
    (``calib.joint``), else the readings are taken as they are.
    """

    name: str
    fix: tuple[str, ...]
    noise: RobotNoise
    estimate_noise: bool = False
    robot_map: bool = False


@dataclass(frozen=True)
class JointData:
    """The measurements of a joint fit: full-grid corners and readings, the setup, and the
    corner noise ``sigma_px`` (pixels per coordinate)."""

    stations: CornerStations
    setup: str
    sigma_px: float

    def subset(self, indices: Sequence[int]) -> JointData:
        return replace(self, stations=self.stations.subset(indices))

    def __len__(self) -> int:
        return len(self.stations.image_points)


def held_at_one(cell: CellParameters, names: Sequence[str]) -> CellParameters:
    """``cell`` with κ and/or ν (``names``) set to exactly 1."""
    return replace(cell, **{name: 1.0 for name in names})


@dataclass(frozen=True)
class JointFit:
    """A converged fit: its parameters, the noise levels it ended with, and its problem."""

    cell: CellParameters
    sigma_px: float
    noise: RobotNoise
    solution: BlockSolution
    problem: JointProblem

    @property
    def corrections(self) -> np.ndarray:
        """The fitted robot corrections δ (n, 6)."""
        return self.solution.x[self.problem.n_free_global:].reshape(-1, 6)

    def result(self, stations: np.ndarray, rejected: tuple[tuple[int, str], ...] = (), *,
               noise: tuple[float, float, float] | None = None) -> JointResult:
        """The fit as ``calib.joint.JointResult`` (covariance, sigmas, corrections).

        The covariance is the sandwich ``H⁻¹ Jᵀ F J H⁻¹`` (``H = JᵀJ`` of the normalised
        residuals, ``F`` each residual group's variance factor from the variance-component
        estimate): the spread of *this* estimator when the noise is what the data show, not
        what was assumed. Assumed levels that are off weight the groups wrongly, which one
        global variance factor cannot correct. ``noise`` (σ_px, σ_rot, σ_trans), e.g. those of
        a converged fit with ``estimate_noise``, gives the factors directly; without it they
        are estimated in one step at this fit's weights.
        """
        res = self.problem.result(self.solution, stations, rejected)
        try:
            free_cov = _sandwich(self.problem, self.solution.x, self.factors(noise))
        except np.linalg.LinAlgError:
            return res
        cov = np.zeros((len(GLOBAL_PARAMS), len(GLOBAL_PARAMS)))
        free = self.problem.free
        cov[np.ix_(free, free)] = free_cov
        return replace(res, covariance=cov, sigmas=sigmas_from_covariance(cov))


    def factors(self, noise: tuple[float, float, float] | None = None
                ) -> tuple[float, float, float]:
        """Variance factors of the corner, robot-rotation and robot-translation residuals:
        those of the noise levels ``noise`` (σ_px, σ_rot, σ_trans) against the weights of
        this fit's problem, else estimated in one step at those weights
        (``variance_factors``). A fit that estimated its noise weighted its last solve with
        the levels before their last update, not with ``sigma_px`` and ``noise``."""
        if noise is None:
            return variance_factors(self.problem, self.solution.x)
        weights = self.problem
        return ((noise[0] / weights.sigma_px) ** 2, (noise[1] / weights.noise.rot_rad) ** 2,
                (noise[2] / weights.noise.trans_m) ** 2)

    def expected_jackknife(self, folds: Sequence[np.ndarray], *,
                           noise: tuple[float, float, float] | None = None
                           ) -> dict[str, float | np.ndarray]:
        """The fold jackknife's σ this fit's noise model predicts for ``folds`` (held-out
        station indices), at the variance factors of :meth:`result` with the same ``noise``
        (``calib.foldspread``)."""
        return expected_jackknife(self.problem, self.solution.x, folds, self.factors(noise))


def fit_joint(data: JointData, model: JointModel, start: CellParameters, *,
              corrections: np.ndarray | None = None, max_nfev: int = 40) -> JointFit:
    """Fit ``model`` to ``data`` from ``start``; parameters in ``model.fix`` keep their start.

    ``corrections`` (n, 6) start the robot corrections δ, e.g. at those of a fit on more
    stations; else they start at zero. From there the minimum is the same and is reached in
    about 5 evaluations instead of 8 (a fold of 18 rendered stations), for from zero the
    first steps only undo the robot's errors again.
    """
    cell = start if model.robot_map else replace(start, robot_map=None)
    sigmas = [data.sigma_px, model.noise.rot_rad, model.noise.trans_m]
    grids = data.stations.grids()
    delta = None if corrections is None else np.asarray(corrections, dtype=float)
    for _ in range(NOISE_ROUNDS if model.estimate_noise else 1):
        options = JointOptions(sigma_px=sigmas[0], setup=data.setup,
                               noise=RobotNoise(sigmas[1], sigmas[2]), fix=model.fix,
                               outlier_sigma=None, robot_map=model.robot_map)
        problem = JointProblem(grids, list(data.stations.image_points),
                               data.stations.T_base_tcp, cell, options)
        x0 = problem.x0()
        if delta is not None:  # each noise round starts where the last one ended
            x0[problem.n_free_global:] = delta.ravel()
        sol = solve_blocks(problem, x0, max_nfev=max_nfev)
        cell, delta = problem.unpack(sol.x)
        if not model.estimate_noise:
            break
        factors = variance_factors(problem, sol.x)
        sigmas = [max(s * float(np.sqrt(f)), lo)
                  for s, f, lo in zip(sigmas, factors, MIN_NOISE, strict=True)]
        if np.all(np.abs(np.asarray(factors) - 1.0) < NOISE_TOLERANCE):
            break
    return JointFit(cell=cell, sigma_px=sigmas[0], noise=RobotNoise(sigmas[1], sigmas[2]),
                    solution=sol, problem=problem)


def variance_factors(problem: JointProblem, x: np.ndarray) -> tuple[float, float, float]:
    """Squared normalised residuals over redundancy: corners, robot rotation, translation."""
    r, _ = problem.evaluate(x)
    rows, n_par = problem.shape
    n = problem.n_stations
    prior = r[rows - 6 * n:].reshape(n, 6)
    corner = r[:rows - 6 * n]
    red_rot, red_trans = prior_redundancy(problem, x)
    red_corner = max(rows - n_par - red_rot - red_trans, 1.0)
    return (float(corner @ corner) / red_corner,
            float(np.sum(prior[:, :3] ** 2)) / max(red_rot, 1e-3),
            float(np.sum(prior[:, 3:] ** 2)) / max(red_trans, 1e-3))


def _sandwich(problem: JointProblem, x: np.ndarray,
              factors: tuple[float, float, float]) -> np.ndarray:
    """Covariance of the free globals under the group variance factors (``JointFit.result``)."""
    f_corner, f_rot, f_trans = factors
    J = problem.jacobian(x)
    H = (J.T @ J).toarray()
    g = problem.n_free_global
    A = J @ np.linalg.solve(H, np.eye(H.shape[0])[:, :g])  # rows x g
    n = problem.n_stations
    w = np.concatenate([np.full(J.shape[0] - 6 * n, f_corner),
                        np.tile([f_rot] * 3 + [f_trans] * 3, n)])
    return A.T @ (A * w[:, None])
