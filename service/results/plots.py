"""The plots of the calibration report (``service.results.report``): matplotlib figures as PNG
bytes.

Per-station errors, residual vectors over the image, corner coverage, hand-eye and κ / ν
uncertainty, and the model selection, each from a typed result (``cellcal/result@1``) and
only when the result holds what it needs.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from calib import COVERAGE_GRID, BoardScale, Result, image_coverage

log = logging.getLogger("cellcal.service")

#: Figure width (inches) and resolution: sharp on paper, a few tens of kB per PNG.
_FIG_WIDTH_IN = 7.2
_DPI = 110
#: Grid of the coverage heat-map (cells across the image width; rows keep the aspect).
_COVERAGE_COLS = 16


@dataclass(frozen=True)
class Plot:
    """One embedded figure: a stable ``key`` (the HTML id ``fig-<key>``), title, caption."""

    key: str
    title: str
    caption: str
    png: bytes


def report_plots(result: Result) -> list[Plot]:
    """Every plot the result's contents allow, in report order; a plot whose data a
    hand-edited result has spoiled (text for numbers, ragged arrays) is left out."""
    makers: list[Callable[[Result], Plot | None]] = [
        _plot_station_errors, _plot_residuals, _plot_coverage, _plot_uncertainty,
        _plot_model_selection]
    return [p for p in (_drawn(make, result) for make in makers) if p is not None]


def _drawn(make: Callable[[Result], Plot | None], result: Result) -> Plot | None:
    """``make(result)``, or None (logged) if the document's data cannot be drawn."""
    try:
        return make(result)
    except (TypeError, ValueError, KeyError, IndexError) as exc:
        log.warning("report: %s left out (%s: %s)", make.__name__, type(exc).__name__, exc)
        return None


def cv_by_station(result: Result) -> dict[str, float]:
    """Cross-validated pixel error per station id (image stations only)."""
    cv = result.cross_validation
    return {} if cv is None else {s.id: s.rms_px for s in cv.stations if s.rms_px is not None}


# ---- plots ---------------------------------------------------------------------------------

def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI, bbox_inches="tight", metadata={"Software": None})
    return buf.getvalue()


def _new_figure(height_in: float, ncols: int = 1) -> tuple[Figure, Sequence[Any]]:
    fig = Figure(figsize=(_FIG_WIDTH_IN, height_in), layout="constrained")
    axes = fig.subplots(1, ncols, squeeze=False)[0]
    return fig, axes


def _plot_station_errors(result: Result) -> Plot | None:
    stations = result.stations or []
    if not stations or result.camera is None:
        return None
    ids = [s.id for s in stations]
    cv = cv_by_station(result)
    series = [("fit (model with robot correction)", [s.rms_px for s in stations], "#4c72b0")]
    if any(s.chain_rms_px is not None for s in stations):
        series.append(("predicted from robot pose (all stations in the fit)",
                       [s.chain_rms_px for s in stations], "#dd8452"))
    if cv:
        series.append(("cross-validated (station held out)", [cv.get(i) for i in ids],
                       "#c44e52"))
    fig, (ax,) = _new_figure(2.9)
    x = np.arange(len(ids))
    width = 0.8 / len(series)
    for k, (label, values, colour) in enumerate(series):
        y = np.array([np.nan if v is None else v for v in values], dtype=float)
        ax.bar(x + (k - (len(series) - 1) / 2) * width, y, width, label=label, color=colour)
    ax.set_xticks(x, ids, rotation=90 if len(ids) > 20 else 0, fontsize=8)
    ax.set_xlabel("station")
    ax.set_ylabel("RMS error (px)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(series),
              frameon=False)
    return Plot("station-errors", "Per-station errors",
                "RMS pixel error of each station's board corners: the fitted model, the "
                "prediction from the robot pose through the hand-eye, and the prediction "
                "for a station left out of the calibration (cross-validation). A station far "
                "above the others is suspect.", _png(fig))


def _corner_arrays(result: Result) -> tuple[np.ndarray, np.ndarray] | None:
    """All stations' detected corners and residuals, each (M, 2), or None if not stored."""
    corners, residuals = [], []
    for s in result.stations or []:
        if s.corners_px is not None:
            corners.append(np.asarray(s.corners_px, dtype=float))
            if s.residuals_px is not None:
                residuals.append(np.asarray(s.residuals_px, dtype=float))
    if not corners:
        return None
    c = np.concatenate(corners)
    r = np.concatenate(residuals) if len(residuals) == len(corners) else np.full_like(c, np.nan)
    return c, r


def _image_axes(ax: Any, size: Sequence[int]) -> None:
    ax.set_xlim(0, size[0])
    ax.set_ylim(size[1], 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def _plot_residuals(result: Result) -> Plot | None:
    arrays, camera = _corner_arrays(result), result.camera
    if arrays is None or camera is None or np.isnan(arrays[1]).all():
        return None
    corners, res = arrays
    size = camera.image_size
    length = np.linalg.norm(res, axis=1)
    # Arrows scaled so the 95th-percentile residual spans 4 % of the image width.
    ref = float(np.percentile(length, 95)) or 1.0
    gain = 0.04 * size[0] / ref
    fig, (ax,) = _new_figure(_FIG_WIDTH_IN * size[1] / size[0] + 0.5)
    q = ax.quiver(corners[:, 0], corners[:, 1], res[:, 0] * gain, -res[:, 1] * gain, length,
                  cmap="viridis", angles="xy", scale_units="xy", scale=1, width=0.0022)
    key = float(f"{ref:.1g}")
    ax.quiverkey(q, 0.86, 1.03, key * gain, f"{key:g} px", labelpos="E", coordinates="axes")
    fig.colorbar(q, ax=ax, label="residual (px)", shrink=0.8)
    _image_axes(ax, size)
    return Plot("residuals", "Residual vectors over the image",
                f"Projected minus detected corner for every corner of every used station, "
                f"magnified {gain:.0f}x. Random directions mean a good camera model; arrows "
                "that swirl or grow towards the edges point to unmodelled lens distortion.",
                _png(fig))


def _plot_coverage(result: Result) -> Plot | None:
    arrays, camera = _corner_arrays(result), result.camera
    if arrays is None or camera is None:
        return None
    corners = arrays[0]
    w, h = camera.image_size
    nx = _COVERAGE_COLS
    ny = max(1, round(nx * h / w))
    counts, _, _ = np.histogram2d(corners[:, 0], corners[:, 1], bins=(nx, ny),
                                  range=((0, w), (0, h)))
    covered, empty_corners = image_coverage(corners, (w, h))
    fig, (ax,) = _new_figure(_FIG_WIDTH_IN * h / w + 0.5)
    masked = np.ma.masked_equal(counts.T, 0)
    im = ax.imshow(masked, extent=(0, w, h, 0), cmap="magma_r", interpolation="nearest",
                   vmin=0)
    ax.set_facecolor("#f6d3d0")
    ax.plot(corners[:, 0], corners[:, 1], ",", color="#1f4e79", alpha=0.5)
    fig.colorbar(im, ax=ax, label=f"corners per cell ({w / nx:.0f}×{h / ny:.0f} px)",
                 shrink=0.8)
    _image_axes(ax, (w, h))
    return Plot("coverage", "Image coverage",
                f"Detected corners of all used stations ({len(corners)}) counted in a "
                f"{nx}x{ny} grid; pink cells hold no corner. Coverage {covered:.0%} (corners "
                f"in {covered * COVERAGE_GRID ** 2:.0f} of the image's {COVERAGE_GRID}x"
                f"{COVERAGE_GRID} cells, the figure the verdict and the page use; "
                f"{empty_corners} of 4 image corners empty). Distortion is only determined "
                "where corners were seen: fill the image corners and edges.", _png(fig))


def _plot_uncertainty(result: Result) -> Plot | None:
    unc = result.uncertainty
    if result.hand_eye is None or unc is None or unc.hand_eye_trans_m is None:
        return None
    fig, axes = _new_figure(2.6, ncols=3)
    spread = unc.jackknife or {}
    axis_names = ["x", "y", "z"]
    for ax, key, reported_m, scale, unit in (
            (axes[0], "hand_eye_trans_m", unc.hand_eye_trans_m, 1e3, "mm"),
            (axes[1], "hand_eye_rot_rad", unc.hand_eye_rot_rad, 180 / np.pi, "deg")):
        reported = np.asarray(reported_m, dtype=float) * scale
        x = np.arange(3)
        ax.bar(x - 0.2, reported, 0.4, label="reported 1σ", color="#4c72b0")
        if spread.get(key) is not None:
            ax.bar(x + 0.2, np.asarray(spread[key], dtype=float) * scale, 0.4,
                   label="jackknife spread", color="#dd8452")
        ax.set_xticks(x, axis_names)
        ax.set_title(f"hand-eye {'translation' if unit == 'mm' else 'rotation'} 1σ ({unit})",
                     fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    _kappa_nu_axes(axes[2], result.target)
    return Plot("uncertainty", "Hand-eye and board uncertainty",
                "Left, middle: the hand-eye's 1σ per axis (translation in mm, rotation in "
                "degrees) as reported" + (" and as spread between calibrations on subsets of "
                                          "the stations (jackknife)" if spread else "")
                + ". Right: board scale κ and aspect ν with ±3σ, as a deviation from the "
                "nominal board in percent; κ far from 0 % means the printed squares are not "
                "the size entered.", _png(fig))


def _kappa_nu_axes(ax: Any, target: BoardScale) -> None:
    names = ["kappa", "nu"]
    dev = [100 * (target.kappa - 1), 100 * (target.nu - 1)]
    err = [300 * (target.kappa_sigma or 0.0), 300 * (target.nu_sigma or 0.0)]
    ax.errorbar(range(len(names)), dev, yerr=err, fmt="o", capsize=5, color="#c44e52")
    for k, d in enumerate(dev):
        ax.annotate(f"{d:+.2f} %", (k, d), textcoords="offset points", xytext=(8, 0),
                    fontsize=8, va="center")
    ax.axhline(0.0, color="#555", lw=0.8)
    ax.set_xticks(range(len(names)), ["κ" if n == "kappa" else "ν" for n in names])
    ax.set_xlim(-0.6, len(names) - 0.2)
    ax.set_title("board: deviation from nominal (%)", fontsize=9)
    ax.grid(axis="y", alpha=0.3)


def _plot_model_selection(result: Result) -> Plot | None:
    selection = result.model_selection
    candidates = [] if selection is None else [c for c in selection.candidates
                                               if c.cv_rms_px is not None]
    if selection is None or not candidates:
        return None
    chosen = selection.chosen
    names = [c.name for c in candidates]
    values = [c.cv_rms_px for c in candidates]
    fig, (ax,) = _new_figure(0.5 + 0.32 * len(names))
    colours = ["#1b7a3a" if n == chosen else "#9aa7b8" for n in names]
    y = np.arange(len(names))
    ax.barh(y, values, color=colours)
    for k, v in enumerate(values):
        ax.annotate(f"{v:.3f}", (v, k), textcoords="offset points", xytext=(4, 0),
                    va="center", fontsize=8)
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("cross-validated prediction error (px)")
    ax.grid(axis="x", alpha=0.3)
    return Plot("model-selection", "Model selection",
                "Each candidate model's cross-validated pixel error; the chosen one (green) "
                "is the simplest that predicts unseen stations about as well as the best.",
                _png(fig))
