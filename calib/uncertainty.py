"""Honest 1-sigma: never smaller than the spread the data themselves show.

The formal covariance of the joint estimate assumes independent per-station robot noise. Real
arms have systematic kinematic errors (a joint offset bends every reading of similar
configurations alike), so estimates from different subsets of the stations scatter more than
the formal σ says. The delete-a-group jackknife over the cross-validation folds measures that
scatter directly (Efron & Tibshirani, *An Introduction to the Bootstrap*, 11.5)::

    σ_jk² = (g - 1) / g · Σ_f (θ_f - θ̄)²          g folds, θ_f the estimate without fold f

Each reported σ is the larger of the two, and the result says which one it is — the jackknife
counting as larger only beyond its own noise (``JACKKNIFE_NOISE``): with 5 folds each of its
components rests on 4 degrees of freedom (about ±35 %), and deleting a fifth of the stations
makes it overstate the spread even on ideal data (1.2x the Monte-Carlo spread of the
translation on the simulated cell without kinematic errors, ``python -m benchmarks.uncertainty``).
A vector (the three rotation or translation components of a pose) is compared as a block, by
the root-sum-square of its components; when the jackknife wins, the formal components are
scaled up to its size — the formal shape, far less noisy, at the level the data show. So the
reported σ is never below the jackknife by more than that factor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib import so3
from calib.crossval import FoldEstimate

#: The jackknife replaces the formal σ only when it is larger by more than this factor (its
#: sampling noise and upward bias with 5 folds, see the module docstring).
JACKKNIFE_NOISE = 1.3


@dataclass(frozen=True)
class UncertaintyEstimate:
    """Reported σ per parameter, the two figures it was taken from, and which one won.

    ``sigmas`` holds floats (κ, ν, camera) and arrays (3,) (``hand_eye_rot_rad``,
    ``hand_eye_trans_m``, ``target_pose_rot_rad``, ``target_pose_trans_m``); ``formal`` and
    ``jackknife`` the same names; ``source`` maps each name to ``formal`` or ``jackknife``
    (the larger as a block; a jackknife vector is reported as the formal one scaled to its
    size). ``folds`` is the number of jackknife groups (0: none).
    """

    sigmas: dict[str, float | np.ndarray]
    formal: dict[str, float | np.ndarray]
    jackknife: dict[str, float | np.ndarray]
    source: dict[str, str]
    folds: int

    @property
    def note(self) -> str:
        """One sentence for people: what the numbers are and where they came from."""
        if not self.jackknife:
            return ("1-sigma from the Jacobian at the optimum, scaled by the residual variance; "
                    "no cross-validation folds to check it against")
        wider = sorted(k for k, v in self.source.items() if v == "jackknife")
        text = (f"1-sigma: the larger of the formal value (Jacobian at the optimum, scaled by "
                f"the residual variance) and the delete-a-group jackknife spread over the "
                f"{self.folds} cross-validation folds, the jackknife counting when it exceeds "
                f"the formal value by more than its own noise ({JACKKNIFE_NOISE:g}x); ")
        if not wider:
            return text + ("the formal value is reported everywhere (the jackknife is within its "
                           "noise of it or smaller)")
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
           reference: FoldEstimate) -> UncertaintyEstimate:
    """Reported σ: the larger of ``formal`` and the fold jackknife, the jackknife counting only
    beyond ``JACKKNIFE_NOISE`` (vectors as a block, see the module docstring).

    Parameters without a formal σ or held fixed (formal 0) keep their formal value.
    """
    jk = jackknife_sigmas(estimates, reference)
    sigmas, source = dict(formal), {}
    for name, s_jk in jk.items():
        s_f = formal.get(name)
        if s_f is None or not np.any(np.asarray(s_f) > 0):
            continue
        size_f, size_jk = float(np.linalg.norm(s_f)), float(np.linalg.norm(s_jk))
        wider = size_jk > JACKKNIFE_NOISE * size_f
        sigmas[name] = (np.asarray(s_f) * (size_jk / size_f) if np.ndim(s_f) else size_jk) \
            if wider else s_f
        source[name] = "jackknife" if wider else "formal"
    return UncertaintyEstimate(sigmas=sigmas, formal=dict(formal), jackknife=jk, source=source,
                       folds=len(estimates) if jk else 0)


#: The 90 % bound on the norm of a 3-vector error (a pose's rotation or translation) as a
#: multiple of its reported σ, the root-sum-square of the per-axis σ (σ² = tr Σ, the mean
#: square of the norm). ``|e|² = Σ λᵢ zᵢ²`` (λ the eigenvalues of Σ, zᵢ standard normal), so
#: ``P(|e| ≤ k σ)`` depends on how Σ splits over its axes: k = 1.443 when it splits evenly
#: (``sqrt(χ²₃(0.9) / 3)``) and at most k = 1.645 (``z₀.₉₅``, all of it on one axis; above
#: ``k² ≈ 1.54`` one axis is the worst case, Székely & Bakirov 2003). The reported σ carries
#: neither the split nor the axes' correlations, so the worst case is taken: ``k σ`` bounds
#: the norm of the error with at least 90 % probability whatever the covariance's shape.
COVERAGE_90 = 1.645

