"""A verdict on every calibration: pass, warn or fail, with findings a person can act on.

Each check looks at one thing a user cannot see in the numbers alone and says what to do:

* ``setup_mismatch`` (fail) — the robot readings need corrections no real arm needs before the
  images fit them: wrong ``setup``, poses that are not T_base_tcp in metres and radians, or
  images that do not belong to their poses.
* ``board_scale`` (warn) — the board's true size differs from the entered one (κ ≠ 1 beyond
  3σ and ``BOARD_SCALE_MIN``); the message names the measured square size.
* ``few_stations``, ``weak_rotation``, ``poor_coverage`` (warn) — the stations cannot pin the
  model down well: too few, rotations too small or about nearly one axis, corners covering
  little of the image or none of its corners (where distortion is largest).
* ``outlier_stations`` (warn) — stations dropped by the outlier rule or predicted far worse
  than the others (``outlier_limit``: flags a set without outliers in at most 1 % of
  calibrations).
* ``high_prediction_error`` (warn; info while the error at the board is within a healthy
  arm's accuracy) — the cross-validated error is far above the corner noise.
* ``tolerance_not_met`` (warn) — the user asked for a tolerance (``SolverOptions.tolerance``,
  a cold-start tolerance run's) and the hand-eye's 90 % bound (``COVERAGE_90`` σ, the bound
  the run's stop rule uses) is beyond it: a run that ended at its station limit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calib import so3
from calib.crossval import CrossValidation
from calib.result import Finding, QualityBlock
from calib.uncertainty import COVERAGE_90

#: κ must differ from 1 by more than this (and 3σ) for ``board_scale``.
BOARD_SCALE_MIN = 0.002
#: Median robot correction beyond which poses and images are irreconcilable (rad, m): real
#: arms are accurate to a few 0.1 deg and mm, a wrong setup needs tens of degrees.
MISMATCH_ROT_RAD, MISMATCH_TRANS_M = np.deg2rad(2.0), 0.02
#: Fewer usable stations than this: ``few_stations`` (cross-validation is leave-one-out).
FEW_STATIONS = 10
#: Spread of the station orientations (deg): largest below the first, second below the other.
WEAK_ROTATION_DEG, WEAK_SECOND_AXIS_DEG = 10.0, 4.0
#: Coverage grid (cells per side); warn below this fraction of cells hit or image corners empty.
COVERAGE_GRID, MIN_COVERAGE = 3, 0.6
#: At most this share of calibrations without any outlier station get ``outlier_stations``
#: from their held-out errors (the rule's false-alarm rate, ``outlier_limit``).
OUTLIER_FALSE_ALARM = 0.01
#: Cross-validated error above this many times the corner noise (and 2 px) is high ...
HIGH_ERROR_FACTOR, HIGH_ERROR_MIN_PX = 10.0, 2.0
#: ... but only worth a warning beyond this error at the board (m): a healthy arm's absolute
#: accuracy over a calibration workspace (systematic kinematic errors of a few 0.01 deg and
#: 0.1 mm predict held-out corners to 0.5-1 mm); below it the finding is information.
ROBOT_ACCURACY_M = 1e-3

@dataclass(frozen=True)
class QualityInputs:
    """What the checks look at (metres, radians, pixels).

    ``T_base_tcp`` (n, 4, 4) the used stations' readings (None: intrinsics only).
    ``corrections`` (n, 2): per-station robot correction (rotation angle, translation length)
    the fit needed, or the pose-prediction residuals of a pose-only fit. ``corners`` and
    ``image_size`` are None for pose-only sets. ``kappa_sigma`` None when κ was held.
    ``robot_map`` (3, 3) the chosen model's map of the robot's translations, if any.
    ``hand_eye_rss`` (rotation rad, translation m) the hand-eye's honest σ, root-sum-square
    over the axes (``calib.uncertainty.hand_eye_rss``); ``tolerance`` in the same order and
    units, the accuracy the user asked for.
    """

    setup: str
    T_base_tcp: np.ndarray | None
    corrections: np.ndarray | None
    cv: CrossValidation | None
    square_size_m: float | None
    kappa: float = 1.0
    kappa_sigma: float | None = None
    sigma_px: float | None = None
    corners: tuple[np.ndarray, ...] | None = None
    image_size: tuple[int, int] | None = None
    rejected: tuple[tuple[str, str], ...] = ()
    robot_map: np.ndarray | None = None
    hand_eye_rss: tuple[float, float] | None = None
    tolerance: tuple[float, float] | None = None


def assess(ev: QualityInputs) -> QualityBlock:
    """All checks on ``ev``; a mismatch makes the others moot, so it is reported alone."""
    mismatch = _setup_mismatch(ev)
    if mismatch is not None:
        return QualityBlock.of([mismatch])
    checks = (_board_scale, _robot_translation_map, _few_stations, _weak_rotation,
              _poor_coverage, _outliers, _high_prediction_error, _tolerance_not_met)
    return QualityBlock.of([f for check in checks if (f := check(ev)) is not None])


def _finding(code: str, severity: str, message: str, figures: dict[str, Any]) -> Finding:
    """A finding of ``code`` with its figures as fields."""
    return Finding(code=code, severity=severity, message=message, **figures)


def irreconcilable(corrections: np.ndarray) -> bool:
    """True when the median robot correction (n, 2: angle rad, length m) is beyond any arm."""
    rot, trans = np.median(corrections, axis=0)
    return bool(rot > MISMATCH_ROT_RAD or trans > MISMATCH_TRANS_M)


def _robot_translation_map(ev: QualityInputs) -> Finding | None:
    """The arm's positions are distorted (the chosen model maps them): say by how much over
    the stations' span, and that hand_eye and target_pose hold for the mapped readings."""
    if ev.robot_map is None or ev.T_base_tcp is None:
        return None
    t = ev.T_base_tcp[:, :3, 3]
    shift = float(np.linalg.norm((t - t.mean(axis=0)) @ np.asarray(ev.robot_map).T,
                                 axis=1).max())
    largest = float(np.abs(ev.robot_map).max())
    return _finding("robot_translation_map", "info", (
        f"the arm's positions are off by a linear map (scale and skew up to "
        f"{100 * largest:.2f} %), {shift * 1e3:.1f} mm at most over the stations' span: "
        f"predicting held-out stations clearly better with it, the calibration estimated it "
        f"(robot_translation_map). hand_eye and target_pose hold for readings corrected by "
        f"it (t + S t); readings used as they are will be off by up to that much. A robot "
        f"calibration of the arm removes it."),
        {"largest_entry": largest, "largest_shift_m": shift})


def _tolerance_not_met(ev: QualityInputs) -> Finding | None:
    """The hand-eye's 90 % bound beyond the tolerance asked for, in either figure."""
    if ev.tolerance is None or ev.hand_eye_rss is None:
        return None
    (tol_rad, tol_m), (sigma_rad, sigma_m) = ev.tolerance, ev.hand_eye_rss
    bound_m, bound_rad = COVERAGE_90 * sigma_m, COVERAGE_90 * sigma_rad
    if bound_m <= tol_m and bound_rad <= tol_rad:
        return None
    return _finding("tolerance_not_met", "warn", (
        f"the hand-eye is known to {bound_m * 1e3:.2f} mm / {np.degrees(bound_rad):.3f} deg "
        f"(90 % bound), not to the {tol_m * 1e3:.3g} mm / {np.degrees(tol_rad):.3g} deg "
        "asked for: use it only where that is good enough, or capture more stations (a nearer "
        "board and larger tilts teach more) and calibrate again."),
        {"bound_trans_m": bound_m, "bound_rot_rad": bound_rad, "tolerance_trans_m": tol_m,
         "tolerance_rot_rad": tol_rad})


def _setup_mismatch(ev: QualityInputs) -> Finding | None:
    if ev.corrections is None or not irreconcilable(ev.corrections):
        return None
    rot, trans = (float(v) for v in np.median(ev.corrections, axis=0))
    return _finding("setup_mismatch", "fail", (
        f"robot poses and images cannot be reconciled: the readings need a median correction "
        f"of {np.degrees(rot):.1f} deg / {trans * 1e3:.0f} mm to fit the images (a robot is "
        f"accurate to about 0.1 deg / 1 mm). Check the setup (now {ev.setup}; eye_in_hand: "
        f"camera on the tool, eye_to_hand: camera fixed), that every tcp_pose is T_base_tcp in "
        f"metres and radians, and that each image was taken at its pose."),
        {"median_correction_rot_rad": rot, "median_correction_trans_m": trans,
         "setup": ev.setup})


def _board_scale(ev: QualityInputs) -> Finding | None:
    if ev.kappa_sigma is None or not np.isfinite(ev.kappa_sigma):
        return None
    off = abs(ev.kappa - 1.0)
    if off <= max(3.0 * ev.kappa_sigma, BOARD_SCALE_MIN):
        return None
    size = ev.square_size_m
    measured = None if size is None else ev.kappa * size
    what = ("the board is" if measured is None else
            f"the board's squares measure {measured * 1e3:.2f} mm, not the {size * 1e3:g} mm "
            f"entered,")
    return _finding("board_scale", "warn", (
        f"{what} {100 * (ev.kappa - 1):+.1f} % off its nominal size (kappa {ev.kappa:.4f} ± "
        f"{ev.kappa_sigma:.4f}). The result is corrected for it; to make it exact, measure the "
        f"printed squares (e.g. 10 squares with a calliper), enter the true square size and "
        f"calibrate with kappa 'fixed'."),
        {"kappa": ev.kappa, "kappa_sigma": ev.kappa_sigma,
         "square_size_m": size, "measured_square_size_m": measured})


def _few_stations(ev: QualityInputs) -> Finding | None:
    n = len(ev.T_base_tcp if ev.T_base_tcp is not None else ev.corners or ())
    if n >= FEW_STATIONS:
        return None
    return _finding("few_stations", "warn", (
        f"only {n} usable stations: the estimate and its check (leave-one-out) rest on few "
        f"views; capture at least {FEW_STATIONS}, better 15-25."),
        {"stations": n, "recommended": FEW_STATIONS})


def _weak_rotation(ev: QualityInputs) -> Finding | None:
    """Spread of the tool orientations about their mean: principal angles (deg)."""
    if ev.T_base_tcp is None:
        return None
    R = ev.T_base_tcp[:, :3, :3]
    dev = so3.log(so3.mean(R).T @ R)
    spread = np.degrees(np.sqrt(np.linalg.eigvalsh(np.cov(dev.T) + 1e-18)[::-1]))
    if spread[0] >= WEAK_ROTATION_DEG and spread[1] >= WEAK_SECOND_AXIS_DEG:
        return None
    return _finding("weak_rotation", "warn", (
        f"the tool orientations vary little (spread {spread[0]:.1f} / {spread[1]:.1f} / "
        f"{spread[2]:.1f} deg about their principal axes): the hand-eye rotation and its "
        f"translation are poorly determined. Tilt the tool 15-35 deg about at least two "
        f"different axes between stations."),
        {"orientation_spread_rad": np.deg2rad(spread).tolist()})


def image_coverage(uv: np.ndarray, image_size: tuple[int, int]) -> tuple[float, int]:
    """The one coverage figure (verdict, page and report): the fraction of the image's
    ``COVERAGE_GRID`` x ``COVERAGE_GRID`` cells that hold a detected corner, and how many of
    its 4 corner cells hold none. ``uv``: (N, 2) pixels; ``image_size``: (width, height)."""
    w, h = image_size
    g = COVERAGE_GRID
    cell = np.clip((np.asarray(uv, float) / [w, h] * g).astype(int), 0, g - 1)
    hit = np.zeros((g, g), bool)
    hit[cell[:, 1], cell[:, 0]] = True
    return float(hit.mean()), int(4 - hit[0, 0] - hit[0, -1] - hit[-1, 0] - hit[-1, -1])


def _poor_coverage(ev: QualityInputs) -> Finding | None:
    if ev.corners is None or ev.image_size is None:
        return None
    g = COVERAGE_GRID
    fraction, empty_corners = image_coverage(np.concatenate(ev.corners), ev.image_size)
    if fraction >= MIN_COVERAGE and empty_corners == 0:
        return None
    return _finding("poor_coverage", "warn", (
        f"the corners cover {100 * fraction:.0f} % of the image ({g}x{g} cells) and "
        f"{empty_corners} of its 4 corner regions are empty: lens distortion there is "
        f"extrapolated. Add stations that put the board near the image corners and edges."),
        {"covered_fraction": fraction, "empty_image_corners": empty_corners})


def outlier_limit(errors: np.ndarray, false_alarm: float = OUTLIER_FALSE_ALARM) -> float:
    """The error beyond which a station's is an outlier among ``errors`` (n,) of stations
    alike (held-out prediction errors, px or m; NaN ignored); inf below 3 values.

    Without outliers a held-out station's error is mostly one rigid shift of its corners (the
    robot's error at its pose), so its square is σ² χ² with 1 to 2 degrees of freedom: on the
    demo's blind cell, 29 calibrations of 15 stations, 0.23 % of the errors passed 4x their
    set's median, against 0.70 % for χ²₁ and 0.002 % for χ²₂. The rule takes the heavier
    tail, χ²₁: then ``e_i² / mean_{j≠i} e_j²`` is F(1, m-1) distributed over m stations, and
    the largest is tested against its ``1 - false_alarm / 2n`` quantile (Bonferroni over the
    n stations, half the rate kept for the steps below), which for all m at once is one
    limit, ``e² > F S / (m - 1 + F)`` (S their sum of squares). As in Rosner's generalized
    ESD test (*Technometrics* 25:165, 1983) the largest is left out and the rest tested
    again, up to half the stations, and the k largest are outliers for the last k that
    passed its limit, so that two outliers do not hide each other; the limit returned is
    that of the rest. A set without outliers is flagged in 0.5-0.9 % of calibrations of 4 to
    60 stations (χ²₁ Monte Carlo, ``tests/test_outlier_rule``), far less for χ²₂. A fixed
    multiple of the median (4x before) flagged 7.7 % of χ²₁ sets of 15 and a clean station in
    1 of 11 demo runs: the median of few stations is itself noisy.
    """
    from scipy.special import stdtrit  # here, when first needed: ~70 ms of import

    e = np.sort(np.asarray(errors, dtype=float)[np.isfinite(errors)])
    n = len(e)
    limits = {}  # m stations tested -> their limit
    outliers = 0
    for m in range(n, max(n - n // 2, 3) - 1, -1):
        # the F(1, m-1) quantile, a two-sided t quantile squared
        f = float(stdtrit(m - 1, 1.0 - false_alarm / (4 * n))) ** 2
        limits[m] = float(np.sqrt(f * np.sum(e[:m] ** 2) / (m - 1 + f)))
        if e[m - 1] > limits[m]:
            outliers = n - m + 1
    return limits.get(n - outliers, np.inf) if outliers < n else np.inf


def _outliers(ev: QualityInputs) -> Finding | None:
    ids = [sid for sid, reason in ev.rejected if "robot pose inconsistent" in reason]
    if ev.cv is not None:
        err = ev.cv.station_errors()
        floor = 1.0 if ev.cv.rms_px is not None else 1e-3
        limit = max(outlier_limit(err), floor)
        ids += [s.id for s, e in zip(ev.cv.stations, err, strict=True) if e > limit]
    ids = list(dict.fromkeys(ids))  # a dropped station is also in the cross-validation
    if not ids:
        return None
    return _finding("outlier_stations", "warn", (
        f"stations {', '.join(ids)} disagree with the others (dropped, or predicted worse than "
        f"{OUTLIER_FALSE_ALARM:.0%} of stations alike would be in any calibration): check their "
        f"images and poses (motion blur, robot not settled, board moved)."),
        {"stations": ids})


def _high_prediction_error(ev: QualityInputs) -> Finding | None:
    if ev.cv is None or ev.cv.rms_px is None or ev.sigma_px is None:
        return None
    px = ev.cv.rms_px
    if px <= max(HIGH_ERROR_FACTOR * ev.sigma_px, HIGH_ERROR_MIN_PX):
        return None
    metric = ev.cv.rms_m
    within = metric is not None and metric <= ROBOT_ACCURACY_M
    mm = metric * 1e3 if metric is not None else float("nan")
    return _finding("high_prediction_error", "info" if within else "warn", (
        f"held-out stations are predicted from their robot poses to {px:.2f} px "
        f"({mm:.2f} mm at the board), {px / ev.sigma_px:.0f}x the corner noise: the robot's "
        f"own accuracy limits the result. Expect errors of this size in use" + (
            f"; within the {ROBOT_ACCURACY_M * 1e3:g} mm a healthy arm achieves." if within
            else f", beyond the {ROBOT_ACCURACY_M * 1e3:g} mm a healthy arm achieves: check "
                 f"the robot's calibration, payload settings and that it settles.")),
        {"cv_rms_px": px, "cv_rms_m": metric, "sigma_px": ev.sigma_px})
