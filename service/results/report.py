"""The calibration report: one self-contained HTML page a person reads, prints and files.

:func:`render_report` turns a result document (``cellcal/result@1``) into HTML with the verdict
and its findings on top, the key figures with their uncertainty, plots (per-station errors,
residual vectors over the image, corner coverage, hand-eye and κ / ν uncertainty, model
selection) and the station table with every rejected station and its reason. Plots are
matplotlib PNGs embedded as base64 ``data:`` URIs and the style is inline, so the file needs
nothing else: no network, no other file. Units for people: mm, degrees, pixels.

It reads the typed result (``calib.result.Result``): its ``quality``,
``cross_validation``, ``model_selection`` and ``uncertainty`` blocks when they are there, and
says so when they are not (older results).
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from calib import (
    CrossValidationBlock,
    ModelSelection,
    QualityBlock,
    Result,
    StationFit,
    Transform,
    outlier_limit,
    parse_result,
    ur_pose_from_matrix,
)
from service.results.identity import ReportIdentity
from service.results.plots import Plot, cv_by_station, report_plots
from service.results.thumbnails import thumbnails_section

_VERDICT_COLOURS = {"pass": "#1b7a3a", "warn": "#b26a00", "fail": "#b3261e"}
_WORST_FIRST = ("fail", "warn", "pass")

_CSS = """
body { font: 13px/1.45 -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #1d1d1f;
       max-width: 820px; margin: 24px auto; padding: 0 16px; }
h1 { font-size: 22px; margin: 0 0 2px; }
h2 { font-size: 16px; border-bottom: 1px solid #ccc; padding-bottom: 3px; margin: 22px 0 8px; }
.sub { color: #555; margin: 0 0 12px; }
.verdict { border: 2px solid; border-radius: 6px; padding: 10px 14px; margin: 12px 0; }
.verdict .word { font-size: 20px; font-weight: 700; text-transform: uppercase; }
.finding { margin: 4px 0 0 0; }
.headline { margin-left: 14px; font-weight: 600; color: #333; }
.sev { display: inline-block; min-width: 44px; font-weight: 600; text-transform: uppercase;
       font-size: 11px; }
.code { font-family: Menlo, Consolas, monospace; font-size: 12px; color: #444; }
table { border-collapse: collapse; width: 100%; font-size: 12px; }
th, td { border-bottom: 1px solid #e3e3e3; padding: 3px 6px; text-align: right; }
th { background: #f3f3f3; }
td.l, th.l { text-align: left; }
tr.rejected td { color: #8a1c14; background: #fdf1f0; }
tr.chosen td { font-weight: 700; background: #eef7f0; }
tr.outlier td { background: #fff3d6; }
.over { color: #b3261e; font-weight: 700; }
figure { margin: 12px 0 18px; break-inside: avoid; page-break-inside: avoid; }
figure img { width: 100%; height: auto; }
figcaption { color: #444; font-size: 12px; }
.kv td:first-child { text-align: left; color: #444; width: 34%; }
.kv td { text-align: left; }
.note { color: #555; font-size: 12px; }
.thumbs { display: flex; flex-wrap: wrap; gap: 6px; }
figure.thumb { width: 32%; margin: 0; }
figure.thumb figcaption { font-size: 11px; }
figure.thumb.outlier figcaption { color: #b3261e; font-weight: 700; }
.signoff td { height: 26px; }
.signoff td:first-child { width: 22%; }
.box { display: inline-block; width: 10px; height: 10px; border: 1px solid #333;
       margin: 0 4px 0 14px; vertical-align: middle; }
@page { size: A4; margin: 14mm 12mm; }
@media print { body { margin: 0; max-width: none; font-size: 11px; }
               h2 { break-after: avoid; } table, .signoff { break-inside: auto; }
               tr, .verdict, .signoff-block { break-inside: avoid; } }
"""


def render_report(result: Result | Mapping[str, Any],
                  images: Mapping[str, str | Path] | None = None,
                  identity: ReportIdentity | None = None) -> str:
    """The HTML report of a result (or its JSON document, validated first), as one
    self-contained string; ValueError (one line) for a document that is not a valid
    ``cellcal/result@1``.

    Every value read from the result is escaped (``_esc``, ``_num``): a hand-edited result
    may hold markup in any text field. ``images`` (station id -> image file) adds a thumbnail
    of every used station with its detected and reprojected corners; ``identity`` names the
    cell and the inputs (``IDENTITY_FIELDS``)."""
    result = parse_result(result)
    parts = [
        _header(result),
        _verdict(result.quality, result.cross_validation),
        _summary(result),
        "<h2>Plots</h2>",
        *(_figure(p) for p in report_plots(result)),
        _selection_table(result.model_selection),
        _station_table(result),
        thumbnails_section(result, images or {}, outlier_ids(result)),
        _provenance(result),
        _identity(result, identity or ReportIdentity()),
        _sign_off(),
    ]
    title = html.escape(f"cellcal calibration report — {result.setup}")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{title}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(parts) + "\n</body></html>\n")


# ---- text sections -------------------------------------------------------------------------

def _esc(value: Any) -> str:
    """Any value as HTML text: every value from the result passes here or ``_num`` (a
    hand-edited result may hold markup anywhere, numbers' places included)."""
    return html.escape(str(value))


def _or(value: Any, missing: str) -> str:
    """``value`` as escaped text, ``missing`` where the result has none."""
    return missing if value is None else _esc(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) \
        and not isinstance(value, bool)


def _num(value: Any, fmt: str, scale: float = 1.0) -> str:
    """A number formatted with ``fmt`` (times ``scale``), "–" for None, and anything else
    (a hand-edited result) escaped as text."""
    if value is None:
        return "–"
    return format(float(value) * scale, fmt) if _is_number(value) else _esc(value)


def _header(result: Result) -> str:
    size = result.camera.image_size if result.camera else None
    facts = [
        f"setup <b>{_esc(result.setup)}</b>",
        f"method <b>{_or(result.method, '?')}</b>",
        f"{len(result.stations or [])} stations used, {len(result.rejected or [])} rejected",
        f"image {size[0]}×{size[1]} px" if size else "pose-only (no camera model)",
        f"created {_or(result.created, '?')}",
        f"cellcal {_or(result.software.version if result.software else None, '?')}",
    ]
    return ("<h1>Calibration report</h1>"
            f"<p class=\"sub\">{' · '.join(facts)}</p>")


def _verdict(quality: QualityBlock | None, cv: CrossValidationBlock | None) -> str:
    if quality is None:
        return ("<div class=\"verdict\" style=\"border-color:#888\"><span class=\"word\">"
                "no verdict</span><p class=\"finding\">This result carries no quality "
                "assessment (made by an older cellcal); judge it by the figures below.</p>"
                "</div>")
    colour = _VERDICT_COLOURS[quality.verdict]
    findings = sorted(quality.findings, key=lambda f: _WORST_FIRST.index(_verdict_of(f.severity)))
    items = "".join(
        f"<p class=\"finding\"><span class=\"sev\" style=\"color:"
        f"{_VERDICT_COLOURS[_verdict_of(f.severity)]}\">"
        f"{_esc(f.severity)}</span> {_esc(f.message)} "
        f"<span class=\"code\">[{_esc(f.code)}]</span></p>" for f in findings)
    if not findings:
        items = "<p class=\"finding\">No findings: every check passed.</p>"
    headline = ""
    if cv is not None and cv.rms_px is not None:
        mm = "" if cv.rms_mm is None else f" ({_num(cv.rms_mm, '.2f')} mm at the board)"
        headline = (f"<span class=\"headline\">stations left out of the calibration are "
                    f"predicted to {_num(cv.rms_px, '.2f')} px{mm}, {_esc(cv.kind)} over "
                    f"{len(cv.stations)} stations{_esc(cv.dropped_clause())}</span>")
    return (f"<div class=\"verdict\" style=\"border-color:{colour}\">"
            f"<span class=\"word\" style=\"color:{colour}\">{_esc(quality.verdict)}</span>"
            f"{headline}{items}</div>")


def _verdict_of(severity: str) -> str:
    """The verdict a finding of ``severity`` makes (older documents say "error" and "warning";
    info passes)."""
    return {"fail": "fail", "error": "fail", "warn": "warn", "warning": "warn"}.get(
        severity, "pass")


def _summary(result: Result) -> str:
    rows = _camera_rows(result) + _pose_rows(result) + _error_rows(result)
    body = "".join(f"<tr><td>{_esc(k)}</td><td>{v}</td></tr>" for k, v in rows)
    note = result.uncertainty.note if result.uncertainty else None
    return ("<h2>Result</h2><table class=\"kv\">" + body + "</table>"
            + (f"<p class=\"note\">Uncertainty: {_esc(note)}</p>" if note else ""))


def _pm(value: Any, sigma: Any, fmt: str = ".3f", scale: float = 1.0) -> str:
    """``value ± sigma`` (both times ``scale``); the value alone if sigma is None, zero or not
    finite."""
    if not _is_number(sigma) or not np.isfinite(sigma) or sigma == 0:
        return _num(value, fmt, scale)
    return f"{_num(value, fmt, scale)} ± {_num(sigma, fmt, scale)}"


def _camera_rows(result: Result) -> list[tuple[str, str]]:
    camera, target = result.camera, result.target
    rows: list[tuple[str, str]] = []
    if camera:
        K = np.asarray(camera.K)
        sigmas = (result.uncertainty.camera if result.uncertainty else None) or {}
        fx, fy, cx, cy = (sigmas.get(k) for k in ("fx", "fy", "cx", "cy"))
        rows.append(("focal length fx, fy (px)",
                     f"{_pm(K[0, 0], fx, '.2f')}, {_pm(K[1, 1], fy, '.2f')}"))
        rows.append(("principal point cx, cy (px)",
                     f"{_pm(K[0, 2], cx, '.2f')}, {_pm(K[1, 2], cy, '.2f')}"))
        rows.append(("distortion k1 k2 p1 p2 k3",
                     " ".join(_num(v, ".5f") for v in camera.dist)))
    rows.append(("board scale κ (true / nominal square)",
                 _pm(target.kappa, target.kappa_sigma, ".5f")))
    rows.append(("board aspect ν", _pm(target.nu, target.nu_sigma, ".5f")))
    return rows


#: How ``hand_eye`` and ``target_pose`` read in each setup (docs/conventions.md).
_FRAMES = {"eye_in_hand": ("T_tcp_cam", "T_base_target"),
           "eye_to_hand": ("T_base_cam", "T_tcp_target")}


def _pose_rows(result: Result) -> list[tuple[str, str]]:
    rows = []
    unc = result.uncertainty
    blocks: tuple[Transform | None, Transform | None] = (result.hand_eye, result.target_pose)
    sigmas = ((None, None), (None, None)) if unc is None else (
        (unc.hand_eye_trans_m, unc.hand_eye_rot_rad),
        (unc.target_pose_trans_m, unc.target_pose_rot_rad))
    for block, frame, (t_sd, r_sd) in zip(blocks, _FRAMES[result.setup], sigmas,
                                         strict=True):
        if block is None:
            continue
        pose = np.asarray(block.pose if block.pose is not None
                          else ur_pose_from_matrix(np.asarray(block.matrix)), dtype=float)
        t_txt = ", ".join(_pm(v, s, ".2f", 1e3)
                          for v, s in zip(pose[:3], t_sd or [None] * 3, strict=True))
        rows.append((f"{frame}: translation x, y, z (mm)", t_txt))
        if r_sd is not None:
            rows.append((f"{frame}: rotation 1σ about x, y, z (°)",
                         ", ".join(_num(s, ".3f", 180 / np.pi) for s in r_sd)))
        rows.append((f"{frame}: UR pose (m, rad)",
                     "p[" + ", ".join(_num(v, ".5f") for v in pose) + "]"))
    return rows


def _error_rows(result: Result) -> list[tuple[str, str]]:
    rows = []
    if result.camera is not None:
        rows.append(("reprojection RMS of the fit (px)", _num(result.camera.rms_px, ".3f")))
    cv = result.cross_validation
    if cv is not None and cv.rms_px is not None:
        mm = ("" if cv.rms_mm is None else f" ≈ {_num(cv.rms_mm, '.2f')} mm at the board")
        rows.append((f"cross-validated prediction error ({cv.folds} folds)",
                     f"{_num(cv.rms_px, '.3f')} px{mm}{_esc(cv.dropped_clause())}"))
    chain_rms_px = (result.validation or {}).get("chain_rms_px")
    if chain_rms_px is not None:
        rows.append(("prediction from the robot poses, all stations (px)",
                     _num(chain_rms_px, ".3f")))
    return rows


def _figure(plot: Plot) -> str:
    data = base64.b64encode(plot.png).decode("ascii")
    return (f"<figure id=\"fig-{plot.key}\"><img alt=\"{_esc(plot.title)}\" "
            f"src=\"data:image/png;base64,{data}\"><figcaption><b>{_esc(plot.title)}.</b> "
            f"{_esc(plot.caption)}</figcaption></figure>")


def outlier_ids(result: Result) -> set[str]:
    """The stations the result calls outliers: those of the ``outlier_stations`` finding and
    those the cross-validation dropped."""
    ids = set(result.cross_validation.dropped or []) if result.cross_validation else set()
    for finding in result.quality.findings if result.quality else []:
        if finding.code == "outlier_stations":
            ids |= {str(i) for i in getattr(finding, "stations", None) or []}
    return ids


def _limits(stations: list[StationFit], keys: tuple[str, str]) -> list[float | None]:
    """Each per-station residual's threshold: the outlier rule of the verdict
    (``calib.outlier_limit`` over the stations); None without values (or too few)."""
    limits: list[float | None] = []
    for key in keys:
        values = [v for v in (getattr(s, key) for s in stations) if v is not None]
        limit = outlier_limit(np.array(values)) if values else np.inf
        limits.append(limit if np.isfinite(limit) else None)
    return limits


def _station_table(result: Result) -> str:
    stations = result.stations or []
    cv = cv_by_station(result)
    pose_only = result.camera is None
    keys = ("residual_rot_rad", "residual_trans_m") if pose_only else ("loo_rot_rad",
                                                                       "loo_trans_m")
    limits = _limits(stations, keys)
    limit_text = [("–" if lim is None else f"≤ {lim * scale:{fmt}}")
                  for lim, scale, fmt in zip(limits, (180 / np.pi, 1e3), (".3f", ".2f"),
                                             strict=True)]
    residual_head = [f"{'rot. residual' if pose_only else 'held-out rot.'} (°, "
                     f"{limit_text[0]})",
                     f"{'trans. residual' if pose_only else 'held-out trans.'} (mm, "
                     f"{limit_text[1]})"]
    head = (["station", *residual_head, "flag"] if pose_only else
            ["station", "corners", "fit RMS (px)", "robot-pose RMS (px)", "CV (px)",
             *residual_head, "robot correction (°, mm)", "Mahalanobis", "flag"])
    outliers = outlier_ids(result)
    rows = [_station_row(s, cv, pose_only, (keys, limits), s.id in outliers)
            for s in stations]
    width = len(head) - 1
    rows += [f"<tr class=\"rejected\"><td class=\"l\">{_esc(r.id)}</td>"
             f"<td class=\"l\" colspan=\"{width}\">rejected: {_esc(r.reason)}</td></tr>"
             for r in result.rejected or []]
    header = "".join(f"<th class=\"{'l' if i == 0 else ''}\">{_esc(h)}</th>"
                     for i, h in enumerate(head))
    return (f"<h2>Stations</h2><table><tr>{header}</tr>{''.join(rows)}</table>")


#: Model-selection table: heading, candidate field, number format (None: text).
_SELECTION_COLUMNS = (("κ", "kappa_value", ".5f"), ("ν", "nu_value", ".5f"),
                      ("robot noise", "robot_noise", None), ("CV (px)", "cv_rms_px", ".3f"),
                      ("CV at board (mm)", "cv_rms_mm", ".3f"),
                      ("CV distance (mm)", "cv_range_mm", ".3f"),
                      ("CV translation (mm)", "cv_trans_mm", ".3f"))


def _selection_table(selection: ModelSelection | None) -> str:
    """Every candidate's cross-validated figures, the chosen one in bold, and the decisions."""
    if selection is None or not selection.candidates:
        return ""
    rows = "".join(
        f"<tr class=\"{'chosen' if c.chosen else ''}\"><td class=\"l\">{_esc(c.name)}</td>"
        + "".join(f"<td>{_or(getattr(c, key), '–') if fmt is None else _num(getattr(c, key), fmt)}"
                  "</td>" for _, key, fmt in _SELECTION_COLUMNS) + "</tr>"
        for c in selection.candidates)
    head = "".join(f"<th>{h}</th>" for h, _, _ in _SELECTION_COLUMNS)
    decisions = "".join(f"<li>{_esc(d)}</li>" for d in selection.decisions)
    return (f"<h2>Model selection</h2><table><tr><th class=\"l\">candidate</th>{head}</tr>"
            f"{rows}</table><ul class=\"note\">{decisions}</ul><p class=\"note\">Rule: "
            f"{_or(selection.rule, '')}.</p>")


def _residual_cells(s: StationFit,
                    checks: tuple[tuple[str, str], list[float | None]]) -> list[str]:
    """A station's rotation (°) and translation (mm) residuals, each marked when over its
    threshold."""
    cells = []
    for key, limit, scale, fmt in zip(*checks, (180 / np.pi, 1e3), (".3f", ".2f"),
                                      strict=True):
        value = getattr(s, key)
        over = value is not None and limit is not None and value > limit
        text = _num(value, fmt, scale)
        cells.append(f"<span class=\"over\">{text} over</span>" if over else text)
    return cells


def _station_row(s: StationFit, cv: Mapping[str, float], pose_only: bool,
                 checks: tuple[tuple[str, str], list[float | None]], outlier: bool) -> str:
    residuals = _residual_cells(s, checks)
    if pose_only:
        cells = residuals
    else:
        correction = "–"
        if s.correction_rot_rad is not None:
            correction = (f"{_num(s.correction_rot_rad, '.3f', 180 / np.pi)}, "
                          f"{_num(s.correction_trans_m, '.2f', 1e3)}")
        cells = [_or(s.n_corners, ""), _num(s.rms_px, ".3f"), _num(s.chain_rms_px, ".2f"),
                 _num(cv.get(s.id), ".2f"), *residuals, correction,
                 _num(s.mahalanobis, ".1f")]
    cells.append("outlier" if outlier else "")
    return (f"<tr class=\"{'outlier' if outlier else ''}\"><td class=\"l\">{_esc(s.id)}</td>"
            + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")


def _provenance(result: Result) -> str:
    command = result.software.command if result.software else None
    opts = ", ".join(f"{k}={v}" for k, v in (result.options or {}).items())
    return ("<h2>Provenance</h2><table class=\"kv\">"
            f"<tr><td>command</td><td class=\"code\">{_esc(command or '–')}"
            f"</td></tr><tr><td>options</td><td class=\"code\">{_esc(opts or '–')}</td></tr>"
            f"<tr><td>format</td><td>{_esc(result.format)}</td></tr></table>")


def _sign_off() -> str:
    """The block the integrator fills in on paper: who accepted this calibration, when, and
    the decision."""
    decisions = "".join(f"<span class=\"box\"></span>{d}" for d in (
        "accepted", "accepted with reservations", "rejected"))
    return ("<div class=\"signoff-block\"><h2>Sign-off</h2><table class=\"kv signoff\">"
            "<tr><td>Name</td><td></td></tr><tr><td>Date</td><td></td></tr>"
            f"<tr><td>Decision</td><td>{decisions}</td></tr>"
            "<tr><td>Reservations</td><td></td></tr><tr><td>Signature</td><td></td></tr>"
            "</table></div>")


#: The cell and the inputs a signed report names: field of ``ReportIdentity`` and its label.
IDENTITY_FIELDS = (("cell", "cell"), ("robot", "robot"), ("robot_model", "robot model"),
                   ("robot_serial", "robot serial"),
                   ("controller_version", "controller version"), ("camera", "camera"),
                   ("board", "board"), ("stations", "stations"),
                   ("input_sha256", "input checksum (SHA-256 of the station set)"))


def _identity(result: Result, identity: ReportIdentity) -> str:
    """What was calibrated with what: each field, or "not known" where the source does not
    say (a robot driver that reports no serial, a result file without its station set)."""
    version = result.software.version if result.software else None
    rows = [("cellcal version", version or "not known"),
            *((label, getattr(identity, key) or "not known") for key, label in IDENTITY_FIELDS)]
    body = "".join(f"<tr><td>{_esc(label)}</td><td class=\"code\">{_esc(value)}</td></tr>"
                   for label, value in rows)
    return f"<h2>Cell and inputs</h2><table class=\"kv\">{body}</table>"
