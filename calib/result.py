"""The calibration result ``cellcal/result@1`` as pydantic models, one type per block: the
quality checks (``calib.quality``) make its ``Finding`` and ``QualityBlock``, the service's
document builder (``service.results.document``) the whole ``Result``, which the service stores
as JSON and answers at ``GET /calibrations/{id}`` (so the OpenAPI document shows every field),
and the report, plots, exports and validations read as typed attributes.

Only ``format``, ``setup``, ``camera``, ``target``, ``hand_eye`` and ``target_pose`` are required
(product.md, "Result"); every other block is optional, so older and hand-written documents
still validate. ``camera`` is None for a pose-only hand-eye calibration, ``hand_eye`` and
``target_pose`` None for an intrinsics-only one. Version 1 only grows: unknown fields are kept
(``extra="allow"``), and the tests check that what cellcal itself writes has none.

Data in metres and radians; names ending in ``_mm``, ``_deg`` or ``_px`` are figures for
people (millimetres, degrees, pixels).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from calib.fields import FiniteFloat

RESULT_FORMAT = "cellcal/result@1"

#: A 1-sigma figure: a scalar, or a small-angle / translation vector (3,); None = not estimated.
Sigma = float | list[float] | None
Row4 = Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)]
Row3 = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]


class _Block(BaseModel):
    model_config = ConfigDict(extra="allow")


class Transform(_Block):
    """A rigid transform ``T_a_b`` (maps points of b into a), docs/conventions.md."""

    matrix: Annotated[list[Row4], Field(min_length=4, max_length=4,
                                        description="4x4 homogeneous matrix, metres")]
    pose: Annotated[list[FiniteFloat], Field(min_length=6, max_length=6)] | None = Field(
        None, description="the same as a UR pose [x, y, z, rx, ry, rz] (m, rad)")


class CameraModel(_Block):
    """The pinhole camera with OpenCV's distortion model."""

    image_size: Annotated[list[Annotated[int, Field(gt=0)]],
                          Field(min_length=2, max_length=2, description="[width, height] px")]
    K: Annotated[list[Row3], Field(min_length=3, max_length=3,
                                   description="camera matrix (3, 3), pixels")]
    dist: list[FiniteFloat] = Field(description="OpenCV distortion k1, k2, p1, p2, k3[, ...]")
    rms_px: float | None = Field(None, description="RMS reprojection error")
    sigma_px: float | None = Field(None, description="estimated corner noise, 1-sigma")


class BoardScale(_Block):
    """The board's scale factors (Strobl & Hirzinger eq. 4: true point (κν x, κ y, 0))."""

    kappa: float = Field(description="κ: true / nominal square size")
    nu: float = Field(1.0, description="ν: x / y scale of the printed board")
    kappa_sigma: float | None = None
    nu_sigma: float | None = None


class Uncertainty(_Block):
    """1-sigma uncertainties; rotations as small angles (rad) about the axes of the frame
    named first, translations in metres; 0 = held fixed."""

    note: str | None = Field(None, description="which sigma is reported and where it came from")
    variance_factor: float | None = None
    camera: dict[str, float | None] | None = Field(
        None, description="fx, fy, cx, cy (px), k1, k2, p1, p2, k3, nu, kappa")
    hand_eye_rot_rad: list[float] | None = None
    hand_eye_trans_m: list[float] | None = None
    target_pose_rot_rad: list[float] | None = None
    target_pose_trans_m: list[float] | None = None
    kappa: float | None = Field(None, description="pose-only results: κ's sigma")
    jackknife_folds: int | None = None
    source: dict[str, Literal["formal", "jackknife"]] | None = Field(
        None, description="per parameter, which figure was reported")
    formal: dict[str, Sigma] | None = Field(None, description="from the Jacobian")
    jackknife: dict[str, Sigma] | None = Field(None, description="spread over the folds")
    jackknife_expected: dict[str, Sigma] | None = Field(
        None, description="the spread over the folds the noise model predicts (the "
                          "jackknife scales the formal sigma by its excess over this)")
    held_at_one: list[str] | None = Field(
        None, description="parameters the model selection held at 1 (kappa, nu)")
    held_shift: dict[str, Sigma] | None = Field(
        None, description="per pose σ, the shift when those are estimated instead")
    held_bias: dict[str, Sigma] | None = Field(
        None, description="per pose σ, the bias that shift shows beyond its own noise, "
                          "added to the σ in quadrature")
    workspace_extrapolation: dict[str, Sigma] | None = Field(
        None, description="hand-eye σ added in quadrature for using the stations' estimate "
                          "over the whole workspace box (calib.extrapolation)")


class StationFit(_Block):
    """Per-station residuals. Image-based: corners and their residuals, ``rms_px`` the
    fitted model's reprojection RMS (the joint model with the robot correction, or the
    intrinsic stage's own pose), ``chain_rms_px`` the image predicted from the uncorrected
    robot reading through hand-eye and target pose, ``correction_*`` and ``mahalanobis`` the
    joint estimate's robot-pose correction, ``loo_*`` the eq. (23) leave-one-out prediction
    error; pose-only: the residual of the robot pose predicted through the estimate."""

    id: str
    n_corners: int | None = None
    rms_px: float | None = None
    chain_rms_px: float | None = Field(
        None, description="image predicted from the uncorrected robot reading")
    correction_rot_rad: float | None = None
    correction_trans_m: float | None = None
    mahalanobis: float | None = None
    loo_rot_rad: float | None = None
    loo_trans_m: float | None = None
    corners_px: list[list[float]] | None = Field(None, description="detected corners (N, 2)")
    residuals_px: list[list[float]] | None = Field(None, description="projection - corners")
    point_ids: list[int] | None = Field(None, description="board point id of each corner")
    residual_rot_rad: float | None = None
    residual_trans_m: float | None = None

    @classmethod
    def of_image(cls, id: str, corners_px: np.ndarray, residuals_px: np.ndarray,
                 point_ids: np.ndarray, **figures: float | None) -> StationFit:
        """An image station's fit: its detected corners (N, 2), the fitted model's projection
        minus them (N, 2), both to 0.001 px (far below their noise, to keep the result small),
        and their board point ids (N,). ``figures``: any of ``IMAGE_FIGURES``; every one is
        written, None where not given or not finite."""
        given = {k: figures.pop(k, None) for k in IMAGE_FIGURES}
        if figures:
            raise TypeError(f"not a figure of an image station: {', '.join(figures)}")
        return cls(id=id, n_corners=len(corners_px),
                   **{k: None if v is None or not np.isfinite(v) else float(v)
                      for k, v in given.items()},
                   corners_px=np.round(corners_px, 3).tolist(),
                   residuals_px=np.round(residuals_px, 3).tolist(),
                   point_ids=np.asarray(point_ids).tolist())


#: The per-station figures of an image station (``StationFit.of_image``).
IMAGE_FIGURES = ("rms_px", "chain_rms_px", "correction_rot_rad", "correction_trans_m",
                 "mahalanobis", "loo_rot_rad", "loo_trans_m")


class Rejected(_Block):
    id: str
    reason: str


class Motions(_Block):
    used: int
    skipped: int


def _optional(description: str) -> Any:
    """An optional field of the document (None when not measured or not applicable), described."""
    return Field(None, description=description)


class _PredictionFigures(_Block):
    """How far the prediction from robot poses alone was from what the camera saw: corners
    (px, and mm at the board) and the camera pose (rotation, translation)."""

    rms_px: float | None = _optional("RMS corner error in the image, px")
    rms_mm: float | None = _optional("RMS corner error on the board plane, mm")
    rot_deg: float | None = _optional("predicted vs observed camera pose: rotation, deg")
    trans_mm: float | None = _optional("predicted vs observed camera pose: translation, mm")


class HeldOutStation(_PredictionFigures):
    id: str
    fold: int | None = _optional("the fold that held this station out")
    max_px: float | None = _optional("largest corner error in the image, px")
    dropped: bool | None = _optional(
        "the fit dropped this station as an outlier: predicted, never trained on")


class CrossValidationBlock(_PredictionFigures):
    """Held-out stations predicted from their robot poses alone: every station whose board
    was detected, the ones the fit dropped as outliers included (the headline figures)."""

    kind: str = Field(description="k-fold or leave-one-out")
    folds: int
    kept_rms_px: float | None = _optional(
        "RMS corner error over the stations the fit kept (dropped ones left out), px")
    kept_rms_mm: float | None = _optional("the same on the board plane, mm")
    dropped: list[str] | None = _optional("ids of the stations the fit dropped as outliers")
    stations: list[HeldOutStation] = Field(default_factory=list)
    note: str | None = None

    def dropped_clause(self) -> str:
        """What the headline hides without it: the figure over the kept stations and the ids
        the fit dropped, e.g. ``"; 0.48 px over the 19 kept stations, dropped as outliers:
        04, 11"``; empty when none was dropped."""
        if not self.dropped or self.kept_rms_px is None:
            return ""
        kept = len(self.stations) - len(self.dropped)
        return (f"; {self.kept_rms_px:.2f} px over the {kept} kept stations, dropped as "
                f"outliers: {', '.join(self.dropped)}")


class Candidate(_Block):
    """A model tried in model selection, with its cross-validated figures."""

    name: str
    chosen: bool
    cv_rms_px: float | None = _optional("cross-validated corner error, px")
    cv_rms_mm: float | None = _optional("the same on the board plane, mm")
    cv_trans_mm: float | None = _optional("cross-validated camera-pose translation error, mm")
    cv_range_mm: float | None = _optional("cross-validated camera-to-board distance error, mm")
    cv_rot_deg: float | None = _optional("cross-validated camera-pose rotation error, deg")
    kappa: str | None = _optional("κ 'estimated' or 'held at 1'")
    nu: str | None = _optional("ν 'estimated' or 'held at 1'")
    robot_noise: str | None = _optional("robot noise 'estimated' or 'assumed'")
    kappa_value: float | None = None
    nu_value: float | None = None
    robot_noise_rot_rad: float | None = _optional("robot pose noise, 1-sigma")
    robot_noise_trans_m: float | None = _optional("robot pose noise, 1-sigma")
    sigma_px: float | None = _optional("corner noise of the fit, 1-sigma")


class ModelSelection(_Block):
    chosen: str
    decisions: list[str] = Field(default_factory=list)
    rule: str | None = None
    candidates: list[Candidate] = Field(default_factory=list)


#: Severities of a finding, mildest first; a result's verdict is its worst finding's.
SEVERITIES = ("info", "warn", "fail")
Verdict = Literal["pass", "warn", "fail"]


class Finding(_Block):
    """One quality finding: a stable code, its severity (info, warn or fail), a message for
    people; its figures (named per code) follow as further fields."""

    code: str
    severity: str
    message: str

    @property
    def values(self) -> dict[str, Any]:
        """The finding's figures, by name."""
        return dict(self.model_extra or {})


class QualityBlock(_Block):
    """The verdict and the findings it rests on."""

    verdict: Verdict
    findings: list[Finding] = Field(default_factory=list)

    @classmethod
    def of(cls, findings: list[Finding]) -> QualityBlock:
        """The quality of ``findings``: the verdict is the worst severity among them."""
        worst = max((SEVERITIES.index(f.severity) for f in findings), default=0)
        verdict: Verdict = ("pass", "warn", "fail")[worst]
        return cls(verdict=verdict, findings=findings)


class Software(_Block):
    name: str
    version: str
    command: str | None = None


class Result(_Block):
    """A calibration result, ``cellcal/result@1``."""

    format: Literal["cellcal/result@1"]
    setup: Literal["eye_in_hand", "eye_to_hand"]
    camera: CameraModel | None = Field(description="None: pose-only hand-eye calibration")
    target: BoardScale
    hand_eye: Transform | None = Field(
        description="T_tcp_cam (eye-in-hand) or T_base_cam (eye-to-hand); None: intrinsics "
                    "only")
    target_pose: Transform | None = Field(
        description="T_base_target (eye-in-hand) or T_tcp_target (eye-to-hand)")
    robot_translation_map: list[list[float]] | None = Field(
        None, description="S (3x3, base frame): the robot's translation readings t are "
                          "corrected to t + S t before hand_eye and target_pose apply (scale "
                          "and skew of an industrial arm's positions, chosen by "
                          "cross-validation); None: the readings are used as they are")
    uncertainty: Uncertainty | None = None
    noise_estimate: dict[str, float | None] | None = Field(
        None, description="pose-only: the robot noise the refinement estimated")
    stations: list[StationFit] | None = None
    rejected: list[Rejected] | None = None
    motions: Motions | None = None
    validation: dict[str, float | int | str | None] | None = Field(
        None, description="E_R, E_t (eq. 21-22), leave-one-out prediction errors (eq. 23)")
    method: str | None = None
    options: dict[str, Any] | None = Field(None, description="the solver options used")
    cross_validation: CrossValidationBlock | None = None
    model_selection: ModelSelection | None = None
    quality: QualityBlock | None = None
    software: Software | None = None
    created: str | None = Field(None, description="ISO 8601 time, UTC")

    def document(self) -> dict[str, Any]:
        """The JSON document: the fields it was read with (none added), unknown ones kept."""
        return self.model_dump(mode="json", exclude_unset=True)


def parse_result(doc: Any, where: str = "result") -> Result:
    """A result document as ``Result`` (a ``Result`` as it is); ValueError with one line
    naming the first problem."""
    if isinstance(doc, Result):
        return doc
    try:
        return Result.model_validate(doc)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        more = f" (and {exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
        raise ValueError(f"{where}: not a {RESULT_FORMAT} document: "
                         f"{loc or 'document'}: {first['msg']}{more}") from None
