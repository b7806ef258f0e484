"""Levenberg-Marquardt: the one damping loop of cellcal's solvers, and its dense form.

The loop (:func:`levenberg_marquardt`) is Marquardt's: the normal equations' diagonal scaled
by ``1 + λ``, λ shrinking after a successful step and growing after a failed one (Marquardt,
J. SIAM 11(2):431, 1963). What a step costs depends on the problem's structure, so the caller
gives two functions: the normal equations at a point and the step from them at a damping.
``calib.schur`` gives the joint problem's, with the station blocks eliminated; :func:`solve_dense`
a small dense problem's (``calib.refine``: 12-13 unknowns, 6 residuals per station) with a
forward-difference Jacobian.

:func:`solve_dense` stands where ``scipy.optimize.least_squares(method="lm")`` stood: the same
minimum (to its tolerance; this one converges tighter), the same forward-difference Jacobian
at it, without importing ``scipy.optimize`` (its linear-programming, global and FFT modules
come along: 0.2-0.3 CPU s of every ``cellcal calibrate``, on the path that gates the solve).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np

#: Floor of the Marquardt damping λ, and where it starts: the Gauss-Newton step.
MIN_DAMPING = 1e-9
#: λ after a failed step at the floor.
FIRST_DAMPING = 1e-4
#: Relative forward-difference step (``least_squares``'s "2-point": √eps · max(1, |x|)).
_DIFF_STEP = float(np.sqrt(np.finfo(float).eps))


class Normals(Protocol):
    """What the loop reads of the normal equations at a point: the cost ``Σ r²``."""

    cost: float


N = TypeVar("N", bound=Normals)


def levenberg_marquardt(normals: Callable[[np.ndarray], N], step: Callable[[N, float], np.ndarray],
                        x0: np.ndarray, *, max_nfev: int, ftol: float
                        ) -> tuple[np.ndarray, N, int, bool]:
    """Minimise ``Σ r(x)²`` from ``x0``: (x, its normal equations, evaluations, converged).

    ``normals(x)`` evaluates the problem at ``x``; ``step(normals, λ)`` solves the damped
    system for the step. The first step is Gauss-Newton's (λ at its floor): from the nearby
    starts the solvers get it lands on the minimum; a first step that fails goes on from
    λ = ``FIRST_DAMPING``. Converged when a step changes the cost by less than ``ftol``
    relative (at the minimum rounding may make that a rise, which no damping could undo) or
    the step is negligible; a λ beyond 1e8 ends the search there too.
    """
    x = np.asarray(x0, dtype=float).copy()
    ne = normals(x)
    nfev, damping = 1, MIN_DAMPING
    while nfev < max_nfev:
        try:
            dx = step(ne, damping)
        except np.linalg.LinAlgError:
            break
        x_new = x + dx
        trial = normals(x_new)
        nfev += 1
        if np.isfinite(trial.cost) and trial.cost <= ne.cost * (1.0 + ftol):
            small = abs(ne.cost - trial.cost) <= ftol * ne.cost or \
                np.abs(dx).max() <= 1e-14 * (1.0 + np.abs(x).max())
            if trial.cost <= ne.cost:
                x, ne = x_new, trial
            damping = max(damping / 5.0, MIN_DAMPING)
            if small:
                return x, ne, nfev, True
        else:
            damping = max(8.0 * damping, FIRST_DAMPING)
            if damping > 1e8:
                return x, ne, nfev, True
    return x, ne, nfev, False


#: Singular values of a Jacobi-scaled normal matrix below this fraction of its largest are
#: taken for zero: the directions the data leave undetermined.
RCOND = 1e-14


def _jacobi_scale(S: np.ndarray) -> np.ndarray:
    """``d = √diag S`` (p,): ``S / d dᵀ`` has a unit diagonal, so unknowns in pixels, radians,
    metres and ratios side by side do not read as an ill-conditioned matrix.

    A diagonal at or below zero is an unknown without information (in a reduced matrix,
    one the eliminated blocks explain entirely, left as rounding noise): its ``d`` is inf,
    so its row and column of ``S / d dᵀ`` are zero and the solve or pseudo-inverse drops it.
    A floor such as 1e-300 would instead scale its noise up by 1e150, overflow, and leave
    that row the only direction above the cut-off, dropping every determined one.
    """
    diag = np.diag(S)
    return np.sqrt(np.where(diag > 0.0, diag, np.inf))


def solve_scaled(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``S⁻¹ b`` with Jacobi scaling, least squares over the undetermined directions."""
    d = _jacobi_scale(S)
    if not (np.isfinite(S).all() and np.isfinite(b).all()):
        raise np.linalg.LinAlgError("non-finite normal equations")
    return np.linalg.lstsq(S / d[:, None] / d[None, :], b / d, rcond=RCOND)[0] / d


def inverse_scaled(S: np.ndarray, *, strict: bool = False) -> np.ndarray:
    """``S⁻¹`` (p, p) of a normal matrix with Jacobi scaling: the pseudo-inverse of
    ``S / d dᵀ``, scaled back. ``strict``: LinAlgError where ``S`` is not finite or has
    directions the pseudo-inverse would drop (condition of the scaled matrix above 1/RCOND)."""
    d = _jacobi_scale(S)
    scaled = S / d[:, None] / d[None, :]
    if strict and (not np.isfinite(scaled).all() or np.linalg.cond(scaled) > 1.0 / RCOND):
        raise np.linalg.LinAlgError("singular after Jacobi scaling")
    return np.linalg.pinv(scaled, rcond=RCOND) / d[:, None] / d[None, :]


@dataclass(frozen=True)
class DenseSolution:
    """Result of :func:`solve_dense`: ``x``, the residuals (m,) and forward-difference
    Jacobian (m, p) there, the cost ``Σ r²``, evaluations of the normal equations, and
    whether it converged."""

    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    cost: float
    nfev: int
    converged: bool


def solve_dense(fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, *,
                max_nfev: int = 50, ftol: float = 1e-12) -> DenseSolution:
    """Minimise ``Σ fun(x)²`` for a few unknowns by :func:`levenberg_marquardt`, the Jacobian
    by forward differences (p + 1 calls of ``fun`` per evaluation)."""
    x, ne, nfev, converged = levenberg_marquardt(
        lambda x: _dense_normals(fun, x), _dense_step, x0, max_nfev=max_nfev, ftol=ftol)
    return DenseSolution(x=x, residuals=ne.r, jacobian=ne.J, cost=ne.cost, nfev=nfev,
                         converged=converged)


@dataclass(frozen=True)
class _Dense:
    """Residuals ``r`` (m,), Jacobian ``J`` (m, p) and cost of a dense problem at a point."""

    r: np.ndarray
    J: np.ndarray
    cost: float


def _dense_normals(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray) -> _Dense:
    """``fun`` and its forward-difference Jacobian at ``x``: step √eps · max(1, |x_j|) away
    from zero, divided by the step as represented (``x + h - x``)."""
    r = np.asarray(fun(x), dtype=float)
    h = _DIFF_STEP * np.where(x >= 0.0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
    J = np.empty((len(r), len(x)))
    for j in range(len(x)):
        moved = x.copy()
        moved[j] += h[j]
        J[:, j] = (fun(moved) - r) / (moved[j] - x[j])
    return _Dense(r=r, J=J, cost=float(r @ r))


def _dense_step(ne: _Dense, damping: float) -> np.ndarray:
    U = ne.J.T @ ne.J
    return -solve_scaled(U + damping * np.diag(np.diag(U)), ne.J.T @ ne.r)
