"""Honest 1-sigma: never smaller than the spread the data themselves show.

The formal covariance of the joint estimate assumes independent per-station robot noise. Real
arms have systematic kinematic errors (a joint offset bends every reading of similar
configurations alike), so estimates from different subsets of the stations scatter more than
the formal σ says. The delete-a-group jackknife over the cross-validation folds measures that
scatter directly (Efron & Tibshirani, *An Introduction to the Bootstrap*, 11.5)::

    σ_jk² = (g - 1) / g · Σ_f (θ_f - θ̄)²          g folds, θ_f the estimate without fold f

Deleting a fold overstates the spread of the full estimate even where the noise model is
exact, the more so where a few stations carry much of what is known of a parameter (κ from
a few tilted views of 15): the fold without them moves far. The jackknife variance is biased
upwards (Efron & Stein, *Ann. Stat.* 9:586, 1981), by the leverage of what is deleted
(Hinkley, *Technometrics* 19:285, 1977). So whether the data scatter more than the noise
model says is judged against what that model expects the jackknife to be for these very
folds, ``σ_m`` (``calib.foldspread``; the formal σ where it is missing, as for pose-only fits:
the expectation for a balanced linear design), not against the formal σ: the test of a
variance against its expectation under the null, for the design at hand.

Each reported σ is the formal one unless the jackknife exceeds ``σ_m`` by more than its own
noise (``JACKKNIFE_NOISE``: with 5 folds each of its components rests on 4 degrees of
freedom, about ±35 %); then it is the jackknife, never less than the spread the data
themselves show. The result says which one it is. A vector (the three rotation or
translation components of a pose) is compared as a block, by the root-sum-square of its
components; when the jackknife wins, the formal components are scaled up to its size — the
formal shape, far less noisy, at the level the data show. So the reported σ is never below
the formal one, and never below the jackknife debiased for its design (``σ_jk · σ / σ_m``)
by more than that factor.

A parameter the model selection held at 1 (κ or ν: estimating it did not predict clearly
better, ``calib.selection``) is not known to be 1, only not shown to differ. Both σ's above
take it as exact, so the pose estimates lose the bias a board off its entered size gives them:
a board 0.1 % larger than entered moves a camera 1.2 m away by 1.2 mm, far beyond their σ.
That bias is estimated from the shift ``d`` of the pose estimates between the chosen model
(σ_h, formal) and the same model with the held parameters estimated (σ_f): with the held
value right, ``d`` is noise of variance ``v = σ_f² - σ_h²`` per axis (the held fit is the
efficient one; Hausman, *Econometrica* 46, 1978, lemma 2.1), so ``max(0, d² - v)`` is the
positive part of an unbiased estimate of the bias's square. Each 3-vector (a pose's rotation
or translation) is tested as one: ``T = Σ d² / v`` over its axes against χ² with as many
degrees of freedom at 95 % (``HELD_LEVEL``; twelve separate tests at 95 % would add a false
bias somewhere in every other result). Where the shift is within its noise it is no evidence
of a bias, and adding it anyway makes a board that is right over-cover. Beyond it, the bias's
square is shrunk by ``(1 - c / T)`` (c the critical value; the positive-part shrinkage of
Stein's estimator, Baranchik, *Ann. Math. Stat.* 41:642, 1970), so the added term grows from 0
at the test's threshold instead of jumping there. An axis on which freeing the parameter
costs no precision (``v <= 0``: the held parameter does not inform it) carries no test and no
bias: its shift is no noise the model knows. The reported σ becomes ``sqrt(σ² + bias²)``: the
chosen estimate's mean square error. A parameter the user holds fixed (``kappa='fixed'``)
adds nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import chdtri

from calib import so3
from calib.crossval import FoldEstimate

#: The jackknife replaces the formal σ only when it exceeds its expectation under the noise
#: model by more than this factor (its sampling noise with 5 folds, see the module docstring).
JACKKNIFE_NOISE = 1.3


@dataclass(frozen=True)
class UncertaintyEstimate:
    """Reported σ per parameter, the two figures it was taken from, and which one won.

    ``sigmas`` holds floats (κ, ν, camera) and arrays (3,) (``hand_eye_rot_rad``,
    ``hand_eye_trans_m``, ``target_pose_rot_rad``, ``target_pose_trans_m``); ``formal`` and
    ``jackknife`` the same names, ``expected`` the jackknife the noise model predicts for
    these folds (empty: the formal σ stands for it); ``source`` maps each name to ``formal``
    or ``jackknife`` (the jackknife beyond its noise of that expectation; a jackknife vector
    is reported as the formal one scaled to its size). ``folds`` is the number of jackknife
    groups (0: none). ``held`` names the parameters the model selection held at 1, ``shift``
    the pose estimates' shift (3,) per name when they are estimated instead, ``bias`` the bias
    (3,) that shift shows beyond its noise, added to ``sigmas`` in quadrature (module
    docstring). ``extrapolation`` the hand-eye σ (3,) added for using the estimate over the
    whole workspace box rather than at the stations (``calib.extrapolation``), when the box
    is known.
    """

    sigmas: dict[str, float | np.ndarray]
    formal: dict[str, float | np.ndarray]
    jackknife: dict[str, float | np.ndarray]
    source: dict[str, str]
    folds: int
    expected: dict[str, float | np.ndarray] = field(default_factory=dict)
    held: tuple[str, ...] = ()
    shift: dict[str, np.ndarray] = field(default_factory=dict)
    bias: dict[str, np.ndarray] = field(default_factory=dict)
    extrapolation: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def note(self) -> str:
        """One sentence for people: what the numbers are and where they came from."""
        if not self.jackknife:
            return ("1-sigma from the Jacobian at the optimum, scaled by the residual variance; "
                    "no cross-validation folds to check it against")
        wider = sorted(k for k, v in self.source.items() if v == "jackknife")
        against = ("what the noise model predicts for these folds" if self.expected
                   else "the formal value")
        text = (f"1-sigma: the formal value (Jacobian at the optimum, scaled by the residual "
                f"variance), or the delete-a-group jackknife spread over the {self.folds} "
                f"cross-validation folds where that exceeds {against} by more than its own "
                f"noise ({JACKKNIFE_NOISE:g}x); ")
        if not wider:
            text += ("the formal value is reported everywhere (the jackknife is within its "
                     "noise of that or smaller)")
        else:
            text += ("the data scatter more than the noise model says for "
                     + ", ".join(wider) + " (jackknife reported, as the formal components "
                     "scaled to its size: the robot likely has systematic errors)")
        if self.held:
            text += ("; the poses' σ include the bias shown by how far they move when "
                     + " and ".join(self.held) + ", held at 1 by the model selection, "
                     "is estimated instead, beyond the noise of that move")
        if self.extrapolation:
            text += ("; the hand-eye σ include how far its mean over the workspace box may "
                     "lie from its mean over the stations (the spread the stations show, "
                     "extrapolated to the box's centre)")
        return text


def fold_deviations(estimates: Sequence[FoldEstimate], reference: FoldEstimate
                    ) -> dict[str, np.ndarray]:
    """Per-fold estimates as deviations from ``reference``: (g, 3) for poses, (g,) scalars.

    Rotations as small left rotations ``rotvec(R_f R_refᵀ)``, in the frame of the first index
    (like the formal σ of ``calib.joint``).
    """
    out: dict[str, np.ndarray] = {}
    for name, attr in (("hand_eye", "hand_eye"), ("target_pose", "target_pose")):
        T_ref = getattr(reference, attr)
        T = np.stack([getattr(e, attr) for e in estimates])
        out[f"{name}_rot_rad"] = so3.log(T[:, :3, :3] @ T_ref[:3, :3].T)
        out[f"{name}_trans_m"] = T[:, :3, 3] - T_ref[:3, 3]
    out["kappa"] = np.array([e.kappa for e in estimates])
    out["nu"] = np.array([e.nu for e in estimates])
    return out


def jackknife_sigmas(estimates: Sequence[FoldEstimate], reference: FoldEstimate
                     ) -> dict[str, float | np.ndarray]:
    """Delete-a-group jackknife σ over fold estimates (see module docstring); {} below 3."""
    g = len(estimates)
    if g < 3:
        return {}
    out: dict[str, float | np.ndarray] = {}
    for name, dev in fold_deviations(estimates, reference).items():
        s = np.sqrt((g - 1) / g * np.sum((dev - dev.mean(axis=0)) ** 2, axis=0))
        out[name] = s if np.ndim(s) else float(s)
    return out


def honest(formal: dict[str, float | np.ndarray], estimates: Sequence[FoldEstimate],
           reference: FoldEstimate, expected: dict[str, float | np.ndarray] | None = None
           ) -> UncertaintyEstimate:
    """Reported σ: ``formal``, or the fold jackknife where it exceeds ``expected`` (its
    expectation under the noise model, ``calib.foldspread``; the formal σ where that is
    missing) by more than ``JACKKNIFE_NOISE`` (vectors as a block, see the module docstring).

    Parameters without a formal σ or held fixed (formal 0) keep their formal value.
    """
    jk, expected = jackknife_sigmas(estimates, reference), dict(expected or {})
    sigmas, source = dict(formal), {}
    for name, s_jk in jk.items():
        s_f = formal.get(name)
        if s_f is None or not np.any(np.asarray(s_f) > 0):
            continue
        size_f, size_jk = float(np.linalg.norm(s_f)), float(np.linalg.norm(s_jk))
        size_m = float(np.linalg.norm(expected.get(name, 0.0))) or size_f
        wider = size_jk > JACKKNIFE_NOISE * size_m and size_jk > size_f
        sigmas[name] = (np.asarray(s_f) * (size_jk / size_f) if np.ndim(s_f) else size_jk) \
            if wider else s_f
        source[name] = "jackknife" if wider else "formal"
    return UncertaintyEstimate(sigmas=sigmas, formal=dict(formal), jackknife=jk, source=source,
                               folds=len(estimates) if jk else 0,
                               expected={k: v for k, v in expected.items() if k in source})


#: A held parameter's shift of a pose's rotation or translation counts as bias when Hausman's
#: statistic over its axes exceeds the χ² quantile at this level (module docstring).
HELD_LEVEL = 0.95

#: The pose estimates of ``fold_deviations`` that :func:`with_held_shift` widens.
POSE_SIGMAS = ("hand_eye_rot_rad", "hand_eye_trans_m", "target_pose_rot_rad",
               "target_pose_trans_m")


def with_held_shift(estimate: UncertaintyEstimate, held: Sequence[str],
                    chosen: tuple[FoldEstimate, dict[str, float | np.ndarray]],
                    freed: tuple[FoldEstimate, dict[str, float | np.ndarray]]
                    ) -> UncertaintyEstimate:
    """``estimate`` with the pose σ widened by the bias the parameters ``held`` at 1 show:
    ``chosen`` is the held fit's estimate and formal σ, ``freed`` the same model's with them
    estimated; per 3-vector the shift ``d`` is tested against its noise
    ``v = σ_f² - σ_h²`` (axes with ``v > 0``) and, beyond it, ``(1 - c / T) max(0, d² - v)``
    added to σ² per axis (module docstring). ``shift`` keeps ``|d|``, ``bias`` the square root
    of what was added."""
    if not held:
        return estimate
    (est_h, formal_h), (est_f, formal_f) = chosen, freed
    shift = {name: np.abs(dev[0]) for name, dev in fold_deviations([est_f], est_h).items()
             if name in POSE_SIGMAS}
    sigmas, bias = dict(estimate.sigmas), {}
    for name, d in shift.items():
        if name not in sigmas or name not in formal_h or name not in formal_f:
            continue
        bias[name] = held_bias(d, np.asarray(formal_f[name]) ** 2
                               - np.asarray(formal_h[name]) ** 2)
        sigmas[name] = np.hypot(np.asarray(sigmas[name], dtype=float), bias[name])
    return replace(estimate, sigmas=sigmas, held=tuple(held), shift=shift, bias=bias)


def held_bias(d: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The bias (3,) a shift ``d`` (3,) of noise variance ``v`` (3,) shows: 0 unless Hausman's
    statistic over the axes with ``v > 0`` exceeds its χ² quantile ``c`` at ``HELD_LEVEL``,
    else ``sqrt((1 - c / T) max(0, d² - v))`` on those axes (module docstring)."""
    tested = v > 0
    if not np.any(tested):
        return np.zeros_like(d, dtype=float)
    T = float(np.sum(d[tested] ** 2 / v[tested]))
    c = float(chdtri(int(tested.sum()), 1.0 - HELD_LEVEL))
    keep = max(0.0, 1.0 - c / T) if T > 0 else 0.0
    return np.where(tested, np.sqrt(keep * np.maximum(d ** 2 - np.where(tested, v, 0.0), 0.0)),
                    0.0)


def with_extrapolation(estimate: UncertaintyEstimate, added: dict[str, np.ndarray]
                       ) -> UncertaintyEstimate:
    """``estimate`` with ``added`` (per-axis σ (3,) by name, ``calib.extrapolation``) added
    to its σ in quadrature: the mean square error of the estimate as the box's hand-eye."""
    if not added:
        return estimate
    sigmas = dict(estimate.sigmas)
    for name, s_b in added.items():
        sigmas[name] = np.hypot(np.asarray(sigmas[name], dtype=float), s_b)
    return replace(estimate, sigmas=sigmas, extrapolation=dict(added))


#: The 90 % bound on the norm of a 3-vector error (a pose's rotation or translation) as a
#: multiple of its reported σ, the root-sum-square of the per-axis σ (σ² = tr Σ, the mean
#: square of the norm). ``|e|² = Σ λᵢ zᵢ²`` (λ the eigenvalues of Σ, zᵢ standard normal), so
#: ``P(|e| ≤ k σ)`` depends on how Σ splits over its axes: k = 1.443 when it splits evenly
#: (``sqrt(χ²₃(0.9) / 3)``) and at most k = 1.645 (``z₀.₉₅``, all of it on one axis; above
#: ``k² ≈ 1.54`` one axis is the worst case, Székely & Bakirov 2003). The reported σ carries
#: neither the split nor the axes' correlations, so the worst case is taken: ``k σ`` bounds
#: the norm of the error with at least 90 % probability whatever the covariance's shape.
COVERAGE_90 = 1.645


def hand_eye_rss(sigmas: dict[str, float | np.ndarray]) -> tuple[float, float] | None:
    """The hand-eye's σ root-sum-square over the axes, (rotation rad, translation m) as
    ``calib.viewselect.hand_eye_sigma`` gives a covariance's, from a result's ``sigmas``; None
    when they hold none. ``COVERAGE_90`` times it bounds the error's norm."""
    if "hand_eye_rot_rad" not in sigmas or "hand_eye_trans_m" not in sigmas:
        return None
    return (float(np.linalg.norm(sigmas["hand_eye_rot_rad"])),
            float(np.linalg.norm(sigmas["hand_eye_trans_m"])))

