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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

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
    groups (0: none).
    """

    sigmas: dict[str, float | np.ndarray]
    formal: dict[str, float | np.ndarray]
    jackknife: dict[str, float | np.ndarray]
    source: dict[str, str]
    folds: int
    expected: dict[str, float | np.ndarray] = field(default_factory=dict)

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
            return text + ("the formal value is reported everywhere (the jackknife is within its "
                           "noise of that or smaller)")
        return text + ("the data scatter more than the noise model says for "
                       + ", ".join(wider) + " (jackknife reported, as the formal components "
                       "scaled to its size: the robot likely has systematic errors)")


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


#: The 90 % bound on the norm of a 3-vector error (a pose's rotation or translation) as a
#: multiple of its reported σ, the root-sum-square of the per-axis σ (σ² = tr Σ, the mean
#: square of the norm). ``|e|² = Σ λᵢ zᵢ²`` (λ the eigenvalues of Σ, zᵢ standard normal), so
#: ``P(|e| ≤ k σ)`` depends on how Σ splits over its axes: k = 1.443 when it splits evenly
#: (``sqrt(χ²₃(0.9) / 3)``) and at most k = 1.645 (``z₀.₉₅``, all of it on one axis; above
#: ``k² ≈ 1.54`` one axis is the worst case, Székely & Bakirov 2003). The reported σ carries
#: neither the split nor the axes' correlations, so the worst case is taken: ``k σ`` bounds
#: the norm of the error with at least 90 % probability whatever the covariance's shape.
COVERAGE_90 = 1.645

