"""The capture thread of a run: visit the planned poses in order while the thread owns the run.

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

Every exception that ends a capture thread passes through ``Capture.run``, which turns it into
the run's final state, always one ``resume`` continues from: the one place for the capture
loop's error handling. Database work is retried with backoff (``service.store.db.retry_transient``)
for ``Settings.database_retry_s``; then the run becomes ``interrupted`` with the reason (that
last write waits for the database as long as the service runs). After a device fault the devices
are closed, so the next run or ``resume`` opens them afresh. A run that ends without a single
captured station is ``failed``.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
from sqlalchemy.orm import Session

from calib import Board, ChecksConfiguration, Station, board_from_target
from drivers.base import DescribesRobot
from drivers.capture import CaptureOptions, capture_station
from drivers.errors import (
    CameraError,
    CameraStalledError,
    CameraTimeoutError,
    DeviceError,
    EmergencyStopError,
    ProtectiveStopError,
    RobotConnectionError,
)
from drivers.frozen import FrameWatch
from drivers.stall import STALL_AFTER
from service.cell.motion import Motion
from service.events import EventBus
from service.store import queries, writes
from service.store.db import DatabaseUnavailableError, retry_transient
from service.store.records import RunRecord, Topic
from service.store.stations import row_values, run_target
from service.store.storage import StorageError, storage_error

log = logging.getLogger("cellcal.service")
T = TypeVar("T")

#: Camera error codes that mean the camera is gone or hangs (stop the run, do not skip
#: stations).
_CAMERA_GONE = ("camera_not_open", "camera_not_found", "camera_open_failed",
                "camera_disconnected", "camera_stalled", "camera_frozen")
#: A failed station is tried this many times in all before it is skipped.
ATTEMPTS = 2

#: What the worker made of a station.
STORED, _RETRY, _LOST = "stored", "retry", "lost"


@dataclass
class _Shot:
    """Try ``attempt`` at station ``index`` (commanded TCP pose ``pose``) for the worker: the
    station ``taken`` (robot reading and frame, not yet detected), or why there is none.
    ``final``: not taken again if the board is not found (a posted image)."""

    index: int
    pose: list[float]
    attempt: int
    taken: Station | None
    error: str | None = None
    error_code: str | None = None
    joints: list[float] | None = None
    late: int = 0  # grabs that timed out before this one (they use up no attempt)
    final: bool = False
    seen: str | None = None  # what a posted image's worker saw instead of the board

    @property
    def tries(self) -> int:
        """Captures of the station so far, timed-out grabs included (stored as attempts)."""
        return self.attempt + self.late


class BoardMismatchError(ValueError):
    """The run's first image shows a board of another size than the configured one."""


def _stops_run(exc: DeviceError) -> bool:
    """True for faults that need a person (robot gone or stopped, camera gone)."""
    if isinstance(exc, RobotConnectionError | ProtectiveStopError | EmergencyStopError):
        return True
    return (isinstance(exc, CameraError) and not isinstance(exc, CameraTimeoutError)
            and exc.code in _CAMERA_GONE)


@dataclass(frozen=True)
class PostedOutcome:
    """What the image worker said of a posted image besides its station: why there is no
    image (``problem``: detail, code), or what it shows instead of the board (``seen``)."""

    problem: tuple[str, str] | None = None
    seen: str | None = None


def _wrong_board(seen: str | None) -> str | None:
    """A station's reason for what an image shows instead of the run's board, or None."""
    return None if seen is None else (f"Wrong board configuration: {seen}; correct the run's "
                                      "target.")


def write_png(path: Path, image: np.ndarray) -> None:
    """Write a PNG atomically (temporary file, then rename) into an existing folder."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"could not encode the image for {path}")
    tmp = path.with_suffix(".png.tmp")
    tmp.write_bytes(data.tobytes())
    os.replace(tmp, path)


class Capture:
    """One capture thread's work on one run, identified by its owner ``token``."""

    def __init__(self, motion: Motion, events: EventBus, *, run_id: str, token: str) -> None:
        self.motion = motion
        self.events = events
        self.run_id = run_id
        self.token = token
        self.settings = motion.settings
        self.db = motion.db
        self.data_dir = Path(motion.settings.data_dir)
        self.options = CaptureOptions(settle_timeout=self.settings.settle_timeout_s,
                                      grab_timeout=self.settings.grab_timeout_s,
                                      speed=self.settings.move_speed)
        #: The run's board, read with the run (``_plan``, ``develop_posted``).
        self.board: Board | None = None
        #: The station the worker last developed (stored or not), for a planner to read.
        self.developed: Station | None = None
        #: Whether the first station was checked against the board (``_first_view_mismatch``).
        self._board_checked = False
        #: This thread's frames so far: a frozen camera stops the run (``drivers.frozen``).
        self._frames = FrameWatch()

    # ---- the thread body: every way a capture ends -----------------------------------------

    def run(self) -> None:
        """Visit the run's missing stations in order while this thread owns the run, and end
        the run in the state that says how it went."""
        try:
            with self.motion.robot_lock:
                self._capture_owned()
        except DeviceError as exc:
            # whatever the fault, the next run or resume opens the devices afresh (a camera
            # unplugged and plugged in again, a robot that dropped its connection)
            self.motion.devices.reset()
            self.finish("failed", str(exc), exc.code)
        except StorageError as exc:
            log.error("run %s failed: %s", self.run_id, exc)
            self.finish("failed", str(exc), exc.code)
        except DatabaseUnavailableError as exc:
            log.error("run %s interrupted: %s", self.run_id, exc)
            self.finish("interrupted", f"{exc}; resume the run once the database is back.",
                        DatabaseUnavailableError.code)
        except BoardMismatchError as exc:
            self.finish("failed", str(exc), "board_mismatch")
        except ValueError as exc:  # e.g. a malformed device URL
            self.finish("failed", str(exc), "invalid_configuration")
        except Exception as exc:
            log.exception("capture run %s", self.run_id)
            self.finish("failed", f"Internal error ({type(exc).__name__}: {exc}).",
                        "internal_error")

    def finish(self, state: str, error: str | None = None, code: str | None = None) -> None:
        """End the run in ``state`` if this thread still owns it, and tell the listeners.

        Retried for as long as the service runs: a run must not stay ``capturing`` without a
        thread (if the service stops first, its next start marks the run ``interrupted``).
        """
        def save() -> bool:
            return self._in_session(lambda s: writes.finish_run(
                s, run_id=self.run_id, token=self.token, state=state, error=error,
                error_code=code), f"ending run {self.run_id} as {state}", budget_s=math.inf)

        def retry(read: Callable[[], dict[str, Any]]) -> dict[str, Any]:
            return retry_transient(read, budget_s=self.settings.database_retry_s,
                                   what="reading the run state", stopping=self.motion.stopping)

        try:
            self.events.finish(Topic("run", self.run_id), save, retry=retry)
        except DatabaseUnavailableError as exc:
            log.error("run %s: %s", self.run_id, exc)

    def _publish(self, event: dict[str, Any]) -> None:
        """Send a run event (the bus stores it, retried, without holding the capture)."""
        self.events.publish(Topic("run", self.run_id), event)

    def _in_session(self, work: Callable[[Session], T], what: str, *,
                    budget_s: float | None = None) -> T:
        """``work`` in a session of its own, retried after transient database errors."""
        def transaction() -> T:
            with self.db.session() as s:
                return work(s)

        budget = self.settings.database_retry_s if budget_s is None else budget_s
        return retry_transient(transaction, budget_s=budget, what=what,
                               stopping=self.motion.stopping)

    def _open_devices(self) -> None:
        """Open the robot and the camera; keep the robot's identity with the run, for the
        report (a driver that cannot tell it leaves None)."""
        self.robot, self.camera = self.motion.devices.get()
        if isinstance(self.robot, DescribesRobot):
            identity = asdict(self.robot.identity())
            self._in_session(lambda s: writes.move_run(
                s, run_id=self.run_id, from_state="capturing", robot_identity=identity),
                f"recording the robot of run {self.run_id}")

    # ---- the loop --------------------------------------------------------------------------

    def _capture_owned(self) -> None:
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
        self._open_devices()
        plan = self._in_session(self._plan, f"reading run {self.run_id}")
        if plan is None:
            return
        todo, poses = plan
        with cf.ThreadPoolExecutor(1, thread_name_prefix=f"develop-{self.run_id[:8]}") as pool:
            self._worker = pool
            complete = self._visit(todo, poses)
        if self.motion.stopping.is_set():
            self.finish("interrupted", writes.INTERRUPTED, "interrupted")
        elif complete:
            counts = self._in_session(lambda s: queries.run_counts(
                s, run=queries.get_run(s, run_id=self.run_id)), "counting stations")
            if counts["stations_captured"] == 0:
                self.finish("failed", f"No station was captured ({counts['stations_skipped']} "
                            "skipped): see the station errors.", "nothing_captured")
            else:
                self.finish("done")

    def _plan(self, s: Session) -> tuple[list[int], list[list[float]]] | None:
        """The missing station indices and all poses, or None if the run is not ours."""
        run = s.get(RunRecord, self.run_id)
        if run is None or run.owner != self.token or run.state != "capturing":
            return None
        stored = queries.stored_indices(s, run_id=self.run_id)
        self.board = board_from_target(run_target(run))
        return [k for k in range(len(run.poses)) if k not in stored], run.poses

    def _visit(self, todo: list[int], poses: list[list[float]]) -> bool:
        """Capture the stations ``todo`` in order; True if all of them were stored."""
        in_worker: tuple[_Shot, cf.Future[str]] | None = None
        try:
            for index in todo:
                if self.motion.stopping.is_set() or not self._owns():
                    break
                shot = self._shoot(index, poses[index], 1)
                if shot is None or self.motion.stopping.is_set():  # None: no longer ours
                    break
                if in_worker is not None:
                    done, in_worker = self._settle(*in_worker), None
                    if not done:
                        break
                in_worker = (shot, self._develop_async(shot))
            else:
                return in_worker is None or self._settle(*in_worker)
            if in_worker is not None:  # stopped early: let the worker finish, no retry
                in_worker[1].result()
            return False
        except BaseException as exc:  # the worker still finishes its station
            if in_worker is not None and (lost := in_worker[1].exception()) not in (None, exc):
                log.error("run %s, station %d: %s: %s", self.run_id, in_worker[0].index,
                          type(lost).__name__, lost)
            raise

    def _develop_async(self, shot: _Shot) -> cf.Future[str]:
        return self._worker.submit(self._develop, shot)

    def _settle(self, shot: _Shot, future: cf.Future[str]) -> bool:
        """Wait for the worker's station, re-capturing it for its retry; True if it was
        stored, False if the run is no longer ours (or the service stops)."""
        while (outcome := future.result()) == _RETRY:
            if not self._wanted():
                return False
            again = self._shoot(shot.index, shot.pose, shot.attempt + 1)
            if again is None:
                return False
            shot, future = again, self._develop_async(again)
        return outcome == STORED

    def _shoot(self, index: int, pose: list[float], first_attempt: int) -> _Shot | None:
        """Move, settle, grab and read the pose, retrying a device error once; None if the
        run was taken meanwhile. Raises the device errors that stop the run.

        A grab timeout is the camera's fault, not the station's: it uses up no attempt, the
        station is tried again, and the ``drivers.stall.STALL_AFTER``-th timeout in a row is
        ``camera_stalled`` (raised by the camera, or here for a camera that does not count),
        which stops the run with this station still to capture, so ``resume`` captures it.
        """
        shot: _Shot | None = None
        attempt, late = first_attempt, 0
        while attempt <= ATTEMPTS:
            try:
                taken = capture_station(self.robot, self.camera, np.asarray(pose),
                                        self.options, self._frames)
            except DeviceError as exc:
                if not self._wanted():
                    return None
                if _stops_run(exc):
                    raise
                if isinstance(exc, CameraTimeoutError):
                    late += 1
                    if late >= STALL_AFTER:
                        raise CameraStalledError(f"The camera delivered no frame in {late} "
                                                 f"grabs in a row ({exc}).") from exc
                    continue
                shot = _Shot(index, pose, attempt, None, str(exc), exc.code, late=late)
                attempt += 1
                continue
            return _Shot(index, pose, attempt, taken.station(f"{index:03d}"), late=late)
        return shot

    # ---- stations a cell controller posts (service.runs.external) -------------------------

    def develop_posted(self, index: int, pose: list[float], taken: Station | None, *,
                       joints: list[float] | None = None,
                       outcome: PostedOutcome = PostedOutcome()) -> bool:
        """Detect and store a posted station as station ``index`` exactly as the worker does
        a captured one (``_develop``), without the retry: the controller took the image.
        ``taken`` holds the image (and the board found in it already, by
        ``service.jobs.image_worker``); ``outcome`` what the image worker said besides. True if
        stored."""
        with self.db.session() as s:
            self.board = board_from_target(run_target(queries.get_run(s, run_id=self.run_id)))
        detail, code = outcome.problem or (None, None)
        return self._develop(_Shot(index, pose, 1, taken, detail, code, joints,
                                   final=True, seen=outcome.seen)) == STORED

    # ---- the worker's part -----------------------------------------------------------------

    def _develop(self, shot: _Shot) -> str:
        """The worker's part of a station: detect, write the PNG and commit (``STORED``),
        or ``_RETRY`` for a first detection failure, or ``_LOST`` if the run is not ours."""
        code, taken = shot.error_code, shot.taken
        if taken is not None and (too_many := self._too_many_pixels(taken)) is not None:
            shot, taken = replace(shot, error=too_many, error_code="image_too_large"), None
            code = shot.error_code
        mismatch = None
        if taken is None or not isinstance(taken.image, np.ndarray):
            station = Station(f"{shot.index:03d}", rejected=shot.error or "No image.")
        elif (mismatch := self._first_view_mismatch(shot, taken.image)) is not None:
            station, code = replace(taken, rejected=mismatch), "board_mismatch"
        else:
            assert self.board is not None  # read with the run
            det = (self.board.detect(taken.image) if taken.detection is None
                   else taken.detection)
            if not det.ok and shot.attempt < ATTEMPTS and not shot.final:
                return _RETRY
            if not det.ok and shot.final:  # a posted image: the better reason, if any
                mismatch = (self._mismatch(taken.image) if taken.detection is None
                            else _wrong_board(shot.seen))  # searched in a worker, bounded
            station = replace(taken, detection=det, rejected=None if det.ok else mismatch or
                              f"{self.board.kind.capitalize()} not found: {det.reason}.")
            code = None if det.ok else "board_mismatch" if mismatch else "not_detected"
        self.developed = station
        stored = self._store(shot, station, code)
        if mismatch is not None and not shot.final:
            raise BoardMismatchError(mismatch)
        return STORED if stored else _LOST

    def _first_view_mismatch(self, shot: _Shot, image: np.ndarray) -> str | None:
        """``_mismatch`` for the first station a capture thread develops (not a posted one),
        None for the others: a wrong board configuration ends the run at its first station
        instead of after every station failed its whole search."""
        if shot.final or self._board_checked:
            return None
        self._board_checked = True
        return self._mismatch(image)

    def _mismatch(self, image: np.ndarray) -> str | None:
        """What ``image`` shows instead of the run's board, as a station's reason, or None
        (``calib.ChecksConfiguration``)."""
        return _wrong_board(self.board.mismatch(image)
                            if isinstance(self.board, ChecksConfiguration) else None)

    def _too_many_pixels(self, taken: Station) -> str | None:
        """Why a camera frame is too large to search, or None: a camera set to a larger
        resolution than ``max_image_pixels`` would cost the search gigabytes."""
        if not isinstance(taken.image, np.ndarray):
            return None
        height, width = taken.image.shape[:2]
        limit = self.settings.max_image_pixels
        if width * height <= limit:
            return None
        return (f"The camera frame is {width}x{height} = {width * height / 1e6:.0f} MP, more "
                f"than the {limit / 1e6:g} MP allowed (CELLCAL_MAX_IMAGE_PIXELS).")

    def _wanted(self) -> bool:
        """True while the service runs and this thread owns the run (worth another try)."""
        return not self.motion.stopping.is_set() and self._owns()

    def _owns(self) -> bool:
        return self._in_session(
            lambda s: queries.owns_run(s, run_id=self.run_id, token=self.token),
            f"checking run {self.run_id}")

    def _store(self, shot: _Shot, station: Station, code: str | None) -> bool:
        """Commit one station (image file first) unless the run is no longer ours; True if
        it was stored. ``code`` names the reason of a rejected station.

        Ownership is claimed in the same transaction as the insert (``writes.claim_run`` locks
        the run row), so a station is never committed after a cancel, a pause or a takeover
        has been committed.
        """
        self.motion.storage.check()  # a data directory deleted, read-only or full
        rel = None
        if isinstance(station.image, np.ndarray):
            rel = Path("runs") / self.run_id / f"{shot.index:03d}-{self.token[:8]}.png"
            try:
                for folder in (self.data_dir / "runs", self.data_dir / rel.parent):
                    folder.mkdir(exist_ok=True)  # never the data directory itself
                write_png(self.data_dir / rel, station.image)
            except OSError as exc:  # the directory's own check names the cause best
                raise (self.motion.storage.problem()
                       or storage_error(exc, f"writing the image of station {shot.index}")
                       ) from exc
        row = row_values(station)

        def commit(s: Session) -> bool:
            if not writes.claim_run(s, run_id=self.run_id, token=self.token):
                return False
            return writes.add_station(s, run_id=self.run_id, index=shot.index,
                                      commanded_tcp_pose=shot.pose, joint_positions=shot.joints,
                                      image_path=None if rel is None else rel.as_posix(),
                                      error_code=code, attempts=shot.tries, **row)

        stored = False
        try:
            stored = self._in_session(commit, f"storing station {shot.index} of run "
                                              f"{self.run_id}")
        finally:
            if not stored and rel is not None:
                (self.data_dir / rel).unlink(missing_ok=True)
        if not stored:
            return False
        event: dict[str, Any] = {"type": "station", "run_id": self.run_id,
                                 "index": shot.index, "state": row["state"]}
        if station.rejected:
            event["error"] = {"code": code, "detail": station.rejected}
        self._publish(event)
        return True
