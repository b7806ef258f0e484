"""Background work: capture runs in a thread per run, calibrations in worker processes.

Capture (blocking device calls) never runs on the event loop: each run gets a thread that
visits its planned poses in order (move, settle, grab, read the pose) and hands each frame to
a worker thread that detects the corners, writes the PNG and commits the station while the
next one is captured. At most two stations are in flight and they are committed in index
order, so a crash loses at most those two. Restart safety rests on the database:

- a run row names its capture thread by an ``owner`` token; a thread writes stations and
  changes the run state only while it still owns a ``capturing`` run (conditional updates),
  so a paused, cancelled or resumed run sheds a stale thread at its next step;
- at startup, runs left ``capturing`` by a dead service become ``interrupted``; ``resume``
  gives the run a new owner, which continues from the first index without a station row;
- ``(run, index)`` is unique, so no station is ever stored twice.

Calibrations are CPU-bound: they run in a ``ProcessPoolExecutor`` (spawned workers) so the API
stays responsive, and the result is stored when the future completes.

Validations (the dot-hit run, SM eq. 24) move the robot in a thread like a capture run. The
robot does one motion job at a time: a validation is refused while a run is active (capturing
or paused) and a run while a validation is running; within the service ``_motion_lock`` makes
each check and the row that claims the robot one step.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import contextlib
import logging
import multiprocessing
import os
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from calib.geometry import (
    check_ur_poses,
    make_transform,
    matrix_from_ur_pose,
    rotation_angle,
    ur_pose_from_matrix,
)
from calib.intrinsics import MIN_IMAGES
from calib.planning import camera_view, plan_stations, rough_target_from_image
from calib.target import Detection, board_points, detect_checkerboard
from drivers.base import Camera, Robot
from drivers.capture import capture_station
from drivers.errors import (
    CameraError,
    CameraTimeoutError,
    DeviceError,
    EmergencyStopError,
    ProtectiveStopError,
    RobotConnectionError,
    WorkspaceError,
)
from drivers.registry import open_camera, open_robot
from service.db import Database
from service.models import (
    ACTIVE_RUN_STATES,
    Calibration,
    Run,
    Station,
    Validation,
    new_id,
    utcnow,
)
from service.schemas import CalibrationOptions, RunCreate, ValidationCreate
from service.settings import Settings
from service.validation_run import GroundTruth, probe_points, run_dot_hit

log = logging.getLogger("cellcal.service")

#: Run states after which nothing more happens to a run unless someone resumes it.
FINAL_RUN_STATES = ("done", "failed", "cancelled", "interrupted")
#: Camera error codes that mean the camera is gone (stop the run, do not skip stations).
_CAMERA_GONE = ("camera_not_open", "camera_not_found", "camera_open_failed",
                "camera_disconnected")
#: A failed station is tried this many times in all before it is skipped.
_ATTEMPTS = 2


# ---- domain errors (mapped to HTTP statuses in service.app) --------------------------------

class ServiceError(Exception):
    """A request the service refuses; ``code`` is stable, the message is for people."""

    code = "service_error"

    def __init__(self, detail: str, *, code: str | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        if code is not None:
            self.code = code


class NotFoundError(ServiceError):
    code = "not_found"


class ConflictError(ServiceError):
    code = "conflict"


class UnprocessableError(ServiceError):
    code = "invalid_request"


class AuthError(ServiceError):
    code = "unauthorized"


# ---- devices -------------------------------------------------------------------------------

DeviceOpener = Callable[[], tuple[Robot, Camera]]


def settings_opener(settings: Settings) -> DeviceOpener:
    """Open the configured robot and camera (``mock://`` ones share the scene)."""

    def open_devices() -> tuple[Robot, Camera]:
        scene = settings.mock_scene() if settings.uses_mock else None
        robot = open_robot(settings.robot, scene=scene)
        try:
            camera = open_camera(settings.camera, robot=robot, scene=scene)
        except BaseException:
            robot.close()
            raise
        return robot, camera

    return open_devices


class Devices:
    """The cell's robot and camera, opened on first use and reopened after a connection loss."""

    def __init__(self, opener: DeviceOpener) -> None:
        self._opener = opener
        self._lock = threading.Lock()
        self._devices: tuple[Robot, Camera] | None = None

    def get(self) -> tuple[Robot, Camera]:
        """The open devices; raises ``DeviceError`` (or ``ValueError``) if they cannot open."""
        with self._lock:
            if self._devices is None:
                self._devices = self._opener()
            return self._devices

    def current(self) -> tuple[Robot, Camera] | None:
        """The devices if they are open, without trying to open them."""
        with self._lock:
            return self._devices

    def reset(self) -> None:
        """Close the devices so that the next ``get`` connects again."""
        with self._lock:
            devices, self._devices = self._devices, None
        if devices is not None:
            for device in devices:
                try:
                    device.close()
                except DeviceError as exc:
                    log.warning("closing %s: %s", type(device).__name__, exc)

    close = reset


# ---- events --------------------------------------------------------------------------------

class EventBus:
    """Run events fanned out to server-sent-event listeners; publish from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._listeners: dict[str, set[tuple[asyncio.AbstractEventLoop,
                                             asyncio.Queue[dict[str, Any]]]]] = {}

    @contextlib.contextmanager
    def listen(self, run_id: str) -> Iterator[asyncio.Queue[dict[str, Any]]]:
        """A queue receiving the run's events while the block runs (call on the event loop)."""
        entry = (asyncio.get_running_loop(), asyncio.Queue[dict[str, Any]]())
        with self._lock:
            self._listeners.setdefault(run_id, set()).add(entry)
        try:
            yield entry[1]
        finally:
            with self._lock:
                self._listeners[run_id].discard(entry)
                if not self._listeners[run_id]:
                    del self._listeners[run_id]

    def publish(self, run_id: str, event: dict[str, Any]) -> None:
        with self._lock:
            listeners = list(self._listeners.get(run_id, ()))
        for loop, queue in listeners:
            with contextlib.suppress(RuntimeError):  # the listener's loop has closed
                loop.call_soon_threadsafe(queue.put_nowait, event)


# ---- capture -------------------------------------------------------------------------------

@dataclass
class _Visit:
    """What happened at one station, ready to be stored."""

    state: str
    tcp_pose: list[float] | None
    image: np.ndarray | None
    detection: dict[str, Any] | None
    error: str | None
    error_code: str | None
    attempts: int


@dataclass
class _Shot:
    """A frame taken at a station for the worker, or the device error of its last try."""

    index: int
    pose: list[float]
    attempt: int
    tcp_pose: list[float] | None
    image: np.ndarray | None
    error: str | None = None
    error_code: str | None = None


#: What the worker made of a station.
_STORED, _RETRY, _LOST = "stored", "retry", "lost"


def _detection_json(det: Detection) -> dict[str, Any]:
    return {"ok": det.ok, "reason": det.reason, "sharpness": det.sharpness,
            "coverage": det.coverage, "mean_contrast": det.mean_contrast,
            "ambiguous": det.ambiguous,
            "corners": None if det.corners is None else det.corners.tolist()}


def _stops_run(exc: DeviceError) -> bool:
    """True for faults that need a person (robot gone or stopped, camera gone)."""
    if isinstance(exc, RobotConnectionError | ProtectiveStopError | EmergencyStopError):
        return True
    return (isinstance(exc, CameraError) and not isinstance(exc, CameraTimeoutError)
            and exc.code in _CAMERA_GONE)


def run_counts(session: Session, run: Run) -> dict[str, int]:
    """Stations planned, captured and skipped, counted in SQL (never loading the stations with
    their corners, so polling stays fast on long runs)."""
    by_state = dict(session.execute(
        select(Station.state, func.count()).where(Station.run_id == run.id)
        .group_by(Station.state)).all())
    captured = by_state.get("captured", 0)
    return {"stations_planned": len(run.poses), "stations_captured": captured,
            "stations_skipped": sum(by_state.values()) - captured}


class Jobs:
    """Starts, steers and records capture runs and calibrations."""

    def __init__(self, settings: Settings, db: Database, devices: Devices,
                 events: EventBus) -> None:
        self.settings = settings
        self.db = db
        self.devices = devices
        self.events = events
        self.data_dir = Path(settings.data_dir)
        self._robot_lock = threading.Lock()  # one thread drives the robot at a time
        self._motion_lock = threading.Lock()  # check "robot free" and claim it in one step
        self._threads: dict[str, threading.Thread] = {}  # run owner / validation id -> thread
        self._threads_lock = threading.Lock()
        self._stopping = threading.Event()
        self._pool: cf.ProcessPoolExecutor | None = None
        self._pool_lock = threading.Lock()

    # ---- lifecycle -------------------------------------------------------------------------

    def recover(self) -> None:
        """After a restart: runs left capturing are interrupted, solves and validations in
        flight failed."""
        with self.db.session() as s:
            runs = s.execute(
                update(Run).where(Run.state == "capturing")
                .values(state="interrupted", owner=None, error_code="interrupted",
                        error="The service stopped while this run was capturing; resume it "
                              "to continue from the next station.")).rowcount
            cals = s.execute(
                update(Calibration).where(Calibration.state == "running")
                .values(state="failed", finished_at=utcnow(),
                        error="The service stopped during the computation; start it "
                              "again.")).rowcount
            vals = s.execute(
                update(Validation).where(Validation.state == "running")
                .values(state="failed", finished_at=utcnow(),
                        error="The service stopped during the validation; start it "
                              "again.")).rowcount
            s.commit()
        if runs or cals or vals:
            log.warning("recovered after restart: %d run(s) interrupted, %d calibration(s) "
                        "and %d validation(s) failed", runs, cals, vals)

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop the robot and the motion threads (runs become ``interrupted``, validations
        ``failed``)."""
        self._stopping.set()
        with self._threads_lock:
            threads = list(self._threads.values())
        devices = self.devices.current()
        if threads and devices is not None:
            devices[0].stop()
        for thread in threads:
            thread.join(timeout)
        with self._pool_lock:
            if self._pool is not None:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None

    # ---- runs ------------------------------------------------------------------------------

    def create_run(self, body: RunCreate) -> Run:
        """Validate the plan, store the run and start capturing; 409 if the robot is busy."""
        target = (body.target.model_dump() if body.target is not None
                  else self.settings.target())
        setup = self.settings.calibration_setup()
        if body.poses is not None:
            poses = self._check_poses(body.poses)
        else:
            assert body.stations is not None
            self._check_robot_free()
            poses = self._check_poses(self._plan(body.stations, target, setup))
        token = new_id()
        run = Run(robot=self.settings.robot, state="capturing", owner=token, setup=setup,
                  target=target, poses=poses)
        with self._motion_lock, self.db.session() as s:
            self._check_robot_free()
            s.add(run)
            try:
                s.commit()
            except IntegrityError:
                s.rollback()
                raise self._busy() from None
        self._start_capture(run.id, token)
        return run

    def pause(self, run_id: str) -> None:
        """Stop after the station in progress; idempotent on a paused run."""
        self._transition(run_id, ("capturing",), "paused", same_ok="paused")

    def cancel(self, run_id: str) -> None:
        """Give up a run for good; the robot is stopped if this run is moving it."""
        token = self._transition(run_id, ("capturing", "paused", "interrupted", "failed"),
                                 "cancelled", same_ok="cancelled")
        with self._threads_lock:
            moving = token in self._threads
        devices = self.devices.current()
        if moving and devices is not None:
            devices[0].stop()

    def resume(self, run_id: str) -> None:
        """Continue a paused, interrupted or failed run at its first missing station."""
        token = new_id()
        with self._motion_lock, self.db.session() as s:
            run = self._get_run(s, run_id)
            if run.state == "capturing":
                return
            if run.state not in ("paused", "interrupted", "failed"):
                raise ConflictError(f"Run {run_id} is {run.state}; only a paused, interrupted "
                                    "or failed run can be resumed.", code="invalid_state")
            if self._running_validation(s) is not None:
                raise self._busy()
            try:
                changed = s.execute(
                    update(Run).where(Run.id == run_id, Run.state == run.state)
                    .values(state="capturing", owner=token, error=None,
                            error_code=None)).rowcount
                s.commit()
            except IntegrityError:
                s.rollback()
                raise self._busy() from None
        if not changed:
            raise ConflictError(f"Run {run_id} changed state meanwhile; read it and retry.",
                                code="invalid_state")
        self._publish_state(run_id)
        self._start_capture(run_id, token)

    def _transition(self, run_id: str, sources: tuple[str, ...], target: str, *,
                    same_ok: str) -> str | None:
        """Move a run from one of ``sources`` to ``target``; the old owner token."""
        with self.db.session() as s:
            run = self._get_run(s, run_id)
            if run.state == same_ok:
                return None
            if run.state not in sources:
                raise ConflictError(f"Run {run_id} is {run.state}; it cannot become {target}.",
                                    code="invalid_state")
            owner = run.owner
            changed = s.execute(
                update(Run).where(Run.id == run_id, Run.state == run.state)
                .values(state=target, owner=None)).rowcount
            s.commit()
        if not changed:
            raise ConflictError(f"Run {run_id} changed state meanwhile; read it and retry.",
                                code="invalid_state")
        self._publish_state(run_id)
        return owner

    def _plan(self, n: int, target: dict[str, Any], setup: str) -> list[list[float]]:
        """Plan ``n`` stations around the board as seen from the robot's current pose.

        The board pose comes from one image at the current pose; the hand-eye and the camera
        from the mock scene or, on a real cell, from the configured rough guesses. The
        distance band is 0.8 to 1.3 times the current camera-to-board distance.
        """
        if self.settings.uses_mock:
            scene = self.settings.mock_scene()
            X, K, dist = scene.hand_eye_matrix, scene.camera.k_matrix, scene.camera.dist_coeffs
        elif self.settings.hand_eye_guess is None or self.settings.focal_px_guess is None:
            raise UnprocessableError(
                "Automatic planning on a real cell needs rough guesses: set "
                "CELLCAL_HAND_EYE_GUESS ([x, y, z, rx, ry, rz]) and CELLCAL_FOCAL_PX_GUESS, or "
                "give the stations as 'poses'.", code="planning_unavailable")
        else:
            X = matrix_from_ur_pose(np.asarray(self.settings.hand_eye_guess))
            K, dist = None, None
        robot, camera = self.devices.get()
        with self._robot_lock:
            P0 = matrix_from_ur_pose(robot.tcp_pose())
            image = camera.grab(timeout=self.settings.grab_timeout_s)
        h, w = image.shape[:2]
        if K is None:
            f = float(self.settings.focal_px_guess or 0.0)
            K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
        corners = tuple(target["inner_corners"])
        det = detect_checkerboard(image, corners)
        if not det.ok:
            raise UnprocessableError(
                f"Cannot plan: the board is not in view at the robot's current pose "
                f"({det.reason}). Move the robot so the camera sees the whole board.",
                code="planning_failed")
        try:
            Y = rough_target_from_image(det.corners, K, corners, target["square_size_m"], P0,
                                        X, setup=setup, dist=dist)
            d0 = float(np.linalg.norm(camera_view(P0, X, Y, setup)[:3, 3]))
            plan = plan_stations(
                n, start_tcp_pose=P0, target_pose_guess=Y, hand_eye_guess=X, K=K,
                image_size=(w, h), inner_corners=corners, square_size=target["square_size_m"],
                distance_band=(0.8 * d0, 1.3 * d0), setup=setup, dist=dist,
                workspace=(self.settings.workspace_min, self.settings.workspace_max))
        except ValueError as exc:
            raise UnprocessableError(f"Cannot plan {n} stations: {exc}.",
                                     code="planning_failed") from None
        return ur_pose_from_matrix(plan.tcp_poses).tolist()

    def _check_poses(self, poses: list[list[float]]) -> list[list[float]]:
        """Refuse poses that are malformed, implausible or outside the workspace box (422)."""
        if len(poses) > self.settings.max_stations:
            raise UnprocessableError(f"{len(poses)} poses; at most "
                                     f"{self.settings.max_stations} per run.")
        try:
            check_ur_poses(np.asarray(poses, dtype=float), "poses")
        except ValueError as exc:
            raise UnprocessableError(str(exc), code="invalid_pose") from None
        for k, pose in enumerate(poses):
            if (outside := self._outside_workspace(pose)) is not None:
                raise UnprocessableError(f"poses[{k}]: {outside}; the run was not started.",
                                         code="outside_workspace")
        return [[float(v) for v in pose] for pose in poses]

    def _outside_workspace(self, pose: Any) -> str | None:
        """Why UR pose ``pose`` (6,) lies outside the workspace box, or None if inside."""
        lo, hi = np.asarray(self.settings.workspace_min), np.asarray(self.settings.workspace_max)
        p = np.asarray(pose[:3], dtype=float)
        if np.all(p >= lo) and np.all(p <= hi):
            return None
        mm = ", ".join(f"{v * 1e3:.0f}" for v in p)
        box = " x ".join(f"[{a * 1e3:.0f}, {b * 1e3:.0f}]" for a, b in zip(lo, hi, strict=True))
        return f"position ({mm}) mm is outside the workspace limits {box} mm (base frame)"

    def _check_workspace(self, pose: np.ndarray) -> None:
        """Raise ``WorkspaceError`` for a commanded UR pose (6,) outside the workspace box."""
        if (outside := self._outside_workspace(pose)) is not None:
            raise WorkspaceError(f"Target {outside}; the robot was not moved.")

    @staticmethod
    def _running_validation(s: Session) -> str | None:
        return s.scalars(select(Validation.id).where(Validation.state == "running")).first()

    def _check_robot_free(self) -> None:
        """409 while a run is active on the robot or a validation moves it."""
        with self.db.session() as s:
            if self._running_validation(s) is not None or s.scalars(
                    select(Run.id).where(Run.robot == self.settings.robot,
                                         Run.state.in_(ACTIVE_RUN_STATES))).first():
                raise self._busy()

    def _busy(self) -> ConflictError:
        with self.db.session() as s:
            validation = self._running_validation(s)
            active = s.scalars(select(Run.id).where(Run.robot == self.settings.robot,
                                                    Run.state.in_(ACTIVE_RUN_STATES))).first()
        if validation is not None and active is None:
            return ConflictError(f"The robot is running validation {validation}; let it finish "
                                 "first.", code="robot_busy")
        return ConflictError(f"The robot already has an active run ({active}); cancel it or "
                             "let it finish first.", code="robot_busy")

    @staticmethod
    def _get_run(s: Session, run_id: str) -> Run:
        run = s.get(Run, run_id)
        if run is None:
            raise NotFoundError(f"No run {run_id}.")
        return run

    def _start_capture(self, run_id: str, token: str) -> None:
        thread = threading.Thread(target=self._capture, args=(run_id, token),
                                  name=f"capture-{run_id[:8]}", daemon=True)
        with self._threads_lock:
            self._threads[token] = thread
        thread.start()

    # ---- the capture thread ----------------------------------------------------------------

    def _capture(self, run_id: str, token: str) -> None:
        """Visit the run's missing stations in order while this thread owns the run."""
        try:
            with self._robot_lock:
                self._capture_owned(run_id, token)
        except DeviceError as exc:
            if isinstance(exc, RobotConnectionError):
                self.devices.reset()
            self._finish(run_id, token, "failed", str(exc), exc.code)
        except ValueError as exc:  # e.g. a malformed device URL
            self._finish(run_id, token, "failed", str(exc), "invalid_configuration")
        except Exception as exc:
            log.exception("capture run %s", run_id)
            self._finish(run_id, token, "failed",
                         f"Internal error ({type(exc).__name__}: {exc}).", "internal_error")
        finally:
            with self._threads_lock:
                self._threads.pop(token, None)

    def _capture_owned(self, run_id: str, token: str) -> None:
        """Visit the missing stations in index order, two stations in flight.

        This thread moves, settles, grabs and reads the pose; one worker thread detects the
        corners, writes the PNG and commits the station (``_develop``), so station ``k`` is
        developed while station ``k + 1`` is being captured. A frame goes to the worker only
        once the worker's previous station is settled (stored, or sent back for its retry and
        then stored), so stations are committed in index order and at most two are in flight:
        the one in the worker and the one being captured.

        In-flight stations are committed exactly when this thread still owns the run at
        commit time (the check in ``_store``). Pause, cancel or a takeover by another owner
        therefore discard them (their PNG files are removed); resume captures them again.
        On shutdown or a device fault that stops the run, no new frame is taken, the worker
        finishes the station it holds (stored, since the run is still ours, but not retried)
        and then the run becomes ``interrupted`` or ``failed``; a frame captured but not yet
        handed over is dropped.
        """
        robot, camera = self.devices.get()
        with self.db.session() as s:
            run = s.get(Run, run_id)
            if run is None or run.owner != token or run.state != "capturing":
                return
            stored = set(s.scalars(select(Station.index).where(Station.run_id == run_id)))
            poses, inner = run.poses, tuple(run.target["inner_corners"])
        todo = [k for k in range(len(poses)) if k not in stored]
        complete = False
        with cf.ThreadPoolExecutor(1, thread_name_prefix=f"develop-{run_id[:8]}") as worker:
            def develop(shot: _Shot) -> cf.Future[str]:
                return worker.submit(self._develop, run_id, token, shot, inner)

            def settle(shot: _Shot, future: cf.Future[str]) -> bool:
                """Wait for the worker's station, re-capturing it for its retry; True if
                it was stored, False if the run is no longer ours (or the service stops)."""
                while (outcome := future.result()) == _RETRY:
                    if not self._wanted(run_id, token):
                        return False
                    again = self._shoot(robot, camera, run_id, token, shot.index,
                                        shot.pose, shot.attempt + 1)
                    if again is None:
                        return False
                    shot, future = again, develop(again)
                return outcome == _STORED

            in_worker: tuple[_Shot, cf.Future[str]] | None = None
            try:
                for index in todo:
                    if self._stopping.is_set() or not self._owns(run_id, token):
                        break
                    shot = self._shoot(robot, camera, run_id, token, index, poses[index], 1)
                    if shot is None or self._stopping.is_set():  # None: no longer ours
                        break
                    if in_worker is not None:
                        done, in_worker = settle(*in_worker), None
                        if not done:
                            break
                    in_worker = (shot, develop(shot))
                else:
                    complete = in_worker is None or settle(*in_worker)
                    in_worker = None
                if in_worker is not None:  # stopped early: let the worker finish, no retry
                    in_worker[1].result()
            except BaseException as exc:  # the worker still finishes its station
                if in_worker is not None and (
                        lost := in_worker[1].exception()) not in (None, exc):
                    log.error("run %s, station %d: %s: %s", run_id, in_worker[0].index,
                              type(lost).__name__, lost)
                raise
        if self._stopping.is_set():
            self._finish(run_id, token, "interrupted",
                         "The service stopped while this run was capturing; resume it to "
                         "continue from the next station.", "interrupted")
        elif complete:
            self._finish(run_id, token, "done")

    def _shoot(self, robot: Robot, camera: Camera, run_id: str, token: str, index: int,
               pose: list[float], first_attempt: int) -> _Shot | None:
        """Move, settle, grab and read the pose, retrying a device error once; None if the
        run was taken meanwhile. Raises the device errors that stop the run."""
        shot: _Shot | None = None
        for attempt in range(first_attempt, _ATTEMPTS + 1):
            try:
                taken = capture_station(robot, camera, np.asarray(pose),
                                        settle_timeout=self.settings.settle_timeout_s,
                                        grab_timeout=self.settings.grab_timeout_s,
                                        speed=self.settings.move_speed)
            except DeviceError as exc:
                if not self._wanted(run_id, token):
                    return None
                if _stops_run(exc):
                    raise
                shot = _Shot(index, pose, attempt, None, None, str(exc), exc.code)
                continue
            return _Shot(index, pose, attempt, [float(v) for v in taken.tcp_pose],
                         taken.image)
        return shot

    def _develop(self, run_id: str, token: str, shot: _Shot,
                 inner_corners: tuple[int, int]) -> str:
        """The worker's part of a station: detect, write the PNG and commit (``_STORED``),
        or ``_RETRY`` for a first detection failure, or ``_LOST`` if the run is not ours."""
        if shot.image is None:
            visit = _Visit("skipped", None, None, None, shot.error, shot.error_code,
                           shot.attempt)
        else:
            det = detect_checkerboard(shot.image, inner_corners)
            if det.ok:
                visit = _Visit("captured", shot.tcp_pose, shot.image, _detection_json(det),
                               None, None, shot.attempt)
            elif shot.attempt < _ATTEMPTS:
                return _RETRY
            else:
                visit = _Visit("skipped", shot.tcp_pose, shot.image, _detection_json(det),
                               f"Checkerboard not found: {det.reason}.", "not_detected",
                               shot.attempt)
        return _STORED if self._store(run_id, token, shot.index, shot.pose, visit) else _LOST

    def _wanted(self, run_id: str, token: str) -> bool:
        """True while the service runs and this thread owns the run (worth another try)."""
        return not self._stopping.is_set() and self._owns(run_id, token)

    def _owns(self, run_id: str, token: str) -> bool:
        with self.db.session() as s:
            return s.scalar(select(func.count()).select_from(Run).where(
                Run.id == run_id, Run.owner == token, Run.state == "capturing")) == 1

    def _store(self, run_id: str, token: str, index: int, pose: list[float],
               visit: _Visit) -> bool:
        """Commit one station (image file first) unless the run is no longer ours; True if
        it was stored."""
        rel = None
        if visit.image is not None:
            rel = Path("runs") / run_id / f"{index:03d}-{token[:8]}.png"
            _write_png(self.data_dir / rel, visit.image)
        size = None if visit.image is None else [visit.image.shape[1], visit.image.shape[0]]
        with self.db.session() as s:
            if not self._owns(run_id, token):
                stored = False
            else:
                s.add(Station(run_id=run_id, index=index, state=visit.state, target_pose=pose,
                              tcp_pose=visit.tcp_pose, image_path=None if rel is None
                              else rel.as_posix(), image_size=size,
                              detection=visit.detection, error=visit.error,
                              error_code=visit.error_code, attempts=visit.attempts))
                try:
                    s.commit()
                    stored = True
                except IntegrityError:  # another owner stored this index
                    s.rollback()
                    stored = False
        if not stored:
            if rel is not None:
                (self.data_dir / rel).unlink(missing_ok=True)
            return False
        event: dict[str, Any] = {"type": "station", "run_id": run_id, "index": index,
                                 "state": visit.state}
        if visit.error:
            event["error"] = {"code": visit.error_code, "detail": visit.error}
        self.events.publish(run_id, event)
        return True

    def _finish(self, run_id: str, token: str, state: str, error: str | None = None,
                code: str | None = None) -> None:
        """End the run in ``state`` if this thread still owns it."""
        with self.db.session() as s:
            changed = s.execute(
                update(Run).where(Run.id == run_id, Run.owner == token,
                                  Run.state == "capturing")
                .values(state=state, owner=None, error=error, error_code=code)).rowcount
            s.commit()
        if changed:
            self._publish_state(run_id)

    def state_event(self, run_id: str) -> dict[str, Any]:
        """The run's state and counts as a ``state`` event (404 for an unknown run)."""
        with self.db.session() as s:
            run = self._get_run(s, run_id)
            return {"type": "state", "run_id": run_id, "state": run.state, **run_counts(s, run),
                    "error": None if run.error is None else {"code": run.error_code,
                                                             "detail": run.error}}

    def _publish_state(self, run_id: str) -> None:
        self.events.publish(run_id, self.state_event(run_id))

    # ---- calibrations ----------------------------------------------------------------------

    def start_calibration(self, run_id: str, options: CalibrationOptions) -> Calibration:
        """Queue a solve over the run's captured stations in a worker process."""
        with self.db.session() as s:
            run = self._get_run(s, run_id)
            if run.state == "capturing":
                raise ConflictError(f"Run {run_id} is still capturing; pause it or wait until "
                                    "it is done.", code="invalid_state")
            captured = [st for st in run.stations if st.state == "captured"]
            if len(captured) < MIN_IMAGES:
                raise UnprocessableError(
                    f"Run {run_id} has {len(captured)} captured stations; a calibration needs "
                    f"at least {MIN_IMAGES}.", code="too_few_stations")
            payload = {
                "run_id": run_id, "setup": run.setup, "target": run.target,
                "ids": [f"{st.index:03d}" for st in captured],
                "tcp_poses": [st.tcp_pose for st in captured],
                "corners": [st.detection["corners"] for st in captured],
                "ambiguous": [st.detection["ambiguous"] for st in captured],
                "image_size": captured[0].image_size,
                "options": options.model_dump(),
            }
            cal = Calibration(run_id=run_id, state="running", options=options.model_dump())
            s.add(cal)
            s.commit()
        future = self._submit(payload)
        future.add_done_callback(lambda f: self._calibration_done(cal.id, f))
        return cal

    def _submit(self, payload: dict[str, Any]) -> cf.Future[dict[str, Any]]:
        with self._pool_lock:
            if self._pool is None:
                self._pool = cf.ProcessPoolExecutor(
                    self.settings.calibration_workers,
                    mp_context=multiprocessing.get_context("spawn"))
            return self._pool.submit(solve_calibration, payload)

    def _calibration_done(self, cal_id: str, future: cf.Future[dict[str, Any]]) -> None:
        values: dict[str, Any] = {"finished_at": utcnow()}
        try:
            values.update(state="done", result=future.result())
        except cf.CancelledError:
            values.update(state="failed", error="The service stopped during the computation; "
                                                "start it again.")
        except ValueError as exc:
            values.update(state="failed", error=str(exc))
        except cf.process.BrokenProcessPool:
            with self._pool_lock:
                self._pool = None
            values.update(state="failed", error="The calibration worker process died "
                                                "(out of memory?); start it again.")
        except Exception as exc:
            log.error("calibration %s: %s: %s", cal_id, type(exc).__name__, exc)
            values.update(state="failed",
                          error=f"Internal error ({type(exc).__name__}: {exc}).")
        with self.db.session() as s:
            s.execute(update(Calibration).where(Calibration.id == cal_id).values(**values))
            s.commit()

    # ---- validations -----------------------------------------------------------------------

    def start_validation(self, cal_id: str, body: ValidationCreate) -> Validation:
        """Check the request, claim the robot and start the dot-hit run in a thread."""
        with self.db.session() as s:
            cal = s.get(Calibration, cal_id)
            if cal is None:
                raise NotFoundError(f"No calibration {cal_id}.")
            if cal.state != "done":
                raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished "
                                    "calibration can be validated.", code="invalid_state")
            run = self._get_run(s, cal.run_id)
            robot_url, target, result = run.robot, run.target, cal.result
        if robot_url != self.settings.robot:
            raise UnprocessableError(f"Calibration {cal_id} was captured with robot "
                                     f"{robot_url}; this service drives {self.settings.robot}.",
                                     code="other_robot")
        plan = dot_hit_plan(result or {}, target, body)
        with self._motion_lock, self.db.session() as s:
            self._check_robot_free()
            val = Validation(calibration_id=cal_id, kind="dot_hit", state="running")
            s.add(val)
            s.commit()
        thread = threading.Thread(target=self._validate, args=(val.id, plan),
                                  name=f"validate-{val.id[:8]}", daemon=True)
        with self._threads_lock:
            self._threads[val.id] = thread
        thread.start()
        return val

    def _validate(self, val_id: str, plan: DotHitPlan) -> None:
        """The validation thread: observe the board, touch the points, store the report."""
        values: dict[str, Any] = {"state": "failed"}
        try:
            with self._robot_lock:
                values.update(state="done", result=self._dot_hit(plan))
        except (DeviceError, ServiceError, ValueError) as exc:
            if isinstance(exc, RobotConnectionError):
                self.devices.reset()
            values["error"] = ("The service stopped during the validation; start it again."
                               if self._stopping.is_set() else str(exc))
        except Exception as exc:
            log.exception("validation %s", val_id)
            values["error"] = f"Internal error ({type(exc).__name__}: {exc})."
        finally:
            with self._threads_lock:
                self._threads.pop(val_id, None)
        with self.db.session() as s:
            s.execute(update(Validation).where(Validation.id == val_id)
                      .values(finished_at=utcnow(), **values))
            s.commit()

    def _dot_hit(self, plan: DotHitPlan) -> dict[str, Any]:
        """Observe the board from where the robot stands (eq. 24 needs a current view), then
        touch each point; the report document."""
        robot, camera = self.devices.get()
        tcp_pose = robot.tcp_pose()
        image = camera.grab(timeout=self.settings.grab_timeout_s)
        det = detect_checkerboard(image, plan.inner_corners)
        if not det.ok:
            raise UnprocessableError(
                f"The board is not in view at the robot's current pose ({det.reason}); move "
                "the robot so the camera sees the whole board, then validate again.",
                code="board_not_visible")
        P = matrix_from_ur_pose(tcp_pose)
        C, rms_px = plan.observe(det, P)
        truth = self._ground_truth(robot, plan)
        report = run_dot_hit(robot, plan.points, setup=plan.setup, hand_eye=plan.hand_eye,
                             tcp_T_probe=plan.probe, observation=(P, C),
                             workspace_check=self._check_workspace, ground_truth=truth)
        return {"kind": "dot_hit", "probe": ur_pose_from_matrix(plan.probe).tolist(),
                "observation": {"tcp_pose": [float(v) for v in tcp_pose],
                                "cam_T_target": ur_pose_from_matrix(C).tolist(),
                                "rms_px": rms_px},
                "ground_truth": None if truth is None else "mock scene",
                **report.to_json()}

    def _ground_truth(self, robot: Robot, plan: DotHitPlan) -> GroundTruth | None:
        """The mock cell's truth: its board through the true target pose, the robot's true pose.

        The points are given on the calibration's (κ, ν-scaled) grid; the scale to the true
        grid is folded into ``board_pose`` so each point maps to its true corner.
        """
        if not self.settings.uses_mock or not hasattr(robot, "true_pose"):
            return None
        scene = self.settings.mock_scene()
        t = scene.target
        s = t.square_size_m * t.kappa / (plan.square_size * plan.kappa)
        scale = np.diag([s * t.nu / plan.nu, s, 1.0, 1.0])
        return GroundTruth(board_pose=scene.target_pose_matrix @ scale,
                           tcp_pose=lambda: robot.true_pose)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class DotHitPlan:
    """A checked dot-hit request with the calibration it tests (arrays in metres)."""

    setup: str
    K: np.ndarray  # shape (3, 3)
    dist: np.ndarray  # shape (n,)
    hand_eye: np.ndarray  # shape (4, 4)
    target_pose: np.ndarray  # shape (4, 4)
    inner_corners: tuple[int, int]
    square_size: float
    kappa: float
    nu: float
    probe: np.ndarray  # shape (4, 4), tcp_T_probe
    points: dict[str, np.ndarray]  # id -> shape (3,), (κ, ν-scaled) target frame

    def observe(self, det: Detection, T_base_tcp: np.ndarray) -> tuple[np.ndarray, float]:
        """cam_T_target (4, 4) at true scale by PnP on the κ, ν-scaled board, and its RMS (px).

        A symmetric board's origin is taken at the end that agrees with the calibration's
        target pose.
        """
        grid = board_points(self.inner_corners, self.square_size, kappa=self.kappa, nu=self.nu)
        assert det.corners is not None
        best: tuple[float, np.ndarray, np.ndarray] | None = None
        for corners in ([det.corners, det.corners[::-1]] if det.ambiguous else [det.corners]):
            ok, rvec, tvec = cv2.solvePnP(grid, corners, self.K, self.dist)
            if not ok:
                continue
            C = make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
            board = T_base_tcp @ self.hand_eye @ C
            miss = float(rotation_angle(board[:3, :3].T @ self.target_pose[:3, :3]))
            if best is None or miss < best[0]:
                uv = cv2.projectPoints(grid, rvec, tvec, self.K, self.dist)[0].reshape(-1, 2)
                best = (miss, C, uv - corners)
        if best is None:
            raise UnprocessableError("PnP failed on the board seen at the robot's current "
                                     "pose.", code="board_not_visible")
        return best[1], float(np.sqrt(np.mean(np.sum(best[2] ** 2, axis=1))))


def dot_hit_plan(result: dict[str, Any], target: dict[str, Any],
                 body: ValidationCreate) -> DotHitPlan:
    """Check a dot-hit request against a result document and the run's board (422 if not)."""
    if result.get("setup") != "eye_in_hand":
        raise UnprocessableError(
            "The dot-hit validation probes the calibration board, which an eye-to-hand cell "
            "carries on the tool; it is available for eye-in-hand calibrations only.",
            code="unsupported_setup")
    camera, hand_eye = result.get("camera"), result.get("hand_eye")
    if not camera or not hand_eye or not result.get("target_pose"):
        raise UnprocessableError("The dot-hit validation needs a camera model and a hand-eye "
                                 "in the result.", code="incomplete_result")
    try:
        probe = check_ur_poses(np.asarray(body.probe, dtype=float), "probe")[0]
    except ValueError as exc:
        raise UnprocessableError(str(exc), code="invalid_probe") from None
    if np.linalg.norm(probe[:3, 3]) > 1.0:
        raise UnprocessableError(f"probe: the tip is {np.linalg.norm(probe[:3, 3]):.3g} m from "
                                 "the TCP, more than 1 m: give metres.", code="invalid_probe")
    kappa, nu = float(result["target"]["kappa"]), float(result["target"]["nu"])
    corners = (int(target["inner_corners"][0]), int(target["inner_corners"][1]))
    square = float(target["square_size_m"])
    points = probe_points(corners, square, kappa=kappa, nu=nu)
    if body.points is not None:
        unknown = [p for p in body.points if p not in points]
        if unknown:
            raise UnprocessableError(f"points: unknown id {unknown[0]!r}; choose from "
                                     f"{', '.join(points)}.", code="unknown_point")
        points = {p: points[p] for p in dict.fromkeys(body.points)}
    return DotHitPlan(
        setup="eye_in_hand", K=np.asarray(camera["K"], dtype=float),
        dist=np.asarray(camera["dist"], dtype=float),
        hand_eye=np.asarray(hand_eye["matrix"], dtype=float),
        target_pose=np.asarray(result["target_pose"]["matrix"], dtype=float),
        inner_corners=corners, square_size=square, kappa=kappa, nu=nu, probe=probe,
        points=points)


def solve_calibration(payload: dict[str, Any]) -> dict[str, Any]:
    """Worker-process entry: stored detections and robot poses -> result JSON document.

    Top level (picklable) and self-contained: it imports the pipeline in the worker.
    """
    from calib.pipeline import calibrate_stations
    from service.results import calibration_result_json

    opts = payload["options"]
    observations = [Detection(ok=True, corners=np.asarray(c, dtype=float), ambiguous=a)
                    for c, a in zip(payload["corners"], payload["ambiguous"], strict=True)]
    noise: dict[str, float] = {}
    if opts["robot_noise_rot_deg"] is not None:
        noise["robot_noise_rot"] = float(np.deg2rad(opts["robot_noise_rot_deg"]))
    if opts["robot_noise_trans_mm"] is not None:
        noise["robot_noise_trans"] = opts["robot_noise_trans_mm"] * 1e-3
    result = calibrate_stations(
        observations, payload["tcp_poses"], inner_corners=payload["target"]["inner_corners"],
        square_size=payload["target"]["square_size_m"], setup=payload["setup"],
        station_ids=payload["ids"], image_size=payload["image_size"], method=opts["method"],
        estimate_nu=opts["estimate_nu"], estimate_kappa=opts["estimate_kappa"],
        nu_method=opts["nu_method"], **noise)
    return calibration_result_json(
        result, command=f"POST /runs/{payload['run_id']}/calibrations")


def _write_png(path: Path, image: np.ndarray) -> None:
    """Write a PNG atomically (temporary file, then rename)."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"could not encode the image for {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".png.tmp")
    tmp.write_bytes(data.tobytes())
    os.replace(tmp, path)
