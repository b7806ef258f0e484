"""Levenberg-Marquardt for the joint problem with the station blocks eliminated (Schur complement).

The joint problem (``calib.joint``) has 23 global unknowns and 6 per station; every corner row
touches the globals and its own station only, every prior row one station parameter. Its
normal equations are therefore an arrow matrix::

    [ U    W ] [dg]   [b_g]        U: globals (g x g), W_i: globals x station i (g x 6),
    [ Wᵀ   V ] [dv] = [b_v]        V = diag(V_1 .. V_n), each 6 x 6

and the globals follow from the reduced system ``(U - Σ W_i V_i⁻¹ W_iᵀ) dg = b_g - Σ W_i V_i⁻¹
b_vi`` (bundle adjustment's classical elimination; Triggs et al., "Bundle adjustment — a modern
synthesis", section 6.1). Each iteration costs one residual/Jacobian evaluation and a g x g
solve, where ``scipy.optimize.least_squares`` with its iterative ``lsmr`` trust-region solver
needs hundreds of sparse products. Cross-validation and model selection solve the joint
problem many times from a nearby start, so this is what makes them cheap enough to run on
every calibration. The minimum is that of :func:`calib.joint.solve_joint` (same residuals).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import Protocol

import numpy as np

from calib.levmar import inverse_scaled, levenberg_marquardt, solve_scaled


class BlockProblem(Protocol):
    """What the solver needs of a problem (``calib.joint.JointProblem``,
    ``calib.intrinsics.IntrinsicsProblem``).

    ``evaluate(x)`` returns the normalised residuals (2m + 6n,) — corner rows first, station
    by station, then 6 prior rows per station — and the corner Jacobian blocks (m, 2, g + 6):
    the free globals, then the corner's station parameters. Prior rows are ``δ / prior_sigma``;
    a problem without them (the intrinsics: camera globals, a pose per image) gives
    ``prior_sigma`` inf and the corner rows alone.
    """

    n_free_global: int
    n_stations: int
    starts: np.ndarray  # shape (n,), first corner of each station
    prior_sigma: np.ndarray  # shape (6,)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class BlockSolution:
    """Result of :func:`solve_blocks`: ``x``, final cost ``Σ r²``, evaluations, convergence."""

    x: np.ndarray
    cost: float
    nfev: int
    converged: bool

    @property
    def status(self) -> int:
        """``least_squares``-style status: > 0 converged, 0 evaluation budget exhausted."""
        return 1 if self.converged else 0


@dataclass(frozen=True)
class _Normal:
    """Blocks of JᵀJ and Jᵀr at one point (see module docstring)."""

    cost: float
    U: np.ndarray  # (g, g)
    W: np.ndarray  # (n, g, 6)
    V: np.ndarray  # (n, 6, 6)
    b_g: np.ndarray  # (g,)
    b_v: np.ndarray  # (n, 6)


def _normal_equations(problem: BlockProblem, x: np.ndarray) -> _Normal:
    r, blocks = problem.evaluate(x)
    g, n = problem.n_free_global, problem.n_stations
    m = blocks.shape[0]
    Jg = blocks[:, :, :g].reshape(2 * m, g)
    Js = blocks[:, :, g:].reshape(2 * m, 6)
    rc = r[:2 * m]
    rp = r[2 * m:].reshape(n, 6) if len(r) > 2 * m else np.zeros((n, 6))
    rows = np.append(2 * np.asarray(problem.starts), 2 * m)
    w = 1.0 / np.asarray(problem.prior_sigma)
    # per station one product Js_iᵀ [Jg_i | Js_i | rc_i] (6, g + 7): W_iᵀ, V_i and b_vi at
    # once, instead of (2m, g, 6) outer products summed by station (30x slower)
    full = np.concatenate([Jg, Js, rc[:, None]], axis=1)
    A = np.stack([Js[a:b].T @ full[a:b] for a, b in pairwise(rows)])
    return _Normal(
        cost=float(r @ r), U=Jg.T @ Jg, W=A[:, :, :g].transpose(0, 2, 1),
        V=A[:, :, g:g + 6] + np.diag(w * w), b_g=Jg.T @ rc, b_v=A[:, :, -1] + rp * w)


def _reduced(ne: _Normal, damping: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Damped reduced system: S (g, g), its right side (g,), and V⁻¹ (n, 6, 6)."""
    U = ne.U + damping * np.diag(np.diag(ne.U))
    V = ne.V + damping * ne.V * np.eye(6)
    V_inv = np.linalg.inv(V)
    WV = ne.W @ V_inv
    S = U - np.einsum("nij,nkj->ik", WV, ne.W)
    b = ne.b_g - np.einsum("nij,nj->i", WV, ne.b_v)
    return S, b, V_inv


def _step(ne: _Normal, damping: float) -> np.ndarray:
    S, b, V_inv = _reduced(ne, damping)
    dg = solve_scaled(S, b)
    dv = np.einsum("nij,nj->ni", V_inv, ne.b_v - np.einsum("nij,i->nj", ne.W, dg))
    return -np.concatenate([dg, dv.ravel()])


def solve_blocks(problem: BlockProblem, x0: np.ndarray, *, max_nfev: int = 50,
                 ftol: float = 1e-10) -> BlockSolution:
    """Minimise ``Σ r(x)²`` from ``x0`` by Levenberg-Marquardt on the reduced system
    (``calib.levmar``: Gauss-Newton's step first, Marquardt's damping after a failed one).

    From the nearby starts of cross-validation and model selection the first step lands on
    the minimum, where a start at λ = 1e-4 crawls along the problem's ill-conditioned
    directions (κ, ν and the focal length) for 5-8 steps. ``ftol`` is the relative change of
    the cost that ends the search (the ``ftol`` of ``least_squares``).
    """
    x, ne, nfev, converged = levenberg_marquardt(
        lambda x: _normal_equations(problem, x), _step, x0, max_nfev=max_nfev, ftol=ftol)
    return BlockSolution(x=x, cost=ne.cost, nfev=nfev, converged=converged)


def prior_redundancy(problem: BlockProblem, x: np.ndarray) -> tuple[float, float]:
    """Redundancy of the rotation and translation prior rows at ``x`` (Förstner's r_g).

    ``r_g = Σ_rows (1 - h_jj)``, with ``h_jj = w_j² [(JᵀJ)⁻¹]_pp`` the hat-matrix diagonal of
    the prior row on station parameter p (weight ``w_j = 1/σ``). The station blocks of the
    inverse are ``V_i⁻¹ + V_i⁻¹ W_iᵀ S⁻¹ W_i V_i⁻¹``. Variance-component estimation divides each
    group's squared residuals by its redundancy.
    """
    ne = _normal_equations(problem, x)
    S, _, V_inv = _reduced(ne, 0.0)
    S_inv = inverse_scaled(S)
    WV = ne.W @ V_inv  # (n, g, 6)
    cov = V_inv + np.einsum("nji,jk,nkl->nil", WV, S_inv, WV)  # (n, 6, 6)
    h = np.diagonal(cov, axis1=1, axis2=2) / np.asarray(problem.prior_sigma) ** 2
    return float(np.sum(1.0 - h[:, :3])), float(np.sum(1.0 - h[:, 3:]))
