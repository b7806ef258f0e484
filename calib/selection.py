"""Model selection by prediction: which joint model to return, decided by cross-validation.

Richer models fit the calibration stations better by construction; whether they are *right*
shows only on stations they have not seen. Each choice is a pair — κ estimated or held at 1,
ν estimated or held at 1, robot noise levels estimated from the data (variance components,
``calib.jointfit``) or assumed — and the simpler side wins unless the richer one predicts the
held-out stations clearly better (``clearly_better``), or, for ν, predicts no worse while
the corners put it many σ away from 1 (``_estimate_reason``). Every
candidate's cross-validated figure is kept, so the choice can be checked.

``kappa`` modes: ``auto`` (chosen by prediction), ``estimate`` (always estimated), ``fixed``
(held at exactly 1: the user measured the board and entered its true square size).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.crossval import CrossValidation, FoldEstimate, cross_validate_joint
from calib.joint import CellParameters
from calib.jointfit import JointData, JointFit, JointModel, fit_joint, held_at_one
from calib.uncertainty import jackknife_sigmas

KAPPA_MODES = ("auto", "estimate", "fixed")
#: A richer model must lower the cross-validated RMS by at least this fraction ...
MIN_IMPROVEMENT = 0.05
#: ... and the mean paired per-station improvement must exceed this many standard errors
#: (one-sided: about 84 % confidence; with 8-20 held-out stations 2 would hide real gains).
MIN_SIGNIFICANCE = 1.0
#: ν this many σ away from 1 is estimated when it does not predict worse.
SIGNIFICANT_SIGMAS = 3.0
RULE = (f"the simpler model unless the richer one lowers the cross-validated RMS by at least "
        f"{100 * MIN_IMPROVEMENT:g} % with a paired per-station improvement beyond "
        f"{MIN_SIGNIFICANCE:g} standard error(s); nu is also estimated when that predicts no "
        f"worse and it lies beyond {SIGNIFICANT_SIGMAS:g} sigma of 1")
NOT_WARRANTED = ("estimating it neither predicts clearly better nor finds it significantly "
                 "different from 1")


@dataclass(frozen=True)
class Candidate:
    """One model tried: its cross-validation and, for joint models, the model and its fit on
    all stations (None for the pose-only candidates)."""

    name: str
    cv: CrossValidation
    model: JointModel | None = None
    fit: JointFit | None = None


@dataclass(frozen=True)
class Selection:
    """All candidates (``candidates[0]`` the base), the chosen one, and why."""

    candidates: tuple[Candidate, ...]
    chosen: Candidate
    decisions: tuple[str, ...]


def clearly_better(rich: CrossValidation, simple: CrossValidation) -> bool:
    """True when ``rich`` predicts clearly better than ``simple`` (paired over stations).

    Both the RMS must drop by ``MIN_IMPROVEMENT`` and the paired differences of squared
    per-station errors must be positive beyond ``MIN_SIGNIFICANCE`` standard errors: a
    one-station fluke is not evidence.
    """
    a, b = simple.station_errors() ** 2, rich.station_errors() ** 2
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 2:
        return False
    d = a[ok] - b[ok]
    se = float(np.std(d, ddof=1) / np.sqrt(len(d)))
    drop = 1.0 - np.sqrt(b[ok].mean() / a[ok].mean())
    return bool(drop >= MIN_IMPROVEMENT and d.mean() > MIN_SIGNIFICANCE * se)


def _estimate_reason(rich: Candidate, simple: Candidate, name: str) -> str | None:
    """Why to estimate ``name`` (κ or ν) rather than hold it at 1, or None: not warranted.

    Estimated when that predicts clearly better. ν also when it predicts no worse and
    differs from 1 by more than ``SIGNIFICANT_SIGMAS`` σ (the larger of the formal σ and the
    fold jackknife): the corners alone pin ν down (Method #1), far better than robot-pose
    predictions can show. Not κ: it is seen only through the robot's translations (eq. 6), so
    an arm's systematic errors fake a significant κ on an exact board.
    """
    if clearly_better(rich.cv, simple.cv):
        return "predicts held-out stations clearly better than held at 1"
    if name == "kappa" or clearly_better(simple.cv, rich.cv) or rich.fit is None:
        return None
    value = getattr(rich.fit.cell, name)
    formal = float(rich.fit.result(np.arange(len(rich.cv.stations))).sigmas[name])
    jackknife = jackknife_sigmas(rich.cv.estimates, FoldEstimate.of(rich.fit.cell))
    sigma = max(formal, float(jackknife.get(name, 0.0)))
    if abs(value - 1.0) > SIGNIFICANT_SIGMAS * sigma:  # see RULE
        return (f"predicts no worse, and {name} = {value:.5f} differs from 1 by "
                f"{abs(value - 1.0) / sigma:.0f} sigma")
    return None


@dataclass(frozen=True)
class Modes:
    """Which choices are made by prediction (``auto``) and which are forced: ``kappa`` and
    ``nu`` ``estimate``/``fixed``, ``noise`` ``estimate``/``assumed``."""

    kappa: str = "auto"
    nu: str = "auto"
    noise: str = "auto"

    def __post_init__(self) -> None:
        if self.kappa not in KAPPA_MODES:
            raise ValueError(f"unknown kappa mode '{self.kappa}': choose one of "
                             f"{', '.join(KAPPA_MODES)}")


def select_joint_model(data: JointData, station_ids: Sequence[str], base: JointModel,
                       start: CellParameters, modes: Modes = Modes()) -> Selection:
    """Cross-validate the base model and its simpler/richer neighbours; pick one.

    ``base`` estimates everything it may (κ unless ``kappa='fixed'``, ν unless held) with the
    assumed noise levels; ``start`` its solution on all stations; ``modes`` which choices
    are forced.
    """
    kappa, nu, noise = modes.kappa, modes.nu, modes.noise

    def run(model: JointModel) -> Candidate:
        fit = fit_joint(data, model, held_at_one(
            start, [p for p in ("kappa", "nu") if p in model.fix and p not in base.fix]))
        cv_model = replace(model, noise=fit.noise, estimate_noise=False)
        cv_data = replace(data, sigma_px=fit.sigma_px)
        cv = cross_validate_joint(cv_data, station_ids, cv_model, fit.cell)
        return Candidate(name=model.name, cv=cv, model=model, fit=fit)

    base_c = run(base)
    candidates = [base_c]
    chosen_fix, estimate_noise, decisions = set(base.fix), False, []
    for name, mode in (("kappa", kappa), ("nu", nu)):
        if name in base.fix or mode == "estimate":
            decisions.append(f"{name}: {'held' if name in base.fix else 'estimated'} "
                             f"({'given' if mode != 'auto' else 'known intrinsics'})")
            continue
        simple = run(replace(base, name=f"{name} = 1", fix=(*base.fix, name)))
        candidates.append(simple)
        why = "given" if mode == "fixed" else _estimate_reason(base_c, simple, name)
        if why is None or mode == "fixed":
            chosen_fix.add(name)
            why = why or NOT_WARRANTED
            decisions.append(f"{name}: held at 1 ({why})")
        else:
            decisions.append(f"{name}: estimated ({why})")
    if noise != "assumed":
        rich = run(replace(base, name="robot noise estimated", estimate_noise=True))
        candidates.append(rich)
        estimate_noise = noise == "estimate" or clearly_better(rich.cv, base_c.cv)
        decisions.append("robot noise: " + ("estimated from the data" if estimate_noise else
                                            "assumed: estimating it does not predict "
                                            "clearly better"))
    fix = tuple(p for p in base.fix if p in chosen_fix) + tuple(
        p for p in ("kappa", "nu") if p in chosen_fix and p not in base.fix)
    chosen = next((c for c in candidates if c.model is not None and set(c.model.fix) == set(fix)
                   and c.model.estimate_noise == estimate_noise), None)
    if chosen is None:
        held = " and ".join(p for p in fix if p in ("kappa", "nu")) + " = 1"
        chosen = run(replace(base, name=held + (", robot noise estimated" if estimate_noise
                                                else ""), fix=fix, estimate_noise=estimate_noise))
        candidates.append(chosen)
    return Selection(candidates=tuple(candidates), chosen=chosen, decisions=tuple(decisions))
