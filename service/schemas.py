"""Request and response shapes of the REST API (pydantic): create shapes apart from public ones.

Poses are UR vectors ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians), T_base_tcp,
as everywhere in cellcal (``docs/conventions.md``).
"""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from fastapi import Path as PathParam
from pydantic import BaseModel, ConfigDict, Field, field_serializer, model_validator

from calib import (
    COVERAGE_90,
    METHODS,
    Detection,
    FiniteFloat,
    Result,
    RobotNoise,
    SolverOptions,
    Target,
)
from service.exports import FORMATS, formats_help

#: Request bodies take numbers only as numbers (strict: no "1.5" text).
StrictFiniteFloat = Annotated[FiniteFloat, Field(strict=True)]
Pose = Annotated[list[StrictFiniteFloat], Field(min_length=6, max_length=6,
                                          description="[x, y, z, rx, ry, rz], m and rad")]
RunState = Literal["capturing", "paused", "done", "failed", "cancelled", "interrupted"]
ExportFormat = Literal[FORMATS]  # type: ignore[valid-type]
#: The largest station index or listing offset: any larger number is no row, and SQL integers
#: (64 bit) could not even hold it.
MAX_INDEX = 2**31 - 1
StationIndex = Annotated[int, PathParam(ge=0, le=MAX_INDEX, description="station index")]
#: T_tcp_probe of the default dot-hit probe: 10 cm along tool z.
DEFAULT_PROBE = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
#: A tolerance run's stop rule in words (``StopRule.rule``).
STOP_RULE = (f"stop when the 90 % bound ({COVERAGE_90} x the hand-eye's honest 1-sigma) is "
             "within the tolerance in rotation and translation, at max_stations, or when no "
             "feasible view remains")


class _Input(BaseModel):
    """A request body: unknown fields refused, and JSON types as documented (strict: no
    ``true`` for a number, no ``"5"`` for an integer)."""

    model_config = ConfigDict(extra="forbid", strict=True)


def _only(mode: str | None, given: str | None, title: str) -> dict[str, Any]:
    """The JSON schema of a run-creation body with ``mode`` and exactly ``given`` of
    stations / poses / tolerance_mm (None: neither); a tolerance goes with tolerance_deg.
    ``title`` names the shape in the docs (ReDoc shows an untitled branch as "object")."""
    kinds = {"stations": {"type": "integer"}, "poses": {"type": "array"},
             "tolerance_mm": {"type": "number"}}
    props: dict[str, Any] = {k: v if k == given else {"type": "null"} for k, v in kinds.items()}
    if given != "tolerance_mm":
        props |= {"tolerance_deg": {"type": "null"}, "max_stations": {"type": "null"}}
    branch: dict[str, Any] = {"title": title, "properties": props}
    if mode == "external":
        props["mode"] = {"const": "external"}
        branch["required"] = ["mode"]
    else:
        props["mode"] = {"const": "robot"}
        branch["required"] = [given] if given != "tolerance_mm" else [given, "tolerance_deg"]
    return branch


class RunCreate(_Input):
    """``stations`` (automatic planning), a tolerance (``tolerance_mm`` with
    ``tolerance_deg``: plan until the hand-eye's σ meets it, at most ``max_stations``) or
    explicit ``poses``; ``target`` optional. In ``external`` mode none of them: a cell
    controller posts the stations."""

    # the rule of ``_one_plan`` in the OpenAPI document: exactly one of the four shapes
    model_config = ConfigDict(json_schema_extra={"oneOf": [
        _only("robot", "stations", "planned stations"), _only("robot", "poses", "pose list"),
        _only("robot", "tolerance_mm", "planned to a tolerance"),
        _only("external", None, "external")]})

    #: A valid body of each shape, shown in the API docs instead of one generated from the
    #: schema (which mixed the shapes into a body the service refuses).
    EXAMPLES: ClassVar[dict[str, dict[str, Any]]] = {
        "planned": {"summary": "15 stations planned automatically",
                    "value": {"stations": 15}},
        "tolerance": {"summary": "planned until the hand-eye's 1-sigma meets a tolerance",
                      "value": {"tolerance_mm": 0.5, "tolerance_deg": 0.05,
                                "max_stations": 40}},
        "poses": {"summary": "the given TCP poses, in order",
                  "value": {"poses": [[0.4, -0.1, 0.5, 0.0, 3.1416, 0.0],
                                      [0.45, -0.1, 0.5, 0.1, 3.1, 0.0],
                                      [0.4, -0.05, 0.55, 0.0, 3.1, 0.1]]}},
        "external": {"summary": "a cell controller moves the robot and posts the stations",
                     "value": {"mode": "external", "target": {
                         "type": "checkerboard", "inner_corners": [11, 8],
                         "square_size_m": 0.03}}}}

    mode: Literal["robot", "external"] = Field(
        "robot", description="robot: the service moves the robot through the stations; "
                             "external: a cell controller moves it and posts each station "
                             "(POST /runs/{id}/stations), then finishes the run")
    stations: Annotated[int, Field(ge=3, le=500)] | None = Field(
        None, description="number of stations to plan automatically")
    poses: Annotated[list[Pose], Field(min_length=1)] | None = Field(
        None, description="TCP poses to visit in order")
    tolerance_mm: Annotated[float, Field(gt=0.0, le=100.0)] | None = Field(
        None, description="stop once the 90 % bound on the hand-eye translation error "
                          "(1.645x its honest 1-sigma, root-sum-square over the axes) is "
                          "within this many mm; with tolerance_deg")
    tolerance_deg: Annotated[float, Field(gt=0.0, le=10.0)] | None = Field(
        None, description="... and its rotation's within this many degrees")
    max_stations: Annotated[int, Field(ge=3, le=500)] | None = Field(
        None, description="with a tolerance: stop after this many stations at the latest "
                          "(default 40)")
    target: Target | None = Field(
        None, description="the board to detect: a checkerboard (type 'checkerboard', the "
                          "default when 'type' is left out) or a ChArUco board (type "
                          "'charuco'); default: the configured board")

    @model_validator(mode="after")
    def _one_plan(self) -> RunCreate:
        tolerance = (self.tolerance_mm, self.tolerance_deg)
        if (None in tolerance) != (tolerance == (None, None)):
            raise ValueError("give tolerance_mm and tolerance_deg together")
        if self.max_stations is not None and self.tolerance_mm is None:
            raise ValueError("max_stations goes with a tolerance (tolerance_mm, "
                             "tolerance_deg); a fixed count is 'stations'")
        shapes = [self.stations, self.poses, self.tolerance_mm]
        given = sum(v is not None for v in shapes)
        if self.mode == "external":
            if given:
                raise ValueError("an 'external' run takes its stations from POST "
                                 "/runs/{id}/stations: give none of 'stations', 'poses' or "
                                 "a tolerance")
        elif given != 1:
            raise ValueError("give exactly one of 'stations' (a number to plan), "
                             "'tolerance_mm' with 'tolerance_deg' (plan until the hand-eye is "
                             "that good) or 'poses' (a list of [x, y, z, rx, ry, rz])")
        return self

    @property
    def stop_rule(self) -> StopRule | None:
        """The cold-start stop rule of a tolerance run (None for other runs)."""
        if self.tolerance_mm is None or self.tolerance_deg is None:
            return None
        return StopRule(tolerance_mm=self.tolerance_mm, tolerance_deg=self.tolerance_deg,
                        max_stations=self.max_stations or DEFAULT_MAX_STATIONS)


#: ``max_stations`` of a tolerance run that does not give one.
DEFAULT_MAX_STATIONS = 40


class StopRule(BaseModel):
    """When a tolerance run stops: the 90 % bound on both hand-eye errors within tolerance,
    or ``max_stations``."""

    tolerance_mm: float
    tolerance_deg: float
    max_stations: int
    coverage_factor: float = Field(COVERAGE_90, description="the 90 % bound in honest σ "
                                   "(calib.COVERAGE_90): the run stops when the bound is within "
                                   "the tolerance, so the true error is in >= 90 % of runs")
    rule: str = Field(STOP_RULE, description="the rule in words")


class SigmaPoint(BaseModel):
    """The hand-eye's 1-σ after a station: root-sum-square over the axes, and its 90 %
    bound."""

    stations: int = Field(description="good stations so far (exploratory views included)")
    rot_deg: float
    trans_mm: float
    bound_rot_deg: float | None = Field(
        None, description="90 % bound on the rotation error: coverage_factor x rot_deg")
    bound_trans_mm: float | None = Field(
        None, description="90 % bound on the translation error: coverage_factor x trans_mm")
    kind: Literal["honest", "estimate"] = Field(
        description="honest: the σ a calibration of these stations reports (jackknife floor "
                    "included); estimate: the planner's formal σ before enough stations")


class Created(BaseModel):
    id: str


#: A failed job's ``error_code``: what a program tells failures apart by.
_ERROR_CODE = ("why it failed, for programs (None unless failed): storage_unavailable or "
               "disk_full (the data directory), interrupted (the service stopped), a device "
               "fault's code (e.g. camera_frozen, protective_stop), calibration_failed or "
               "validation_failed (the data do not allow it), worker_died, internal_error")


class ErrorInfo(BaseModel):
    code: str
    detail: str


class StationError(BaseModel):
    index: int
    code: str | None
    detail: str


class RunPublic(BaseModel):
    id: str
    state: RunState
    mode: Literal["robot", "external"]
    cell: str = Field(description="the cell whose service captured it (CELLCAL_CELL); its "
                                  "images are on that service")
    robot: str
    setup: str
    target: Target
    stations_planned: int
    stations_captured: int
    stations_skipped: int
    error: ErrorInfo | None = Field(None, description="why the run failed or stopped")
    station_errors: list[StationError] = Field(
        default_factory=list, description="stations skipped after a retry, with the reason")
    cold_start: ColdStartPublic | None = Field(
        None, description="a run planned station by station from a cold start: its stop rule, "
                          "exploratory moves, σ history and why it stopped")
    created_at: dt.datetime
    updated_at: dt.datetime


class ColdStartPublic(BaseModel):
    """How a cold-start run went (``service.runs.coldstart``)."""

    stop_rule: StopRule | None = Field(None, description="a tolerance run's rule; None for a "
                                                         "run of a fixed station count")
    stop_reason: Literal["tolerance_met", "max_stations", "no_feasible_view"] | None = Field(
        None, description="why it stopped; None while capturing")
    exploratory_moves: int = 0
    sigma_history: list[SigmaPoint] = Field(default_factory=list)
    notes: list[str] = Field(default_factory=list, description="e.g. a configured guess that "
                                                               "did not fit and was ignored")


class DetectionPublic(BaseModel):
    """The public view of a :class:`calib.Detection`."""

    ok: bool
    reason: str | None = None
    sharpness: float | None = None
    coverage: float = 0.0
    mean_contrast: float | None = None
    ambiguous: bool = False
    corners: list[list[float]] | None = Field(
        None, description="pixels, shape (N, 2), of the board points ``ids``; only on the "
                          "single-station view")
    ids: list[int] | None = Field(
        None, description="board point ids of ``corners`` (a ChArUco view may show part of "
                          "the board; a checkerboard shows all, 0 .. cols * rows - 1); only "
                          "on the single-station view")

    @classmethod
    def of(cls, det: Detection, *, corners: bool) -> DetectionPublic:
        """``det`` as the API shows it; ``corners`` and ``ids`` only when asked for."""
        return cls(ok=det.ok, reason=det.reason, sharpness=det.sharpness,
                   coverage=det.coverage, mean_contrast=det.mean_contrast,
                   ambiguous=det.ambiguous,
                   corners=det.corners.tolist() if corners and det.corners is not None else None,
                   ids=det.ids.tolist() if corners and det.ids is not None else None)


class StationPublic(BaseModel):
    """The public view of a stored station: the one station model (``calib.Station``) and
    the capture's bookkeeping (``api.stations.station_public`` converts)."""

    index: int
    state: Literal["captured", "skipped"]
    commanded_tcp_pose: list[float] = Field(description="the TCP pose the run commanded "
                                                        "(T_base_tcp, UR pose vector)")
    tcp_pose: list[float] | None = Field(description="TCP pose read after the grab")
    freshness: str | None = Field(None, description="how the camera made sure the image was "
                                                    "exposed after the robot had settled")
    joint_positions: list[float] | None = Field(None, description="rad, when known")
    detection: DetectionPublic | None
    image_url: str | None
    image_size: list[int] | None
    error: ErrorInfo | None
    attempts: int
    captured_at: dt.datetime


class CalibrationOptions(_Input):
    """Solver options (``calib.calibrate``); noise levels are 1-sigma."""

    method: Literal[METHODS] = "joint"  # type: ignore[valid-type]
    estimate_kappa: bool = True
    kappa: Literal["auto", "estimate", "fixed"] = Field(
        "auto", description="board scale: auto (estimated only when that predicts held-out "
                            "stations clearly better), estimate, or fixed at exactly 1 (the "
                            "entered square size was measured); estimate_kappa false = fixed")
    estimate_nu: bool = True
    nu_method: Literal["images", "extrinsics"] = "images"
    robot_noise_rot_deg: Annotated[float, Field(gt=0.0, le=5.0)] | None = Field(
        None, description="robot rotation reading noise; default: the pipeline's")
    robot_noise_trans_mm: Annotated[float, Field(gt=0.0, le=50.0)] | None = Field(
        None, description="robot position reading noise; default: the pipeline's")

    @model_validator(mode="after")
    def _the_solver_takes_them(self) -> CalibrationOptions:
        """Options the solver would refuse (e.g. Method #2 with a method other than joint)
        are refused when the request arrives (422 with the solver's reason)."""
        self.solver()
        return self

    def solver(self) -> SolverOptions:
        """The solver's options (metres and radians)."""
        default = RobotNoise()
        noise = RobotNoise(
            default.rot_rad if self.robot_noise_rot_deg is None
            else float(np.deg2rad(self.robot_noise_rot_deg)),
            default.trans_m if self.robot_noise_trans_mm is None
            else self.robot_noise_trans_mm * 1e-3)
        return SolverOptions(method=self.method, estimate_nu=self.estimate_nu,
                             estimate_kappa=self.estimate_kappa, kappa=self.kappa,
                             nu_method=self.nu_method, noise=noise)


class CalibrationCreate(_Input):
    options: CalibrationOptions = Field(default_factory=CalibrationOptions)


class CalibrationPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)  # read from the stored row

    id: str
    run_id: str
    cell: str
    state: Literal["running", "done", "failed"]
    options: dict[str, Any]
    result: Result | None = Field(None, description="the cellcal/result@1 document once done")
    error: str | None
    error_code: str | None = Field(None, description=_ERROR_CODE)
    created_at: dt.datetime
    finished_at: dt.datetime | None

    # No return annotation: with one, pydantic would document the answer by it instead of
    # by ``Result``.
    @field_serializer("result")
    def _as_stored(self, result: Result | None):
        """The document as stored: no field added that it did not have."""
        return None if result is None else result.document()


class ValidationCreate(_Input):
    """A dot-hit run (SM eq. 24): the robot touches board points with a probe."""

    probe: Pose = Field(default_factory=lambda: list(DEFAULT_PROBE),
                        description="T_tcp_probe [x, y, z, rx, ry, rz]: the probe tip in the "
                                    "TCP frame, the probe along its z axis; default a 10 cm "
                                    "probe along tool z")
    points: Annotated[list[str], Field(min_length=1, max_length=100)] | None = Field(
        None, description="ids of the board points to touch, from corner_0_0, "
                          "corner_<cols-1>_0, corner_0_<rows-1>, corner_<cols-1>_<rows-1>, "
                          "centre; default all five")


class CheckCreate(_Input):
    """A re-check: revisit ``stations`` of the calibration's run (spread over its captured
    stations; default 5) or the given ``poses``, not both."""

    # the rule of ``_one_plan`` in the OpenAPI document
    model_config = ConfigDict(json_schema_extra={"not": {
        "properties": {"stations": {"type": "integer"}, "poses": {"type": "array"}},
        "required": ["stations", "poses"]}})

    stations: Annotated[int, Field(ge=1, le=50)] | None = Field(
        None, description="how many of the calibration's stations to revisit (default 5)")
    poses: Annotated[list[Pose], Field(min_length=1, max_length=50)] | None = Field(
        None, description="TCP poses to visit instead, [x, y, z, rx, ry, rz] (m, rad)")

    @model_validator(mode="after")
    def _one_plan(self) -> CheckCreate:
        if self.stations is not None and self.poses is not None:
            raise ValueError("give either 'stations' (how many of the calibration's stations "
                             "to revisit) or 'poses', not both")
        return self


class ValidationPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)  # read from the stored row

    id: str
    calibration_id: str
    kind: Literal["dot_hit", "check"]
    state: Literal["running", "done", "failed"]
    result: dict[str, Any] | None = Field(
        None, description="the report. dot_hit: probe, the board observation, per point id, "
                          "commanded and reached probe-tip positions (base frame, m) and "
                          "error_m against the truth (mock cells), and error_m mean / max. "
                          "check: state ok | degraded, the mean camera pose offset and its "
                          "limits, per station rms_px, offset and ok | degraded")
    error: str | None
    error_code: str | None = Field(None, description=_ERROR_CODE)
    created_at: dt.datetime
    finished_at: dt.datetime | None


class ExportQuery(BaseModel):
    """The format of ``GET /calibrations/{id}/export`` and the names written into it."""

    format: ExportFormat = Field(  # type: ignore[valid-type]
        "json", description=formats_help())
    camera_name: str = Field("camera", description="ROS camera_name, joint and node prefix")
    parent_frame: str | None = Field(None, description="frame the camera is fixed to; default "
                                                       "tool0 (eye-in-hand) or base")
    child_frame: str | None = Field(None, description="default <camera_name>_optical_frame")


class CalibrationQuery(BaseModel):
    """Filters and the page of ``GET /calibrations``."""

    run_id: str | None = Field(None, description="only this run's")
    cell: str | None = Field(None, max_length=255, description="only this cell's (any service "
                                                              "on the database lists them)")
    active: bool | None = Field(None, description="true: only calibrations active now on "
                                                  "their cell; false: only the others")
    state: Literal["running", "done", "failed"] | None = None
    setup: Literal["eye_in_hand", "eye_to_hand"] | None = None
    limit: int = Field(50, ge=1, le=200)
    cursor: str | None = Field(None, max_length=100,
                               description="the next page: `next_cursor` of the page before "
                                           "(keyset: as fast deep in the history as at its top)",
                               json_schema_extra={"pattern": r"^[0-9]{1,19}\.[0-9a-f]{32}$"})
    offset: int = Field(0, ge=0, le=MAX_INDEX, description="rows to skip (prefer `cursor`)")


class CalibrationSummary(BaseModel):
    """A calibration in a listing: what tells calibrations apart, without the result."""

    id: str
    run_id: str
    cell: str
    setup: str
    robot: str
    state: Literal["running", "done", "failed"]
    method: str | None = Field(description="the solver asked for")
    rms_px: float | None = Field(description="RMS reprojection error; None without camera model")
    verdict: Literal["pass", "warn", "fail"] | None = Field(
        None, description="the result's quality verdict; None while running or failed")
    active: bool = Field(description="its cell's current calibration for its setup")
    error: str | None
    error_code: str | None = Field(None, description=_ERROR_CODE)
    created_at: dt.datetime
    finished_at: dt.datetime | None


class CalibrationPage(BaseModel):
    """One page of a listing, newest first; ``next_cursor`` (and ``next_offset``) is None on
    the last page."""

    items: list[CalibrationSummary]
    total: int = Field(description="how many match the filters, counted up to a limit "
                                   "(1,000)")
    total_exact: bool = Field(description="false when more than `total` match: the count "
                                          "stops at its limit, so a listing costs the same "
                                          "however long the plant's history")
    limit: int
    offset: int
    next_offset: int | None
    next_cursor: str | None = Field(description="give as `cursor` for the next page; None "
                                                "when this page is not full")


class ActivationPublic(BaseModel):
    """One period in which a calibration was the robot cell's current one."""

    calibration_id: str
    active_from: dt.datetime
    active_until: dt.datetime | None = Field(description="None while it is still active")


class ActiveCalibration(BaseModel):
    """The calibration a cell controller should use now, and what was active when."""

    cell: str
    setup: str
    robot: str
    activated_at: dt.datetime
    calibration: CalibrationPublic
    history: list[ActivationPublic] = Field(description="newest first, the current one first")
