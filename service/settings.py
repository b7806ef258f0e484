"""Service configuration from the environment (prefix ``CELLCAL_``), checked at startup.

Bad configuration stops the service before it binds a port or touches a device: an unknown
device URL scheme, an empty workspace box, a missing scene file, or a non-loopback host
without an API key all raise a ``pydantic.ValidationError`` naming the setting.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import socket
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, SecretStr, ValidationInfo, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from calib import SolverOptions, Target, TargetAdapter, matrix_from_ur_pose
from drivers import registry
from drivers.base import CellHints

Vector3 = tuple[float, float, float]


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Settings(BaseSettings):
    """Everything the service needs to start; each field is ``CELLCAL_<NAME>`` in the env."""

    model_config = SettingsConfigDict(env_prefix="CELLCAL_", extra="ignore")

    data_dir: Path = Field(Path("./cellcal-data"),
                           description="where the database (default) and images live")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default sqlite:///<data_dir>/cellcal.db")
    cell: Annotated[str, Field(min_length=1, max_length=255, pattern=r"^\S(.*\S)?$")] = Field(
        default_factory=socket.gethostname,
        description="the robot cell this service drives, named on every run and calibration "
                    "so many cells can share one database (default: the host name)")
    lease_s: Annotated[float, Field(ge=1.0, le=3600.0)] = Field(
        15.0, description="heartbeat lease: a service silent this long is taken for dead and "
                          "its runs, calibrations and validations are recovered by the others")
    api_key: SecretStr | None = Field(None, description="bearer token every call but /health "
                                                        "needs")
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 8000
    robot: str = Field("mock://", description=f"robot URL: {registry.ROBOT_URLS}")
    camera: str = Field("mock://", description=f"camera URL: {registry.CAMERA_URLS}")
    scene: Path | None = Field(None, description="device configuration file handed to the "
                                                 "backends: the mock scene JSON for mock:// "
                                                 "devices (default: the built-in cell)")
    setup: Literal["eye_in_hand", "eye_to_hand"] | None = Field(
        None, description="default: what the robot's backend knows (a mock scene's setup), "
                          "else eye_in_hand")
    target: Target | None = Field(
        None, description="the board as JSON, the target type of station sets and of POST "
                          "/runs: a checkerboard {\"inner_corners\": [cols, rows], "
                          "\"square_size_m\": s} (\"type\": \"checkerboard\", the default) or a "
                          "ChArUco board {\"type\": \"charuco\", \"squares\": [cols, rows], "
                          "\"square_size_m\", \"marker_size_m\", \"dictionary\"}; default: what "
                          "the robot's backend knows (a mock scene's board)")
    target_inner_corners: tuple[int, int] | None = Field(
        None, exclude=True, description="the older spelling of a checkerboard target, with "
                                        "target_square_size_m; read into target")
    target_square_size_m: float | None = Field(None, exclude=True)
    workspace_min: Vector3 = Field((-1.5, -1.5, 0.0),
                                   description="lower corner of the TCP box, base frame, m")
    workspace_max: Vector3 = Field((1.5, 1.5, 1.5),
                                   description="upper corner of the TCP box, base frame, m")
    hand_eye_guess: tuple[float, float, float, float, float, float] | None = Field(
        None, description="rough hand_eye as [x, y, z, rx, ry, rz] (CAD) for automatic "
                          "planning; default: what the robot's backend knows (a mock scene's)")
    focal_px_guess: Annotated[float, Field(gt=0.0)] | None = Field(
        None, description="rough focal length in pixels for automatic planning; default: "
                          "what the robot's backend knows (a mock scene's camera)")
    max_stations: Annotated[int, Field(ge=3, le=10000)] = 500
    max_body_bytes: Annotated[int, Field(ge=1024)] = Field(
        4 * 2**20, description="largest request body, bytes (413 beyond); checked before the "
                               "body is read")
    database_busy_timeout_s: Annotated[float, Field(gt=0.0)] = Field(
        30.0, description="SQLite: how long a statement waits for another writer's lock")
    database_retry_s: Annotated[float, Field(ge=0.0)] = Field(
        60.0, description="how long a capture run retries a failing database write before it "
                          "is interrupted (resume it once the database is back)")
    max_image_pixels: Annotated[int, Field(ge=10_000)] = Field(
        25_000_000, description="largest posted image or camera frame, width x height: a "
                                "posted image beyond is answered 413 from its header, before "
                                "it is decoded")
    image_worker_memory_mb: Annotated[int, Field(ge=256)] = Field(
        3072, description="address space of the process that decodes a posted image and "
                          "searches it for the board; an image needing more is answered 413")
    image_cpu_s: Annotated[float, Field(gt=0.0)] = Field(
        20.0, description="CPU seconds the board search of one posted image may take (422 "
                          "image_too_complex beyond)")
    min_free_mb: Annotated[int, Field(ge=0)] = Field(
        64, description="free space the data directory's disk must keep: below it, runs fail "
                        "with disk_full, new runs are refused 503 and /health is degraded")
    report_wait_s: Annotated[float, Field(gt=0.0, le=600.0)] = Field(
        20.0, description="a report request waits this long for its page to be rendered, "
                          "then is answered 503 report_rendering with Retry-After")
    settle_timeout_s: Annotated[float, Field(gt=0.0)] = 5.0
    grab_timeout_s: Annotated[float, Field(gt=0.0)] = 2.0
    move_speed: Annotated[float, Field(gt=0.0, le=1.0)] = 0.25
    calibration_workers: Annotated[int, Field(ge=1, le=16)] = 1
    max_queued_calibrations: Annotated[int, Field(ge=1, le=1000)] = Field(
        8, description="calibrations queued or running at a time; more get 429 queue_full")
    max_connections: Annotated[int, Field(ge=1)] = Field(
        1000, description="open HTTP connections at a time (fewer if the open-files limit "
                          "needs it); beyond, the oldest idle one is closed, or, if all are "
                          "busy, the new one is answered 503")
    header_timeout_s: Annotated[float, Field(gt=0.0, le=3600.0)] = Field(
        10.0, description="a new connection must send its request's headers within this")
    keep_alive_s: Annotated[float, Field(gt=0.0, le=3600.0)] = Field(
        5.0, description="an idle connection between requests is closed after this")
    send_timeout_s: Annotated[float, Field(gt=0.0, le=3600.0)] = Field(
        30.0, description="a client that reads nothing of its answer for this long is "
                          "disconnected")

    @field_validator("robot")
    @classmethod
    def _robot_scheme(cls, url: str) -> str:
        registry.check_robot_url(url)
        return url

    @field_validator("camera")
    @classmethod
    def _camera_scheme(cls, url: str) -> str:
        registry.check_camera_url(url)
        return url

    @field_validator("scene")
    @classmethod
    def _scene_loads(cls, path: Path | None, info: ValidationInfo) -> Path | None:
        """The robot's backend reads its configuration file now, so a bad one stops startup."""
        if path is not None and "robot" in info.data:
            registry.describe_cell(info.data["robot"], path)
        return path

    @model_validator(mode="after")
    def _consistent(self) -> Settings:
        if any(lo >= hi for lo, hi in zip(self.workspace_min, self.workspace_max, strict=True)):
            raise ValueError(f"workspace_min {list(self.workspace_min)} must be below "
                             f"workspace_max {list(self.workspace_max)} on every axis")
        if not is_loopback(self.host) and self.api_key is None:
            raise ValueError(f"refusing to serve on {self.host} (not loopback) without an API "
                             "key: set CELLCAL_API_KEY")
        if self.api_key is not None and len(self.api_key.get_secret_value()) < 16:
            raise ValueError("api_key must be at least 16 characters")
        registry.check_pair(self.robot, self.camera)
        self._read_older_target()
        if self.target is None and self.cell_hints().target is None:
            raise ValueError("a real robot needs the checkerboard or ChArUco board it sees: "
                             "set CELLCAL_TARGET, e.g. '{\"inner_corners\": [11, 8], "
                             "\"square_size_m\": 0.03}' for a checkerboard")
        return self

    def _read_older_target(self) -> None:
        """``target_inner_corners`` with ``target_square_size_m`` (settings written before
        ``target``) become ``target``, a checkerboard parsed by the one target type."""
        older = (self.target_inner_corners, self.target_square_size_m)
        if older == (None, None):
            return
        if None in older or self.target is not None:
            raise ValueError("give target (CELLCAL_TARGET), or its older spelling "
                             "target_inner_corners with target_square_size_m, not a mix")
        self.target = TargetAdapter.validate_python(
            {"inner_corners": older[0], "square_size_m": older[1]})

    @property
    def database(self) -> str:
        """The SQLAlchemy URL in use."""
        return self.database_url or f"sqlite:///{self.data_dir / 'cellcal.db'}"

    def cell_hints(self) -> CellHints:
        """What is known about the cell before calibrating it: the settings, else what the
        robot's backend knows (``drivers.base.DescribesCell``; a mock scene)."""
        known = registry.describe_cell(self.robot, self.scene)
        hints = dataclasses.replace(known, setup=self.setup or known.setup)
        if self.target is not None:
            hints = dataclasses.replace(hints, target=self.target)
        if self.hand_eye_guess is not None:
            hints = dataclasses.replace(
                hints, hand_eye=matrix_from_ur_pose(np.asarray(self.hand_eye_guess)))
        if self.focal_px_guess is not None:  # K follows from it and the image size
            hints = dataclasses.replace(hints, K=None, dist=None)
        return hints

    def run_target(self) -> Target:
        """The board captured runs look for: the setting, else the robot backend's."""
        target = self.cell_hints().target
        assert target is not None  # checked at startup
        return target

    def workspace(self) -> tuple[Vector3, Vector3]:
        """The TCP box (lo, hi corners, base frame, m), as the planners and ``calib``'s
        ``SolverOptions.workspace`` take it."""
        return self.workspace_min, self.workspace_max

    def cold_start_solver(self, solver: SolverOptions | None = None,
                          stop_rule: dict[str, Any] | None = None) -> SolverOptions:
        """``solver`` (default options if None) for a cold-start run's stations: told the
        workspace box, so the hand-eye σ covers using the result anywhere in it
        (``calib.extrapolation``), and a tolerance run's tolerance (``stop_rule``, the run's:
        ``tolerance_mm``, ``tolerance_deg``), so a result beyond it is not a plain pass. The
        run's stop rule and its calibrations both use it, so the σ a run stopped at is the σ
        its result reports."""
        tolerance = None if not stop_rule else (float(np.deg2rad(stop_rule["tolerance_deg"])),
                                                stop_rule["tolerance_mm"] * 1e-3)
        return dataclasses.replace(solver or SolverOptions(), workspace=self.workspace(),
                                   tolerance=tolerance)

    def calibration_setup(self) -> str:
        """``eye_in_hand`` or ``eye_to_hand``: the setting, else the backend's, else
        eye-in-hand."""
        return self.cell_hints().setup or "eye_in_hand"
