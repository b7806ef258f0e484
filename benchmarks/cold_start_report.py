"""What the cold-start benchmark (``benchmarks.cold_start``) records per method and cell, and
its table and figure: the outcomes, the success criterion (the acceptance's, module docstring
there), the log a run appends to and ``--from-log`` reads, the acceptance lines of the cold
start and the plot."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib
import numpy as np

from calib import COVERAGE_90

matplotlib.use("Agg")
import matplotlib.pyplot as plt

TOL_DEG, TOL_MM, MAX_STATIONS = 0.05, 0.5, 40
METHODS = ("cold start", "easy_handeye", "random", "oracle")
#: The service computes the honest σ from this many images on
#: (``service.runs.coldstart.MIN_HONEST_STATIONS``).
FIRST_CHECK = 8


@dataclass
class Outcome:
    """One method on one cell."""

    stations: int = 0
    explore: int = 0
    lost: int = 0
    refused: int = 0
    err_deg: float = np.nan
    err_mm: float = np.nan
    sigma_deg: float = np.nan
    sigma_mm: float = np.nan
    met: bool = False
    bound_met: bool = False
    tol_stations: int = -1
    tol_explore: int = 0
    plan_s: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    next_check: int = 0
    hand_eye: list[list[float]] | None = None
    rf_deg: float = np.nan
    rf_mm: float = np.nan
    rigid_deg: float = np.nan
    rigid_mm: float = np.nan
    own_deg: float = np.nan
    own_mm: float = np.nan
    cell: int = -1
    verdict: str = ""  # the result's, given the tolerance (empty in logs from before it)
    stations_at: list[int] = field(default_factory=list)
    explore_at: list[int] = field(default_factory=list)
    last_miss: int = FIRST_CHECK - 1

    @property
    def success(self) -> bool:
        """The acceptance's success: judged against the hand-eye the readings see
        (``readings_hand_eye``; module docstring)."""
        return _success(self.rf_deg, self.rf_mm, self)

    @property
    def flange_success(self) -> bool:
        """Success against the true hand-eye (the physical flange), the second figure."""
        return _success(self.err_deg, self.err_mm, self)


def _success(err_deg: float, err_mm: float, out: Outcome) -> bool:
    return bool(err_deg <= 0.1 and err_mm <= 1.0
                and err_deg <= 2 * out.sigma_deg and err_mm <= 2 * out.sigma_mm)


def bound(sigma: float) -> float:
    """The 90 % bound on the error norm of a reported σ (``calib.COVERAGE_90``)."""
    return COVERAGE_90 * sigma


def read_log(log: Path) -> dict[str, list[Outcome]]:
    """The outcomes a run wrote to ``log``."""
    results: dict[str, list[Outcome]] = {m: [] for m in METHODS}
    for line in log.read_text().splitlines():
        for m, o in json.loads(line).items():
            results[m].append(Outcome(**o))
    return results


def table(results: dict[str, list[Outcome]]) -> str:
    rows = ["| method | success | success (true flange) | σ ≤ tolerance "
            "| stations median / p90 | exploratory median "
            "| lost views | out-of-box commands | planning CPU s/step max | wall s median "
            "| error median deg / mm | error / σ median (rot, trans) |",
            "|---" * 12 + "|"]
    for name, outs in results.items():
        st = np.array([o.stations for o in outs])
        ratio_r = np.nanmedian([o.rf_deg / o.sigma_deg for o in outs])
        ratio_t = np.nanmedian([o.rf_mm / o.sigma_mm for o in outs])
        plan = [max(o.plan_s) for o in outs if o.plan_s]
        rows.append(
            f"| {name} | {np.mean([o.success for o in outs]):.0%} | "
            f"{np.mean([o.flange_success for o in outs]):.0%} | "
            f"{np.mean([o.met or o.tol_stations >= 0 for o in outs]):.0%} | "
            f"{np.median(st):.0f} / {np.percentile(st, 90):.0f} | "
            f"{np.median([o.explore for o in outs]):.0f} | "
            f"{sum(o.lost for o in outs)} | {sum(o.refused for o in outs)} | "
            f"{max(plan) if plan else float('nan'):.2f} | "
            f"{np.median([o.wall_s for o in outs]):.1f} | "
            f"{np.nanmedian([o.rf_deg for o in outs]):.3f} / "
            f"{np.nanmedian([o.rf_mm for o in outs]):.2f} | {ratio_r:.2f}, {ratio_t:.2f} |")
    return "\n".join([*rows, "", *_cold_start_lines(results)])


def _verdicts(outs: list[Outcome]) -> str:
    """How many results got each verdict, e.g. ``pass 44, warn 6``."""
    names = sorted({o.verdict or "not recorded" for o in outs})
    return ", ".join(f"{n} {sum((o.verdict or 'not recorded') == n for o in outs)}"
                     for n in names)


def _cold_start_lines(results: dict[str, list[Outcome]]) -> list[str]:
    """The cold start against the acceptance: stations to σ <= tolerance, the tolerance
    runs' coverage, stations against random's for the same σ, planning CPU."""
    cs, rnd = results["cold start"], results["random"]
    reached = np.array([o.tol_stations for o in cs if o.tol_stations >= 0])
    explore = [o.tol_explore for o in cs if o.tol_stations >= 0]
    stopped = [o for o in cs if o.bound_met]
    within = [o.rf_deg <= TOL_DEG and o.rf_mm <= TOL_MM for o in cs]
    within_fl = [o.err_deg <= TOL_DEG and o.err_mm <= TOL_MM for o in cs]
    both = [(a, b.stations) for a, b in zip(cs, rnd, strict=True)
            if a.tol_stations >= 0 and b.met]
    ratio = np.median([a.tol_stations / b for a, b in both]) if both else float("nan")
    ratio_all = (np.median([(a.tol_stations + a.tol_explore + 1) / b for a, b in both])
                 if both else float("nan"))
    bad = sum(o.rf_deg > 2 * o.sigma_deg or o.rf_mm > 2 * o.sigma_mm for o in cs)
    bad_fl = sum(o.err_deg > 2 * o.sigma_deg or o.err_mm > 2 * o.sigma_mm for o in cs)
    bad_pass = sum(o.verdict == "pass" and (o.rf_deg > 2 * o.sigma_deg
                                            or o.rf_mm > 2 * o.sigma_mm) for o in cs)
    steps = np.concatenate([o.plan_s for o in cs])
    if not len(reached) or not stopped:
        return [f"cold start: σ ≤ tolerance held in {len(reached)} and the 90 % bound in "
                f"{len(stopped)} of {len(cs)} runs; results with error > 2x σ: {bad}"]
    return [
        f"cold start, σ ≤ tolerance ({TOL_MM} mm / {TOL_DEG}°, honest σ) first held in "
        f"{len(reached)} of {len(cs)} runs, after {np.median(reached):.0f} stations median, "
        f"{np.percentile(reached, 90):.0f} p90, max {reached.max()}, plus "
        f"{np.median(explore):.0f} exploratory moves median (max {max(explore)}); stations / "
        f"random's for the same σ ({len(both)} cells where both reached it): median "
        f"{ratio:.2f} (all images, start and exploratory moves included: {ratio_all:.2f})",
        f"cold start, tolerance runs (stop when the 90 % bound, {COVERAGE_90} σ, is within "
        f"the tolerance, or at {MAX_STATIONS} stations): the bound met in {len(stopped)} of "
        f"{len(cs)} runs, after {np.median([o.stations for o in stopped]):.0f} stations "
        f"median; error (readings frame) within the tolerance in "
        f"{np.mean([w for w, o in zip(within, cs, strict=True) if o.bound_met]):.0%} of "
        f"those and {np.mean(within):.0%} of all runs; results with error > 2x σ: {bad}, "
        f"of them stored as pass: {bad_pass} (verdicts given the tolerance: "
        f"{_verdicts(cs)}); "
        f"against the true flange: within the tolerance in "
        f"{np.mean([w for w, o in zip(within_fl, cs, strict=True) if o.bound_met]):.0%} of "
        f"those and {np.mean(within_fl):.0%} of all runs, error > 2x σ: {bad_fl}",
        f"cold start against the readings frame without a common scale of the readings' "
        f"translations (readings_hand_eye(scale=False), a rigid fit): success "
        f"{np.mean([_success(o.rigid_deg, o.rigid_mm, o) for o in cs]):.0%}, error > 2x σ: "
        f"{sum(o.rigid_deg > 2 * o.sigma_deg or o.rigid_mm > 2 * o.sigma_mm for o in cs)}, "
        f"error median {np.nanmedian([o.rigid_mm for o in cs]):.2f} mm (with the scale "
        f"{np.nanmedian([o.rf_mm for o in cs]):.2f} mm), smaller with the scale in "
        f"{np.mean([o.rf_mm < o.rigid_mm for o in cs]):.0%} of the cells",
        f"cold start against the readings frame over each result's own stations "
        f"(readings_hand_eye(poses=...); its scale is ill-determined where they cluster): "
        f"success "
        f"{np.mean([_success(o.own_deg, o.own_mm, o) for o in cs]):.0%}, error > 2x σ: "
        f"{sum(o.own_deg > 2 * o.sigma_deg or o.own_mm > 2 * o.sigma_mm for o in cs)}; the "
        f"box's frame differs from it by median {np.nanmedian(_frame_gap(cs, 0)):.3f}° / "
        f"{np.nanmedian(_frame_gap(cs, 1)):.2f} mm of error",
        f"cold start planning CPU per step (a proposal plus the refit after its image): median "
        f"{np.median(steps):.3f} s, p99 {np.percentile(steps, 99):.2f} s, max "
        f"{steps.max():.2f} s"]


def _frame_gap(outs: list[Outcome], part: int) -> np.ndarray:
    """How much more error (deg for ``part`` 0, mm for 1) each result has against the box's
    readings frame than against its own stations' (negative: less)."""
    return np.array([(o.rf_deg - o.own_deg, o.rf_mm - o.own_mm)[part] for o in outs])


def plot(results: dict[str, list[Outcome]], path: Path) -> None:
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name in ("cold start", "random", "easy_handeye", "oracle"):
        outs = results[name]
        a.scatter([o.sigma_mm for o in outs], [o.rf_mm for o in outs], s=14, label=name)
    cs = results["cold start"]
    a.scatter([o.sigma_mm for o in cs], [o.err_mm for o in cs], s=16, facecolors="none",
              edgecolors="k", lw=0.6, label="cold start, against the true flange")
    lim = np.nanmax([o.sigma_mm for outs in results.values() for o in outs] + [1.0])
    a.plot([0, lim], [0, 2 * lim], "k--", lw=0.8, label="error = 2σ")
    a.set_xscale("log"), a.set_yscale("log")
    a.set_xlabel("reported σ (mm)"), a.set_ylabel("hand-eye error, readings frame (mm)")
    a.legend(fontsize=8), a.set_title("true error against reported σ")
    cs = [o.tol_stations + o.tol_explore + 1 for o in results["cold start"]
          if o.tol_stations >= 0]
    rnd = [o.stations for o in results["random"] if o.met]
    bins = np.arange(0, 45, 2)
    b.hist(cs, bins=bins, alpha=0.7, label="cold start (start + exploratory + stations)")
    b.hist(rnd, bins=bins, alpha=0.7, label="random poses (stations)")
    b.set_xlabel("images to reach 0.5 mm / 0.05° (honest σ)"), b.set_ylabel("cells")
    b.legend(fontsize=8), b.set_title("how many images the tolerance takes")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
