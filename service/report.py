"""The calibration report: one self-contained HTML page a person reads, prints and files.

:func:`render_report` turns a result document (``cellcal/result@1``) into HTML with the verdict
and its findings on top, the key figures with their uncertainty, plots (per-station errors,
residual vectors over the image, corner coverage, hand-eye and κ / ν uncertainty, model
selection) and the station table with every rejected station and its reason. Plots are
matplotlib PNGs embedded as base64 ``data:`` URIs and the style is inline, so the file needs
nothing else: no network, no other file. Units for people: mm, degrees, pixels.

It reads the result's ``quality``, ``cross_validation``, ``model_selection`` and
``uncertainty`` blocks when they are there and says so when they are not (older results).
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.figure import Figure

Result = Mapping[str, Any]

#: Figure width (inches) and resolution: sharp on paper, a few tens of kB per PNG.
_FIG_WIDTH_IN = 7.2
_DPI = 110
_VERDICT_COLOURS = {"pass": "#1b7a3a", "warn": "#b26a00", "fail": "#b3261e"}
_SEVERITY_ORDER = {"fail": 0, "error": 0, "warn": 1, "warning": 1, "info": 2}
#: Grid of the coverage heat-map (cells across the image width; rows keep the aspect).
_COVERAGE_COLS = 16

_CSS = """
body { font: 13px/1.45 -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #1d1d1f;
       max-width: 820px; margin: 24px auto; padding: 0 16px; }
h1 { font-size: 22px; margin: 0 0 2px; }
h2 { font-size: 16px; border-bottom: 1px solid #ccc; padding-bottom: 3px; margin: 22px 0 8px; }
.sub { color: #555; margin: 0 0 12px; }
.verdict { border: 2px solid; border-radius: 6px; padding: 10px 14px; margin: 12px 0; }
.verdict .word { font-size: 20px; font-weight: 700; text-transform: uppercase; }
.finding { margin: 4px 0 0 0; }
.sev { display: inline-block; min-width: 44px; font-weight: 600; text-transform: uppercase;
       font-size: 11px; }
.code { font-family: Menlo, Consolas, monospace; font-size: 12px; color: #444; }
table { border-collapse: collapse; width: 100%; font-size: 12px; }
th, td { border-bottom: 1px solid #e3e3e3; padding: 3px 6px; text-align: right; }
th { background: #f3f3f3; }
td.l, th.l { text-align: left; }
tr.rejected td { color: #8a1c14; background: #fdf1f0; }
figure { margin: 12px 0 18px; break-inside: avoid; page-break-inside: avoid; }
figure img { width: 100%; height: auto; }
figcaption { color: #444; font-size: 12px; }
.kv td:first-child { text-align: left; color: #444; width: 34%; }
.kv td { text-align: left; }
.note { color: #555; font-size: 12px; }
@media print { body { margin: 0; max-width: none; } h2 { break-after: avoid; } }
"""


@dataclass(frozen=True)
class Plot:
    """One embedded figure: a stable ``key`` (the HTML id ``fig-<key>``), title, caption."""

    key: str
    title: str
    caption: str
    png: bytes


def render_report(result: Result) -> str:
    """The HTML report of a result document, as one self-contained string."""
    parts = [
        _header(result),
        _verdict(result.get("quality")),
        _summary(result),
        "<h2>Plots</h2>",
        *(_figure(p) for p in report_plots(result)),
        _station_table(result),
        _provenance(result),
    ]
    title = html.escape(f"cellcal calibration report — {result.get('setup', '')}")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{title}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(parts) + "\n</body></html>\n")


def report_plots(result: Result) -> list[Plot]:
    """Every plot the result's contents allow, in report order."""
    makers: list[Callable[[Result], Plot | None]] = [
        _plot_station_errors, _plot_residuals, _plot_coverage, _plot_uncertainty,
        _plot_model_selection]
    return [p for p in (make(result) for make in makers) if p is not None]


# ---- text sections -------------------------------------------------------------------------

def _esc(value: Any) -> str:
    return html.escape(str(value))


def _header(result: Result) -> str:
    software = result.get("software") or {}
    camera = result.get("camera") or {}
    size = camera.get("image_size")
    n_used, n_rej = len(result.get("stations") or []), len(result.get("rejected") or [])
    facts = [
        f"setup <b>{_esc(result.get('setup', '?'))}</b>",
        f"method <b>{_esc(result.get('method', '?'))}</b>",
        f"{n_used} stations used, {n_rej} rejected",
        f"image {size[0]}×{size[1]} px" if size else "pose-only (no camera model)",
        f"created {_esc(result.get('created', '?'))}",
        f"cellcal {_esc(software.get('version', '?'))}",
    ]
    return ("<h1>Calibration report</h1>"
            f"<p class=\"sub\">{' · '.join(facts)}</p>")


def _verdict(quality: Mapping[str, Any] | None) -> str:
    if not quality:
        return ("<div class=\"verdict\" style=\"border-color:#888\"><span class=\"word\">"
                "no verdict</span><p class=\"finding\">This result carries no quality "
                "assessment (made by an older cellcal); judge it by the figures below.</p>"
                "</div>")
    verdict = str(quality.get("verdict", "?"))
    colour = _VERDICT_COLOURS.get(verdict, "#555")
    findings = sorted(quality.get("findings") or [],
                      key=lambda f: _SEVERITY_ORDER.get(str(f.get("severity")), 3))
    items = "".join(
        f"<p class=\"finding\"><span class=\"sev\" style=\"color:"
        f"{_VERDICT_COLOURS.get(_verdict_of(f.get('severity')), '#555')}\">"
        f"{_esc(f.get('severity', ''))}</span> {_esc(f.get('message', ''))} "
        f"<span class=\"code\">[{_esc(f.get('code', ''))}]</span></p>" for f in findings)
    if not findings:
        items = "<p class=\"finding\">No findings: every check passed.</p>"
    return (f"<div class=\"verdict\" style=\"border-color:{colour}\">"
            f"<span class=\"word\" style=\"color:{colour}\">{_esc(verdict)}</span>{items}</div>")


def _verdict_of(severity: Any) -> str:
    return {"fail": "fail", "error": "fail", "warn": "warn", "warning": "warn"}.get(
        str(severity), "pass")


def _summary(result: Result) -> str:
    rows = _camera_rows(result) + _pose_rows(result) + _error_rows(result)
    body = "".join(f"<tr><td>{_esc(k)}</td><td>{v}</td></tr>" for k, v in rows)
    note = (result.get("uncertainty") or {}).get("note")
    return ("<h2>Result</h2><table class=\"kv\">" + body + "</table>"
            + (f"<p class=\"note\">Uncertainty: {_esc(note)}</p>" if note else ""))


def _pm(value: float, sigma: float | None, fmt: str = ".3f") -> str:
    if sigma is None or not np.isfinite(sigma) or sigma == 0:
        return format(value, fmt)
    return f"{value:{fmt}} ± {sigma:{fmt}}"


def _camera_rows(result: Result) -> list[tuple[str, str]]:
    camera = result.get("camera")
    rows: list[tuple[str, str]] = []
    if camera:
        K = np.asarray(camera["K"])
        cs = ((result.get("uncertainty") or {}).get("camera")) or {}
        rows.append(("focal length fx, fy (px)", f"{_pm(K[0, 0], cs.get('fx'), '.2f')}, "
                                                 f"{_pm(K[1, 1], cs.get('fy'), '.2f')}"))
        rows.append(("principal point cx, cy (px)", f"{_pm(K[0, 2], cs.get('cx'), '.2f')}, "
                                                    f"{_pm(K[1, 2], cs.get('cy'), '.2f')}"))
        rows.append(("distortion k1 k2 p1 p2 k3",
                     " ".join(f"{v:.5f}" for v in np.ravel(camera["dist"]))))
    target = result.get("target") or {}
    if "kappa" in target:
        rows.append(("board scale κ (true / nominal square)",
                     _pm(target["kappa"], target.get("kappa_sigma"), ".5f")))
    if "nu" in target:
        rows.append(("board aspect ν", _pm(target["nu"], target.get("nu_sigma"), ".5f")))
    return rows


def _pose_rows(result: Result) -> list[tuple[str, str]]:
    rows = []
    frames = {"eye_in_hand": ("tcp_T_cam", "base_T_target"),
              "eye_to_hand": ("base_T_cam", "tcp_T_target")}.get(result.get("setup", ""),
                                                                 ("hand_eye", "target_pose"))
    unc = result.get("uncertainty") or {}
    for key, frame in zip(("hand_eye", "target_pose"), frames, strict=True):
        block = result.get(key)
        if not block:
            continue
        pose = np.asarray(block["pose"], dtype=float)
        t_sd = unc.get(f"{key}_trans_m")
        r_sd = unc.get(f"{key}_rot_rad")
        t_txt = ", ".join(_pm(v * 1e3, None if t_sd is None else s * 1e3, ".2f")
                          for v, s in zip(pose[:3], t_sd or [None] * 3, strict=True))
        rows.append((f"{frame}: translation x, y, z (mm)", t_txt))
        if r_sd is not None:
            rows.append((f"{frame}: rotation 1σ about x, y, z (°)",
                         ", ".join(f"{np.rad2deg(s):.3f}" for s in r_sd)))
        rows.append((f"{frame}: UR pose (m, rad)",
                     "p[" + ", ".join(f"{v:.5f}" for v in pose) + "]"))
    return rows


def _error_rows(result: Result) -> list[tuple[str, str]]:
    rows = []
    camera = result.get("camera") or {}
    if "rms_px" in camera:
        rows.append(("reprojection RMS of the fit (px)", f"{camera['rms_px']:.3f}"))
    cv = result.get("cross_validation") or {}
    if cv.get("rms_px") is not None:
        mm = cv.get("rms_mm")
        rows.append((f"cross-validated prediction error ({cv.get('folds', '?')} folds)",
                     f"{cv['rms_px']:.3f} px" + (f" ≈ {mm:.2f} mm at the board"
                                                 if mm is not None else "")))
    validation = result.get("validation") or {}
    if validation.get("chain_rms_px") is not None:
        rows.append(("prediction from the robot poses, all stations (px)",
                     f"{validation['chain_rms_px']:.3f}"))
    return rows


def _figure(plot: Plot) -> str:
    data = base64.b64encode(plot.png).decode("ascii")
    return (f"<figure id=\"fig-{plot.key}\"><img alt=\"{_esc(plot.title)}\" "
            f"src=\"data:image/png;base64,{data}\"><figcaption><b>{_esc(plot.title)}.</b> "
            f"{_esc(plot.caption)}</figcaption></figure>")


def _station_table(result: Result) -> str:
    stations = result.get("stations") or []
    cv = _cv_by_station(result)
    pose_only = not result.get("camera")
    head = (["station", "rot. residual (°)", "trans. residual (mm)"] if pose_only else
            ["station", "corners", "fit RMS (px)", "robot-pose RMS (px)", "CV (px)",
             "robot correction (°, mm)", "Mahalanobis"])
    rows = [_station_row(s, cv, pose_only) for s in stations]
    width = len(head) - 1
    rows += [f"<tr class=\"rejected\"><td class=\"l\">{_esc(r.get('id'))}</td>"
             f"<td class=\"l\" colspan=\"{width}\">rejected: {_esc(r.get('reason'))}</td></tr>"
             for r in result.get("rejected") or []]
    header = "".join(f"<th class=\"{'l' if i == 0 else ''}\">{_esc(h)}</th>"
                     for i, h in enumerate(head))
    return (f"<h2>Stations</h2><table><tr>{header}</tr>{''.join(rows)}</table>")


def _num(value: Any, fmt: str, scale: float = 1.0) -> str:
    return "–" if value is None else format(float(value) * scale, fmt)


def _station_row(s: Mapping[str, Any], cv: Mapping[str, float], pose_only: bool) -> str:
    if pose_only:
        cells = [_num(s.get("residual_rot_rad"), ".3f", 180 / np.pi),
                 _num(s.get("residual_trans_m"), ".2f", 1e3)]
    else:
        correction = "–"
        if s.get("correction_rot_rad") is not None:
            correction = (f"{np.rad2deg(s['correction_rot_rad']):.3f}, "
                          f"{s['correction_trans_m'] * 1e3:.2f}")
        cells = [str(s.get("n_corners", "")), _num(s.get("rms_px"), ".3f"),
                 _num(s.get("chain_rms_px"), ".2f"), _num(cv.get(str(s.get("id"))), ".2f"),
                 correction, _num(s.get("mahalanobis"), ".1f")]
    return (f"<tr><td class=\"l\">{_esc(s.get('id'))}</td>"
            + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")


def _provenance(result: Result) -> str:
    software = result.get("software") or {}
    options = result.get("options") or {}
    opts = ", ".join(f"{k}={v}" for k, v in options.items())
    return ("<h2>Provenance</h2><table class=\"kv\">"
            f"<tr><td>command</td><td class=\"code\">{_esc(software.get('command') or '–')}"
            f"</td></tr><tr><td>options</td><td class=\"code\">{_esc(opts or '–')}</td></tr>"
            f"<tr><td>format</td><td>{_esc(result.get('format', '?'))}</td></tr></table>")


def _cv_by_station(result: Result) -> dict[str, float]:
    cv = result.get("cross_validation") or {}
    return {str(s["id"]): float(s["rms_px"]) for s in cv.get("stations") or []
            if s.get("rms_px") is not None}


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
    stations = result.get("stations") or []
    if not stations or not result.get("camera"):
        return None
    ids = [str(s["id"]) for s in stations]
    cv = _cv_by_station(result)
    series = [("fit (model with robot correction)", [s.get("rms_px") for s in stations],
               "#4c72b0")]
    if any(s.get("chain_rms_px") is not None for s in stations):
        series.append(("predicted from robot pose (all stations in the fit)",
                       [s.get("chain_rms_px") for s in stations], "#dd8452"))
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
    for s in result.get("stations") or []:
        if s.get("corners_px") is not None:
            corners.append(np.asarray(s["corners_px"], dtype=float))
            if s.get("residuals_px") is not None:
                residuals.append(np.asarray(s["residuals_px"], dtype=float))
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
    arrays, camera = _corner_arrays(result), result.get("camera")
    if arrays is None or not camera or np.isnan(arrays[1]).all():
        return None
    corners, res = arrays
    size = camera["image_size"]
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
    arrays, camera = _corner_arrays(result), result.get("camera")
    if arrays is None or not camera:
        return None
    corners = arrays[0]
    w, h = camera["image_size"]
    nx = _COVERAGE_COLS
    ny = max(1, round(nx * h / w))
    counts, _, _ = np.histogram2d(corners[:, 0], corners[:, 1], bins=(nx, ny),
                                  range=((0, w), (0, h)))
    covered = float(np.mean(counts > 0))
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
                f"{nx}x{ny} grid; pink cells hold no corner. {covered:.0%} of the cells are "
                "covered. Distortion is only determined where corners were seen: fill the "
                "image corners and edges.", _png(fig))


def _plot_uncertainty(result: Result) -> Plot | None:
    unc = result.get("uncertainty") or {}
    if result.get("hand_eye") is None or unc.get("hand_eye_trans_m") is None:
        return None
    fig, axes = _new_figure(2.6, ncols=3)
    spread = unc.get("jackknife") or {}
    axis_names = ["x", "y", "z"]
    for ax, key, scale, unit in ((axes[0], "hand_eye_trans_m", 1e3, "mm"),
                                 (axes[1], "hand_eye_rot_rad", 180 / np.pi, "deg")):
        reported = np.asarray(unc[key], dtype=float) * scale
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
    _kappa_nu_axes(axes[2], result.get("target") or {})
    return Plot("uncertainty", "Hand-eye and board uncertainty",
                "Left, middle: the hand-eye's 1σ per axis (translation in mm, rotation in "
                "degrees) as reported" + (" and as spread between calibrations on subsets of "
                                          "the stations (jackknife)" if spread else "")
                + ". Right: board scale κ and aspect ν with ±3σ, as a deviation from the "
                "nominal board in percent; κ far from 0 % means the printed squares are not "
                "the size entered.", _png(fig))


def _kappa_nu_axes(ax: Any, target: Mapping[str, Any]) -> None:
    names = [n for n in ("kappa", "nu") if target.get(n) is not None]
    dev = [100 * (float(target[n]) - 1) for n in names]
    err = [300 * float(target.get(f"{n}_sigma") or 0.0) for n in names]
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
    selection = result.get("model_selection") or {}
    candidates = [c for c in selection.get("candidates") or []
                  if c.get("cv_rms_px") is not None]
    if not candidates:
        return None
    chosen = selection.get("chosen")
    names = [str(c.get("name")) for c in candidates]
    values = [float(c["cv_rms_px"]) for c in candidates]
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
