"""What the fold jackknife would show if the noise model were right: its expectation, by design.

The delete-a-group jackknife over the cross-validation folds (``calib.uncertainty``) estimates
the spread of the full estimate from the spread of the fold estimates. That holds for a
balanced design. Where a few stations carry much of the information on a parameter (κ from a
few tilted views of 15), the fold without them moves far and the jackknife overstates the
spread even when the noise model is exact: the jackknife variance is biased upwards (Efron &
Stein, *Ann. Stat.* 9:586, 1981), by the leverage of what is deleted (Hinkley, "Jackknifing in
unbalanced situations", *Technometrics* 19:285, 1977; Wu, *Ann. Stat.* 14:1261, 1986, for
groups).

This module gives the jackknife's expectation under the noise model, for the folds as they
are, from the joint problem linearised at its minimum (``calib.schur``'s blocks). With the
station blocks eliminated, station i adds ``S_i = U_i - W_i V_i⁻¹ W_iᵀ`` to the reduced
normal matrix ``S`` of the globals and ``C_i = B_i F B_iᵀ`` to the middle of the sandwich
covariance ``S⁻¹ (Σ C_i) S⁻¹`` (``B_i`` its rows' effect on the globals, ``F`` the residual
groups' variance factors). The fold without the stations of group f has ``S_f = S - Σ_{i∈f}
S_i``, and its deviation from the full estimate is, to first order::

    d_f = (S_f⁻¹ - S⁻¹) u_(-f) - S⁻¹ u_f        u_T = Σ_{i∈T} B_i r_i

so ``Cov(d_f, d_k) = Σ_h M_fh C_h M_khᵀ`` over the groups h (``M_fh = S_f⁻¹ - S⁻¹``, or ``-S⁻¹``
for h = f; ``C_h = Σ_{i∈h} C_i``), and the jackknife's expectation is
``(g - 1)/g · (Σ_f Cov(d_f, d_f) - (1/g) Σ_fk Cov(d_f, d_k))``. For one group and F = I this
is Hausman's ``S_f⁻¹ - S⁻¹`` (*Econometrica* 46, 1978); for g balanced groups of a linear
model it is the formal covariance itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np

from calib.joint import GLOBAL_PARAMS, JointProblem, sigmas_from_covariance
from calib.levmar import inverse_scaled


def expected_jackknife(problem: JointProblem, x: np.ndarray, folds: Sequence[np.ndarray],
                       factors: tuple[float, float, float]
                       ) -> dict[str, float | np.ndarray]:
    """Per parameter the jackknife σ the noise model predicts over ``folds`` (held-out station
    indices per fold), in the layout of ``JointResult.sigmas``; {} below 3 folds or where a
    fold leaves the globals undetermined.

    ``problem`` at its minimum ``x``; ``factors`` the variance factors of the corner,
    robot-rotation and robot-translation residuals (``calib.jointfit.variance_factors``), as
    in the sandwich covariance the formal σ come from.
    """
    if len(folds) < 3:
        return {}
    S_i, C_i = _station_terms(problem, x, factors)
    group = np.full(problem.n_stations, -1)
    for f, held in enumerate(folds):
        group[np.asarray(held, dtype=int)] = f
    S_h = np.stack([S_i[group == f].sum(axis=0) for f in range(len(folds))])
    C_h = np.stack([C_i[group == f].sum(axis=0) for f in range(len(folds))])
    S = S_i.sum(axis=0)
    try:
        S_inv = inverse_scaled(S, strict=True)
        P = np.stack([inverse_scaled(S - S_h[f], strict=True) - S_inv for f in range(len(folds))])
    except np.linalg.LinAlgError:  # the globals are undetermined without a fold
        return {}
    g = len(folds)
    # M[f, h]: the effect of group h's residuals on fold f's deviation (module docstring)
    M = np.repeat(P[:, None], g, axis=1)
    M[np.arange(g), np.arange(g)] = -S_inv
    cov = np.einsum("fhab,hbc,khdc->fkad", M, C_h, M, optimize=True)  # Cov(d_f, d_k)
    spread = (g - 1) / g * (np.einsum("ffab->ab", cov) - cov.sum(axis=(0, 1)) / g)
    full = np.zeros((len(GLOBAL_PARAMS), len(GLOBAL_PARAMS)))
    full[np.ix_(problem.free, problem.free)] = spread
    return sigmas_from_covariance(full)


def _station_terms(problem: JointProblem, x: np.ndarray, factors: tuple[float, float, float]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each station's share of the reduced normal matrix, ``S_i``, and of the sandwich's
    middle, ``C_i`` (n, p, p) (module docstring)."""
    _, blocks = problem.evaluate(x)
    g = problem.n_free_global
    m = blocks.shape[0]
    Jg = blocks[:, :, :g].reshape(2 * m, g)
    Js = blocks[:, :, g:].reshape(2 * m, 6)
    w2 = 1.0 / np.asarray(problem.prior_sigma) ** 2
    f_corner, f_rot, f_trans = factors
    prior = np.diag(w2 * np.array([f_rot] * 3 + [f_trans] * 3))
    rows = np.append(2 * np.asarray(problem.starts), 2 * m)
    S_i, C_i = [], []
    for a, b in pairwise(rows):
        U, W, Vc = Jg[a:b].T @ Jg[a:b], Jg[a:b].T @ Js[a:b], Js[a:b].T @ Js[a:b]
        WV = W @ np.linalg.inv(Vc + np.diag(w2))
        S_i.append(U - WV @ W.T)
        C_i.append(f_corner * (U - 2.0 * WV @ W.T + WV @ Vc @ WV.T) + WV @ prior @ WV.T)
    return np.stack(S_i), np.stack(C_i)
