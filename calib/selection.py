"""Model selection by prediction: which joint model to return, decided by cross-validation.

Richer models fit the calibration stations better by construction; whether they are *right*
shows only on stations they have not seen. Each choice is a pair — κ estimated or held at 1,
ν estimated or held at 1, robot noise levels estimated from the data (variance components,
``calib.jointfit``) or assumed — and the simpler side wins unless the richer one predicts the
held-out stations clearly better (``clearly_better``; for κ also their distances), or
predicts no worse while the data put the parameter away from 1: ν many σ, κ more than the
one σ beyond which holding it costs more than estimating it (``_estimate_reason``).
Every candidate's cross-validated figure is kept, so the choice can be checked.

``kappa`` modes: ``auto`` (chosen by prediction), ``estimate`` (always estimated), ``fixed``
(held at exactly 1: the user measured the board and entered its true square size).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace

import numpy as np

from calib.crossval import CrossValidation, FoldEstimate, JointFolds, submit_joint_folds
from calib.joint import CellParameters, JointResult
from calib.jointfit import JointData, JointFit, JointModel, fit_joint, held_at_one
from calib.options import KAPPA_MODES
from calib.parallel import fit_pool
from calib.quality import BOARD_SCALE_MIN
from calib.uncertainty import jackknife_sigmas

#: A richer model must lower the cross-validated RMS by at least this fraction ...
MIN_IMPROVEMENT = 0.05
#: ... and the mean paired per-station improvement must exceed this many standard errors
#: (one-sided: about 84 % confidence; with 8-20 held-out stations 2 would hide real gains).
MIN_SIGNIFICANCE = 1.0
#: ν this many σ away from 1 is estimated when it does not predict worse.
SIGNIFICANT_SIGMAS = 3.0
#: κ this many σ (and ``BOARD_SCALE_MIN``) away from 1 is estimated when it predicts the
#: distances no worse: where holding it costs more than estimating it (``_estimate_reason``).
KAPPA_SIGMAS = 1.0
RULE = (f"the simpler model unless the richer one lowers the cross-validated RMS by at least "
        f"{100 * MIN_IMPROVEMENT:g} % with a paired per-station improvement beyond "
        f"{MIN_SIGNIFICANCE:g} standard error(s) (for kappa in pixels or in camera-to-board "
        f"distance); nu is also estimated when that predicts no worse and it lies beyond "
        f"{SIGNIFICANT_SIGMAS:g} sigma of 1, kappa when that predicts the distances no worse "
        f"and it lies beyond {KAPPA_SIGMAS:g} sigma and {100 * BOARD_SCALE_MIN:g} % of 1 "
        f"(holding it would then cost the hand-eye more than estimating it)")
NOT_WARRANTED = ("estimating it neither predicts clearly better nor finds it significantly "
                 "different from 1")


@dataclass(frozen=True)
class ModelCandidate:
    """One model tried: its cross-validation and, for joint models, the model and its fit on
    all stations (None for the pose-only candidates)."""

    name: str
    cv: CrossValidation
    model: JointModel | None = None
    fit: JointFit | None = None


@dataclass(frozen=True)
class Selection:
    """All candidates (``candidates[0]`` the base), the chosen one, and why."""

    candidates: tuple[ModelCandidate, ...]
    chosen: ModelCandidate
    decisions: tuple[str, ...]


def clearly_better(rich: CrossValidation, simple: CrossValidation) -> bool:
    """True when ``rich`` predicts clearly better than ``simple`` (paired over stations).

    Both the RMS must drop by ``MIN_IMPROVEMENT`` and the paired differences of squared
    per-station errors must be positive beyond ``MIN_SIGNIFICANCE`` standard errors: a
    one-station fluke is not evidence.
    """
    return clearly_lower(rich.station_errors(), simple.station_errors())


def clearly_lower(rich: np.ndarray, simple: np.ndarray) -> bool:
    """``clearly_better`` on per-station errors (n,) of any one figure, paired by station."""
    a, b = simple ** 2, rich ** 2
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 2:
        return False
    d = a[ok] - b[ok]
    se = float(np.std(d, ddof=1) / np.sqrt(len(d)))
    drop = 1.0 - np.sqrt(b[ok].mean() / a[ok].mean())
    return bool(drop >= MIN_IMPROVEMENT and d.mean() > MIN_SIGNIFICANCE * se)


def _estimate_reason(rich: ModelCandidate, simple: ModelCandidate, name: str) -> str | None:
    """Why to estimate ``name`` (κ or ν) rather than hold it at 1, or None: not warranted.

    Estimated when that predicts the held-out corners clearly better. κ also when it predicts
    the held-out camera-to-board distances clearly better (``HeldOut.range_m``): the pixel
    figure is dominated by the robot's lateral errors and barely moves with a board 0.5 %
    off, the distance figure is the scale itself (PnP's distance from the board's apparent
    size against the robot's translations). Otherwise estimated when it predicts no worse —
    pixels for ν, distances for κ — and differs from 1 by more than ``SIGNIFICANT_SIGMAS``
    σ for ν, ``KAPPA_SIGMAS`` σ and ``BOARD_SCALE_MIN`` for κ (σ the larger of the formal σ
    and the fold jackknife).

    κ's threshold is where holding stops paying (the mean-squared-error test of a
    restriction, Toro-Vizcarrondo & Wallace, JASA 63:558, 1968: the restricted estimate is
    the better one while the bias it takes is below one σ of the free estimate). A κ held
    at 1 while the board is off by δ moves the hand-eye translation by δ times the
    camera-to-board distance, an error the held model's σ does not contain (3.4-3.7 mm at a
    σ of 0.2 mm on ``benchmarks.kappa_nu``'s 0.5 % board held at 2-3 σ); a κ estimated while
    the board is exact costs that distance times σ_κ, an error its σ does contain. The
    0.2 % floor holds the few-0.1 % κ an arm's systematic errors give an exact board. Whether
    the board is *reported* as off is the separate, stricter ``board_scale`` check (3 σ and
    0.2 %, ``calib.quality``).
    """
    if clearly_better(rich.cv, simple.cv):
        return "predicts held-out stations clearly better than held at 1"
    if clearly_better(simple.cv, rich.cv) or rich.fit is None:
        return None
    rich_range, simple_range = rich.cv.range_errors(), simple.cv.range_errors()
    if name == "kappa":
        if clearly_lower(rich_range, simple_range):
            return ("predicts the held-out camera-to-board distances clearly better than "
                    "held at 1")
        if not _rms(rich_range) <= _rms(simple_range):
            return None
    value = getattr(rich.fit.cell, name)
    formal = float(rich.fit.result(np.arange(len(rich.cv.stations))).sigmas[name])
    jackknife = jackknife_sigmas(rich.cv.estimates, FoldEstimate.of(rich.fit.cell))
    sigma = max(formal, float(jackknife.get(name, 0.0)))
    sigmas, floor = (KAPPA_SIGMAS, BOARD_SCALE_MIN) if name == "kappa" else (
        SIGNIFICANT_SIGMAS, 0.0)
    if abs(value - 1.0) > max(sigmas * sigma, floor):  # see RULE
        return (f"predicts no worse, and {name} = {value:.5f} differs from 1 by "
                f"{abs(value - 1.0) / sigma:.1f} sigma")
    return None


def _rms(errors: np.ndarray) -> float:
    ok = np.isfinite(errors)
    return float(np.sqrt(np.mean(errors[ok] ** 2))) if ok.any() else float("nan")


@dataclass(frozen=True)
class Modes:
    """Which choices are made by prediction (``auto``) and which are forced: ``kappa`` and
    ``nu`` ``estimate``/``fixed``, ``noise`` ``estimate``/``assumed``, ``robot_map``
    ``off`` (the robot's translations as read)."""

    kappa: str = "auto"
    nu: str = "auto"
    noise: str = "auto"
    robot_map: str = "auto"

    def __post_init__(self) -> None:
        if self.kappa not in KAPPA_MODES:
            raise ValueError(f"unknown kappa mode '{self.kappa}': choose one of "
                             f"{', '.join(KAPPA_MODES)}")


def select_joint_model(data: JointData, station_ids: Sequence[str], base: JointModel,
                       start: CellParameters, modes: Modes = Modes()) -> Selection:
    """Cross-validate the base model and its simpler/richer neighbours; pick one.

    ``base`` estimates everything it may (κ unless ``kappa='fixed'``, ν unless held) with the
    assumed noise levels; ``start`` its solution on all stations (a ``JointResult``'s robot
    corrections start every fit's too, else they start at zero); ``modes`` which choices
    are forced. The candidates and their folds are fitted on all cores
    (``calib.parallel``), with the same results as one after the other.
    """
    kappa, nu, noise = modes.kappa, modes.nu, modes.noise
    held = [name for name, mode in (("kappa", kappa), ("nu", nu))
            if name not in base.fix and mode != "estimate"]
    models = [base, *(replace(base, name=f"{name} = 1", fix=(*base.fix, name)) for name in held)]
    if noise != "assumed":
        models.append(replace(base, name="robot noise estimated", estimate_noise=True))
    if modes.robot_map != "off":
        models.append(replace(base, name="robot translation map", robot_map=True))
    corrections = start.corrections if isinstance(start, JointResult) else None
    with fit_pool() as pool:

        def run(models: Sequence[JointModel]) -> list[ModelCandidate]:
            return _run_candidates(_Start(data, tuple(station_ids), base, start, corrections),
                                   models, pool)

        tried = dict(zip((m.name for m in models), run(models), strict=True))
        base_c = tried[base.name]
        candidates = list(tried.values())
        chosen_fix, estimate_noise, decisions = set(base.fix), False, []
        for name, mode in (("kappa", kappa), ("nu", nu)):
            if name not in held:
                decisions.append(f"{name}: {'held' if name in base.fix else 'estimated'} "
                                 f"({'given' if mode != 'auto' else 'known intrinsics'})")
                continue
            why = "given" if mode == "fixed" else _estimate_reason(base_c, tried[f"{name} = 1"],
                                                                   name)
            if why is None or mode == "fixed":
                chosen_fix.add(name)
                why = why or NOT_WARRANTED
                decisions.append(f"{name}: held at 1 ({why})")
            else:
                decisions.append(f"{name}: estimated ({why})")
        if noise != "assumed":
            estimate_noise = noise == "estimate" or clearly_better(
                tried["robot noise estimated"].cv, base_c.cv)
            decisions.append("robot noise: " + ("estimated from the data" if estimate_noise
                                                else "assumed: estimating it does not predict "
                                                     "clearly better"))
        robot_map = modes.robot_map != "off" and clearly_better(
            tried["robot translation map"].cv, base_c.cv)
        if modes.robot_map != "off":
            decisions.append("robot translations: " + (
                "mapped by the estimated linear map (scale and skew of the arm's positions)"
                if robot_map else "as read: estimating their linear map does not predict "
                                  "clearly better"))
        fix = tuple(p for p in base.fix if p in chosen_fix) + tuple(
            p for p in ("kappa", "nu") if p in chosen_fix and p not in base.fix)
        chosen = next((c for c in candidates if c.model is not None
                       and set(c.model.fix) == set(fix)
                       and c.model.estimate_noise == estimate_noise
                       and c.model.robot_map == robot_map), None)
        if chosen is None:
            parts = [" and ".join(p for p in fix if p in ("kappa", "nu")) + " = 1",
                     "robot noise estimated" * estimate_noise,
                     "robot translation map" * robot_map]
            model = replace(base, name=", ".join(p for p in parts if p not in ("", " = 1")),
                            fix=fix, estimate_noise=estimate_noise, robot_map=robot_map)
            chosen = run([model])[0]
            candidates.append(chosen)
    return Selection(candidates=tuple(candidates), chosen=chosen, decisions=tuple(decisions))


@dataclass(frozen=True)
class _Start:
    """What every candidate starts from: the data, the station ids, the base model and its
    solution on all stations (``cell`` and the robot ``corrections`` (n, 6), or None)."""

    data: JointData
    station_ids: tuple[str, ...]
    base: JointModel
    cell: CellParameters
    corrections: np.ndarray | None = None


def _run_candidates(start: _Start, models: Sequence[JointModel],
                    pool: Executor) -> list[ModelCandidate]:
    """Each of ``models`` fitted on all stations (from the base solution, with κ, ν at 1
    where the model holds them and the base does not) and cross-validated from that fit, its
    folds fitted at its assumed or estimated noise levels; every fit a task of ``pool``."""
    data, base = start.data, start.base
    fits = [pool.submit(fit_joint, data, model, held_at_one(
        start.cell, [p for p in ("kappa", "nu") if p in model.fix and p not in base.fix]),
        corrections=start.corrections) for model in models]
    pending = []
    for model, task in zip(models, fits, strict=True):
        fit = task.result()
        job = JointFolds(replace(data, sigma_px=fit.sigma_px), start.station_ids,
                         replace(model, noise=fit.noise, estimate_noise=False), fit.cell,
                         fit.corrections)
        pending.append((model, fit, submit_joint_folds(job, pool)))
    return [ModelCandidate(name=model.name, cv=folds.result(), model=model, fit=fit)
            for model, fit, folds in pending]
