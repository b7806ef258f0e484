"""Mock scene: the data that fully defines a simulated robot cell, and its true geometry.

A scene is the JSON file described in ``product.md`` ("Mock scene"): camera, board (with
its *true* κ and ν), setup, true hand-eye and target pose, noise levels and a seed. Frames and
pose conventions are those of ``docs/conventions.md``:

- eye-in-hand: ``hand_eye = T_tcp_cam``, ``target_pose = T_base_target``;
- eye-to-hand: ``hand_eye = T_base_cam``, ``target_pose = T_tcp_target``.

Everything here is noise-free truth; drivers add the scene's noise when they report.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)
from scipy.spatial.transform import Rotation

from calib import (
    BoardTarget,
    CheckerboardTarget,
    board_points,
    camera_from_robot,
    check_transforms,
    cuts_board_at_corner,
    invert,
    make_transform,
    matrix_from_ur_pose,
    robot_from_camera,
)
from calib import CharucoTarget as CalibCharucoTarget
from drivers.config_files import describe_validation_error
from mocks.ur_kinematics import DHOffsets, kinematic_error

#: Fraction of the image the pattern spans (along its tighter axis) at the working distance.
WORKING_FILL = 0.65

Matrix4 = Annotated[list[list[float]], Field(min_length=4, max_length=4)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Camera(_Strict):
    """Pinhole camera with OpenCV distortion ``[k1, k2, p1, p2, k3, ...]``."""

    image_size: tuple[Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]] = Field(
        description="[width, height] in pixels")
    K: list[list[float]] = Field(description="3x3 camera matrix")
    dist: list[float] = Field(default_factory=lambda: [0.0] * 5,
                              description="OpenCV distortion coefficients")

    @field_validator("K")
    @classmethod
    def _check_k(cls, K: list[list[float]]) -> list[list[float]]:
        A = np.asarray(K, dtype=float)
        if A.shape != (3, 3) or not np.isfinite(A).all():
            raise ValueError(f"K must be a finite 3x3 matrix, got shape {A.shape}")
        if A[0, 0] <= 0 or A[1, 1] <= 0:
            raise ValueError("K focal lengths fx = K[0][0] and fy = K[1][1] must be positive")
        if not np.allclose(A[2], [0.0, 0.0, 1.0]) or A[1, 0] != 0:
            raise ValueError("K must be upper triangular with last row [0, 0, 1]")
        return K

    @field_validator("dist")
    @classmethod
    def _check_dist(cls, dist: list[float]) -> list[float]:
        if len(dist) not in (4, 5, 8, 12, 14):
            raise ValueError(f"dist must have 4, 5, 8, 12 or 14 coefficients, got {len(dist)}")
        if not np.isfinite(dist).all():
            raise ValueError("dist contains NaN or inf")
        return dist

    @property
    def k_matrix(self) -> np.ndarray:
        """Camera matrix, shape (3, 3)."""
        return np.asarray(self.K, dtype=float)

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion coefficients, shape (n,)."""
        return np.asarray(self.dist, dtype=float)


class _Printed(_Strict):
    """The truth of a printed board: its scale κ and its extra scale ν along x."""

    kappa: float = Field(1.0, gt=0.9, lt=1.1, description="true scale of the printed board")
    nu: float = Field(1.0, gt=0.9, lt=1.1, description="true extra scale along x")


class Target(_Printed, CheckerboardTarget):
    """Checkerboard as printed: its configuration (``calib.boards``) and the true κ, ν."""


class CharucoTarget(_Printed, CalibCharucoTarget):
    """ChArUco board as printed: its configuration (``calib.boards``, OpenCV's layout, drawn
    by ``mocks.markers``) and the true κ, ν.

    Corner id k (OpenCV's charuco corner id) is inner corner k of the (cols - 1) x (rows - 1)
    grid, row-major: id 0 at the target origin, x along cols.
    """

    @property
    def inner_corners(self) -> tuple[int, int]:
        """(cols - 1, rows - 1): the chessboard corners' grid."""
        return self.squares[0] - 1, self.squares[1] - 1


def _target_type(value: object) -> object:
    """The ``type`` a scene target is read as; a file without one holds a checkerboard."""
    if isinstance(value, dict):
        return value.get("type", "checkerboard")
    return getattr(value, "type", None)


#: The board a scene holds, told apart by ``type``.
SceneTarget = Annotated[Annotated[Target, Tag("checkerboard")]
                        | Annotated[CharucoTarget, Tag("charuco")],
                        Discriminator(_target_type)]


class Noise(_Strict):
    """Noise the mock devices add: robot pose readings and camera images."""

    robot_rot_deg: float = Field(0.0, ge=0.0, le=5.0, description="sigma of TCP rotation error")
    robot_trans_mm: float = Field(0.0, ge=0.0, le=50.0, description="sigma of TCP position error")
    image_noise: float = Field(0.0, ge=0.0, le=50.0,
                               description="sigma of pixel noise, grey levels")
    blur_px: float = Field(0.0, ge=0.0, le=20.0, description="sigma of Gaussian blur, pixels")


def _small(what: str, limit: float, unit: str) -> AfterValidator:
    """A check that a DH offset is finite and within ±``limit`` (as a real arm's are)."""
    def check(v: float) -> float:
        if not abs(v) <= limit:  # NaN fails too
            raise ValueError(f"DH {what} offsets must be finite and within ±{limit:g} {unit}")
        return v

    return AfterValidator(check)


_AngleOffset = Annotated[float, _small("angle", 1.0, "deg")]
_LengthOffset = Annotated[float, _small("length", 10.0, "mm")]


class Kinematics(_Strict):
    """Systematic kinematic errors of the simulated arm, a UR5e (``mocks.ur_kinematics``).

    Offsets of its true DH parameters from the nominal table its controller computes poses
    with: the reported pose of a configuration is then off by the same (configuration-
    dependent) transform at every visit, as on a real arm, besides the per-reading noise.
    """

    dh_theta_deg: list[_AngleOffset] = Field(default_factory=lambda: [0.0] * 6, min_length=6,
                                             max_length=6, description="joint zero offsets")
    dh_d_mm: list[_LengthOffset] = Field(default_factory=lambda: [0.0] * 6, min_length=6,
                                         max_length=6, description="link offset errors")
    dh_a_mm: list[_LengthOffset] = Field(default_factory=lambda: [0.0] * 6, min_length=6,
                                         max_length=6, description="link length errors")
    dh_alpha_deg: list[_AngleOffset] = Field(default_factory=lambda: [0.0] * 6, min_length=6,
                                             max_length=6, description="link twist errors")

    def offsets(self) -> DHOffsets:
        """The offsets in metres and radians."""
        return DHOffsets(theta=np.deg2rad(self.dh_theta_deg), d=np.array(self.dh_d_mm) * 1e-3,
                         a=np.array(self.dh_a_mm) * 1e-3, alpha=np.deg2rad(self.dh_alpha_deg))


class WorkspaceBox(_Strict):
    """The cell's safety box: an axis-aligned box in the base frame, metres."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @model_validator(mode="after")
    def _ordered(self) -> WorkspaceBox:
        if not all(a < b for a, b in zip(self.lo, self.hi, strict=True)):
            raise ValueError(f"workspace lo {list(self.lo)} must be below hi {list(self.hi)} "
                             "on every axis")
        return self

    def contains(self, p: np.ndarray) -> bool:
        """Whether the point ``p`` (3,) lies inside (borders included)."""
        return bool(np.all(p >= self.lo) and np.all(p <= self.hi))


class MockScene(_Strict):
    """A complete simulated cell (see ``product.md``, "Mock scene").

    ``blind`` hides the scene from the service as a real cell would: the backend describes
    only what a user configures (the setup and the board), neither the hand-eye nor the camera,
    and offers no ground truth. ``workspace`` is the cell's safety box: a move whose tcp, or
    eye-in-hand whose camera, would end outside it is refused with a protective stop and
    counted (``MockRobot.refused_moves``), so tests can assert that nothing ever tried.
    """

    format: Literal["cellcal/scene@1"] = "cellcal/scene@1"
    camera: Camera
    target: SceneTarget
    setup: Literal["eye_in_hand", "eye_to_hand"]
    hand_eye: Matrix4 = Field(description="true T_tcp_cam (eye-in-hand) or T_base_cam, 4x4")
    target_pose: Matrix4 = Field(
        description="true T_base_target (eye-in-hand) or T_tcp_target, 4x4")
    noise: Noise = Field(default_factory=Noise)
    seed: int = 0
    kinematics: Kinematics | None = Field(
        None, description="systematic kinematic errors of the arm (UR5e DH offsets); "
                          "default none")
    start_tcp_pose: list[float] | None = Field(
        None, min_length=6, max_length=6,
        description="[x, y, z, rx, ry, rz]; default: camera square to the target centre")
    blind: bool = Field(False, description="reveal only what a real cell reveals: no hand-eye, "
                                           "camera or truth to the service")
    workspace: WorkspaceBox | None = Field(
        None, description="safety box, base frame (m): moves ending outside it (tcp, and the "
                          "camera eye-in-hand) are refused with a protective stop")

    @field_validator("hand_eye", "target_pose")
    @classmethod
    def _check_transform(cls, T: list[list[float]]) -> list[list[float]]:
        check_transforms(np.asarray(T, dtype=float), "transform")
        return T

    @model_validator(mode="after")
    def _check_start(self) -> MockScene:
        if self.start_tcp_pose is not None and not np.isfinite(self.start_tcp_pose).all():
            raise ValueError("start_tcp_pose contains NaN or inf")
        return self

    @property
    def hand_eye_matrix(self) -> np.ndarray:
        """True hand-eye transform, shape (4, 4)."""
        return np.asarray(self.hand_eye, dtype=float)

    @property
    def target_pose_matrix(self) -> np.ndarray:
        """True target pose, shape (4, 4)."""
        return np.asarray(self.target_pose, dtype=float)

    def nominal_target(self) -> BoardTarget:
        """The board as a user configures it (``calib.boards``' target type): the printed
        layout without the truth κ, ν."""
        return self.target.board().target()

    def true_board_points(self) -> np.ndarray:
        """True (κ, ν-scaled) inner corners in the target frame, shape (N, 3), row-major."""
        t = self.target
        return board_points(t.inner_corners, t.square_size_m, kappa=t.kappa, nu=t.nu)

    def pattern_centre(self) -> np.ndarray:
        """Centre of the true inner-corner grid in the target frame, shape (3,)."""
        return self.true_board_points()[[0, -1]].mean(axis=0)

    def working_distance(self) -> float:
        """Camera-to-board distance (m) at which the square pattern fills ``WORKING_FILL``."""
        cols, rows = self.target.inner_corners
        w, h = self.camera.image_size
        K = self.camera.k_matrix
        s = self.target.square_size_m * self.target.kappa
        width_m, height_m = (cols + 1) * s * self.target.nu, (rows + 1) * s
        return max(K[0, 0] * width_m / (WORKING_FILL * w),
                   K[1, 1] * height_m / (WORKING_FILL * h))

    def start_pose(self) -> np.ndarray:
        """Start T_base_tcp, shape (4, 4): ``start_tcp_pose`` or square to the target centre.

        The default puts the camera on the board normal through the pattern centre at the
        working distance, camera x along target x (so the image shows the origin top-left).
        """
        if self.start_tcp_pose is not None:
            return matrix_from_ur_pose(np.asarray(self.start_tcp_pose))
        c = self.pattern_centre()
        T_cam_target = make_transform(np.eye(3), [-c[0], -c[1], self.working_distance()])
        return tcp_pose_for_camera(self, T_cam_target)


def true_tcp_pose(scene: MockScene, T_base_tcp: np.ndarray) -> np.ndarray:
    """Where the flange really is when the controller reports T_base_tcp ``T_base_tcp``.

    Shapes (..., 4, 4). The scene's ``kinematics`` offsets move it by the arm's kinematic error
    (``mocks.ur_kinematics.kinematic_error``); without them it is where it is reported.
    Raises ``ValueError`` for poses beyond the UR5e's reach when there are offsets.
    """
    T = np.asarray(T_base_tcp, dtype=float)
    if scene.kinematics is None:
        return T.copy()
    offsets = scene.kinematics.offsets()
    flat = T.reshape(-1, 4, 4)
    out = np.stack([P @ kinematic_error(P, offsets) for P in flat])
    return out.reshape(T.shape)


def camera_pose_for_tcp(scene: MockScene, T_base_tcp: np.ndarray) -> np.ndarray:
    """True T_cam_target seen from robot pose(s) T_base_tcp, shapes (..., 4, 4) -> (..., 4, 4).

    Eye-in-hand: ``inv(T_tcp_cam) @ inv(T_base_tcp) @ T_base_target``;
    eye-to-hand: ``inv(T_base_cam) @ T_base_tcp @ T_tcp_target`` (``docs/conventions.md``).
    """
    return camera_from_robot(T_base_tcp, scene.hand_eye_matrix, scene.target_pose_matrix,
                             scene.setup)


def tcp_pose_for_camera(scene: MockScene, T_cam_target: np.ndarray) -> np.ndarray:
    """Robot pose(s) T_base_tcp giving camera observation(s) T_cam_target, (..., 4, 4).

    Inverse of :func:`camera_pose_for_tcp`.
    """
    return robot_from_camera(np.asarray(T_cam_target, dtype=float), scene.hand_eye_matrix,
                             scene.target_pose_matrix, scene.setup)


@dataclass(frozen=True)
class StationSpread:
    """How :func:`sample_station_poses` spreads the stations (see there)."""

    max_tilt_deg: float = 35.0
    distance_band: tuple[float, float] = (0.8, 1.3)
    margin_frac: float = 0.04
    cut_fraction: float = 0.0
    min_cut_points: int = 12


def sample_station_poses(scene: MockScene, n: int, rng: np.random.Generator,
                         spread: StationSpread = StationSpread()) -> np.ndarray:
    """Varied, realistic calibration stations T_base_tcp, shape (n, 4, 4).

    Each station looks at a point near the pattern centre from a view direction tilted up to
    ``spread.max_tilt_deg`` from the board normal about a random in-plane axis, at a distance
    drawn from ``spread.distance_band`` times the working distance, rolled by a random angle in
    ±180° about the optical axis. Views are rejected until the whole board plate outline
    (pattern plus one square of white margin) projects inside the image with
    ``spread.margin_frac`` of the smaller image side to spare. A share ``spread.cut_fraction``
    of the stations (spread evenly over the sequence) instead cut the board at the image
    border on purpose, as the planner's cut stations do: look-at points range over the whole
    pattern, and a view is kept when ``calib.planning.cuts_board_at_corner`` accepts its
    projected corners (at least ``spread.min_cut_points`` in view, one near an image corner).
    Poses are true (noise-free) commands.
    """
    cols, rows = scene.target.inner_corners
    s = scene.target.square_size_m * scene.target.kappa
    sx = s * scene.target.nu
    outline = _rectangle_outline((-2.0 * sx, -2.0 * s), ((cols + 1) * sx, (rows + 1) * s))
    w, h = scene.camera.image_size
    centre = scene.pattern_centre()
    d0 = scene.working_distance()
    half_extent = np.array([(cols - 1) * sx, (rows - 1) * s, 0.0]) / 2
    if n < 0:
        raise ValueError(f"number of stations must be >= 0, got {n}")
    out: list[np.ndarray] = []
    for k in range(n):
        cut = np.floor((k + 1) * spread.cut_fraction) > np.floor(k * spread.cut_fraction)
        for _ in range(1000):
            tilt = np.deg2rad(spread.max_tilt_deg) * np.sqrt(rng.uniform())
            azimuth = rng.uniform(-np.pi, np.pi)
            roll = rng.uniform(-np.pi, np.pi)
            jitter = 1.0 if cut else 0.2
            look_at = centre + half_extent * rng.uniform(-jitter, jitter, 3) * [1.0, 1.0, 0.0]
            T = _look_at_pose(look_at, tilt, azimuth, roll,
                              d0 * rng.uniform(*spread.distance_band))
            if (_cuts_board(scene, T, spread) if cut
                    else _in_view(scene, T, outline, spread.margin_frac * min(w, h))):
                out.append(T)
                break
        else:
            raise RuntimeError(f"could not place {n} stations with the board in view; "
                               "check the camera, target size and distance band")
    return tcp_pose_for_camera(scene, np.array(out).reshape(n, 4, 4))


def _project(scene: MockScene, T_cam_target: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels of target-frame ``points`` (N, 3) seen from ``T_cam_target``; NaN behind."""
    uv, _ = cv2.projectPoints(points, cv2.Rodrigues(T_cam_target[:3, :3])[0],
                              T_cam_target[:3, 3], scene.camera.k_matrix,
                              scene.camera.dist_coeffs)
    uv = uv.reshape(-1, 2)
    uv[points @ T_cam_target[2, :3] + T_cam_target[2, 3] <= 0.0] = np.nan
    return uv


def _in_view(scene: MockScene, T_cam_target: np.ndarray, outline: np.ndarray,
             margin: float) -> bool:
    """Whether ``outline`` (N, 3) projects inside the image with ``margin`` pixels to spare."""
    w, h = scene.camera.image_size
    uv = _project(scene, T_cam_target, outline)
    with np.errstate(invalid="ignore"):
        return bool((uv >= margin).all() and (uv <= [w - margin, h - margin]).all())


def _cuts_board(scene: MockScene, T_cam_target: np.ndarray, spread: StationSpread) -> bool:
    """Whether the view cuts the board at the image border as a cut station should."""
    size = tuple(scene.camera.image_size)
    uv = _project(scene, T_cam_target, scene.true_board_points())
    return cuts_board_at_corner(uv, size, spread.min_cut_points)


def _look_at_pose(look_at: np.ndarray, tilt: float, azimuth: float, roll: float,
                  distance: float) -> np.ndarray:
    """T_cam_target of a camera at ``distance`` looking at ``look_at`` (target frame).

    The optical axis is the board normal (+z, away from the camera) tilted by ``tilt`` about
    the in-plane axis at angle ``azimuth`` from x, then the camera rolls by ``roll``.
    """
    axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    v = Rotation.from_rotvec(axis * tilt).apply([0.0, 0.0, 1.0])
    x0 = np.array([1.0, 0.0, 0.0]) - v[0] * v
    x0 /= np.linalg.norm(x0)
    R = np.stack([x0, np.cross(v, x0), v], axis=1)
    R = R @ Rotation.from_rotvec([0.0, 0.0, roll]).as_matrix()
    return invert(make_transform(R, look_at - distance * v))


def _rectangle_outline(lo: tuple[float, float], hi: tuple[float, float],
                       per_side: int = 16) -> np.ndarray:
    """Points along a rectangle's border in the z = 0 plane, shape (4 * per_side, 3)."""
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)
    (x0, y0), (x1, y1) = lo, hi
    xs = np.concatenate([x0 + (x1 - x0) * t, np.full_like(t, x1),
                         x1 - (x1 - x0) * t, np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + (y1 - y0) * t,
                         np.full_like(t, y1), y1 - (y1 - y0) * t])
    return np.stack([xs, ys, np.zeros_like(xs)], axis=1)


def default_scene() -> MockScene:
    """A realistic eye-in-hand cell: 1280x1024 camera, 11x8 board of 30 mm squares.

    The camera (f = 1400 px, mild barrel distortion) sits about 10 cm off the flange, looking
    along tool z, turned 90° about it and tilted a little. The board lies face up on the table
    0.5 m in front of the robot, slightly turned; its z axis points down (away from the camera).
    11 + 8 is odd, so the board's origin is unambiguous in every image.
    """
    R_tcp_cam = Rotation.from_euler("zxy", [90.0, 1.5, -2.0], degrees=True).as_matrix()
    T_tcp_cam = make_transform(R_tcp_cam, [0.021, -0.094, 0.038])
    R_base_target = (Rotation.from_euler("z", 3.0, degrees=True).as_matrix()
                     @ np.diag([1.0, -1.0, -1.0]))
    T_base_target = make_transform(R_base_target, [0.35, 0.105, 0.002])
    return MockScene(
        camera=Camera(
            image_size=(1280, 1024),
            K=[[1400.0, 0.0, 636.2], [0.0, 1401.5, 515.8], [0.0, 0.0, 1.0]],
            dist=[-0.12, 0.09, 0.0004, -0.0003, -0.02]),
        target=Target(inner_corners=(11, 8), square_size_m=0.03, kappa=1.005, nu=0.9975),
        setup="eye_in_hand",
        hand_eye=T_tcp_cam.tolist(),
        target_pose=T_base_target.tolist(),
        noise=Noise(robot_rot_deg=0.02, robot_trans_mm=0.1, image_noise=2.0, blur_px=0.7),
        seed=7,
    )


def charuco_scene() -> MockScene:
    """The default cell holding a 12x9-square ChArUco board (30 mm squares, 22 mm DICT_5X5_100
    markers, OpenCV's current layout) printed 0.4 % oversized with ν = 0.998."""
    target = CharucoTarget(type="charuco", squares=(12, 9), square_size_m=0.03,
                           marker_size_m=0.022, dictionary="DICT_5X5_100", kappa=1.004,
                           nu=0.998)
    return default_scene().model_copy(update={"target": target})


def load_scene(path: str | Path) -> MockScene:
    """Read and validate a mock scene JSON file (raises pydantic ``ValidationError``)."""
    return MockScene.model_validate(json.loads(Path(path).read_text()))


def read_scene(config: MockScene | str | Path | None) -> MockScene:
    """The scene a mock device is configured with: a scene, a scene file, or None for the
    default cell. Every failure to read a file is a one-line ``ValueError``."""
    if config is None:
        return default_scene()
    if isinstance(config, MockScene):
        return config
    try:
        return load_scene(config)
    except OSError as exc:
        raise ValueError(f"scene {config}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"scene {config}: not valid JSON ({exc})") from None
    except ValidationError as exc:
        raise ValueError(f"scene {config}: {describe_validation_error(exc)}") from None
