"""The table and figure of the oracle bound (``benchmarks.cold_start_bound``): one row per
blind cell, the stations at which its design's formal σ is first within the tolerance,
against the cold start's from a cold-start benchmark log."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np

from benchmarks.cold_start_report import MAX_STATIONS, TOL_DEG, TOL_MM

matplotlib.use("Agg")
import matplotlib.pyplot as plt


@dataclass
class Row:
    """One cell's oracle bound: σ after each station (deg, mm; index 0 = the start view
    alone) at the calibration's noise, the first station count within the tolerance (-1: not
    within ``MAX_STATIONS``), the ratio (the larger σ / tolerance) at ``stations`` after
    greedy, exchange and the best random restart, the floor's first count (the mock's own
    reading noise, κ and ν known) and the exchanged design's T_base_tcp (start first); what
    its calibration on the mock gave (``calibrated``, {} if it failed), the greedy design's
    T_base_tcp (start first) and the stations from which its calibration's honest σ is
    within the tolerance (``honest_first``; None: not checked)."""

    cell: int
    setup: str
    distance_m: float
    hfov_deg: float
    pool: int
    sigma_deg: list[float]
    sigma_mm: list[float]
    first: int
    ratio_greedy: float
    ratio_exchange: float
    ratio_restart: float
    floor_first: int
    poses: list[list[list[float]]]
    calibrated: dict[str, float] | None = None
    greedy_poses: list[list[list[float]]] | None = None
    honest_first: int | None = None


def read_rows(log: Path) -> list[Row]:
    """The rows a run logged (none if there is no log)."""
    if not log.exists():
        return []
    return [Row(**json.loads(line)) for line in log.read_text().splitlines()]


def write_rows(log: Path, rows: list[Row]) -> None:
    """Log ``rows`` (JSON lines, by cell), replacing the log."""
    log.write_text("".join(json.dumps(vars(r)) + "\n" for r in sorted(rows, key=lambda r: r.cell)))


def table(rows: list[Row], stations: int, cold: dict[int, int]) -> str:
    """Markdown table of the rows and the summary lines; ``cold`` the cold start's stations
    to σ <= tolerance per cell (-1: never)."""
    lines = [f"| cell | setup | board m | HFOV ° | pool | oracle: stations to σ ≤ tol | σ at "
             f"{stations}: deg / mm | σ/tol at {stations}: greedy / exchange / restarts | "
             f"floor: stations | cold start | the design calibrated: honest σ deg / mm "
             f"(robot noise found, mm) | greedy design calibrated: stations to honest σ ≤ "
             f"tol |", "|---" * 12 + "|"]
    for r in sorted(rows, key=lambda r: r.cell):
        n = min(stations, len(r.sigma_deg) - 1)
        lines.append(
            f"| {r.cell} | {r.setup} | {r.distance_m:.2f} | {r.hfov_deg:.0f} | {r.pool} | "
            f"{count(r.first)} | {r.sigma_deg[n]:.4f} / {r.sigma_mm[n]:.3f} | "
            f"{r.ratio_greedy:.2f} / {r.ratio_exchange:.2f} / {r.ratio_restart:.2f} | "
            f"{count(r.floor_first)} | {count(cold.get(r.cell, -2))} | {_calibrated(r)} | "
            f"{'' if r.honest_first is None else count(r.honest_first)} |")
    first = np.array([r.first if r.first >= 0 else 10 * MAX_STATIONS for r in rows])
    slow = [r.cell for r in rows if min(r.ratio_greedy, r.ratio_exchange, r.ratio_restart) > 1]
    lines += ["", f"oracle bound over {len(rows)} cells: stations to σ ≤ tolerance median "
                  f"{np.median(first):g}, p90 {_p90(first)}, max {_p90(first, 100)}; not "
                  f"within {stations} stations under any design tried (greedy, exchange, "
                  f"random restarts): cells {slow or 'none'}"]
    done = [r for r in rows if r.calibrated]
    failed = [r.cell for r in rows if r.calibrated == {}]
    if done:
        over = [r.cell for r in done if not _within(r.calibrated)]
        ratio = np.median([[r.calibrated["formal_deg"] / r.calibrated["predicted_deg"],
                            r.calibrated["formal_mm"] / r.calibrated["predicted_mm"]]
                           for r in done], axis=0)
        lines.append(f"the oracle's {stations} stations calibrated on the mock ({len(done)} "
                     f"cells, failed: {failed or 'none'}): honest σ within the tolerance in "
                     f"{len(done) - len(over)}, not in cells {over or 'none'}; the formal σ "
                     f"over the one predicted at the robot noise the calibration found: median "
                     f"{ratio[0]:.2f} (rotation), {ratio[1]:.2f} (translation)")
    honest = np.array([r.honest_first for r in rows if r.honest_first is not None])
    if len(honest):
        h = np.where(honest < 0, 10 * MAX_STATIONS, honest)
        lines.append(f"the greedy designs calibrated on the mock ({len(h)} cells): stations to "
                     f"honest σ ≤ tolerance median {np.median(h):g}, p90 {_p90(h)}; more than "
                     f"{stations} in {int((h > stations).sum())} cells")
    both = [(r.first, cold[r.cell]) for r in rows if r.cell in cold]
    if both:
        c = np.array([n if n >= 0 else 10 * MAX_STATIONS for _, n in both])
        lines.append(f"the cold start on the same cells (log): median {np.median(c):g}, p90 "
                     f"{_p90(c)}; more than {stations} stations in "
                     f"{int((c > stations).sum())} of {len(c)} cells")
    return "\n".join(lines)


def _within(c: dict[str, float]) -> bool:
    return c["honest_deg"] <= TOL_DEG and c["honest_mm"] <= TOL_MM


def _calibrated(r: Row) -> str:
    c = r.calibrated
    if c is None:
        return ""
    if not c:
        return "calibration failed"
    return f"{c['honest_deg']:.4f} / {c['honest_mm']:.3f} ({c['noise_mm']:.2f})"


def count(n: int) -> str:
    """A station count as the table shows it (-1: not within ``MAX_STATIONS``)."""
    return {-1: f">{MAX_STATIONS}", -2: "n/a"}.get(n, str(n))


def _p90(values: np.ndarray, q: float = 90) -> str:
    p = float(np.percentile(values, q))
    return f">{MAX_STATIONS}" if p > MAX_STATIONS else f"{p:g}"


def read_cold_start(log: Path) -> dict[int, int]:
    """``tol_stations`` of the "cold start" entries of a cold-start benchmark log (none if
    there is no log)."""
    if not log.exists():
        return {}
    out = {}
    for line in log.read_text().splitlines():
        entry = json.loads(line)["cold start"]
        out[int(entry["cell"])] = int(entry["tol_stations"])
    return out


def plot(rows: list[Row], cold: dict[int, int], stations: int, path: Path) -> None:
    """Per cell, the oracle's stations to σ <= tolerance (formal; honest when calibrated)
    against the cold start's."""
    rows = sorted(rows, key=lambda r: r.cell)
    x = np.array([r.cell for r in rows])
    top = MAX_STATIONS + 4

    def shown(n: int) -> float:
        return top if n < 0 else n

    fig, ax = plt.subplots(figsize=(12, 5.2))
    eih = np.array([r.setup == "eye_in_hand" for r in rows])
    oracle = np.array([shown(r.first) for r in rows])
    ax.scatter(x[eih], oracle[eih], marker="o", color="C0", label="oracle bound, eye-in-hand")
    ax.scatter(x[~eih], oracle[~eih], marker="s", color="C0", facecolor="none",
               label="oracle bound, eye-to-hand")
    checked = [r for r in rows if r.honest_first is not None]
    if checked:
        ax.scatter([r.cell for r in checked], [shown(r.honest_first) for r in checked],
                   marker="+", s=70, color="C2", label="greedy design calibrated: honest σ")
    has = np.array([r.cell in cold for r in rows])
    if has.any():
        ax.scatter(x[has], [shown(cold[r.cell]) for r in rows if r.cell in cold], marker="x",
                   color="C3", label="cold start (benchmark log)")
    over = [r.cell for r in rows if r.calibrated is not None
            and not (r.calibrated and _within(r.calibrated))]
    if over:
        ax.scatter(over, [stations] * len(over), marker="v", s=60, color="C1",
                   label=f"the oracle's {stations} calibrated: honest σ above the tolerance "
                         "(or the calibration failed)")
    ax.axhline(stations, color="k", lw=0.8, ls="--", label=f"{stations} stations")
    ax.axhline(top, color="grey", lw=0.6, ls=":")
    ax.set_xlabel("blind cell")
    ax.set_ylabel("stations to σ ≤ 0.5 mm / 0.05°")
    ax.set_title("Oracle designs (the truth, greedy A-optimal: formal σ; calibrated on the mock: "
                 f"honest σ) against the cold start; top row: not within {MAX_STATIONS}",
                 fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
