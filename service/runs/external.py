"""Stations fed by a cell controller whose robot program moves the robot itself (runs in
``"mode": "external"``, ``POST /runs/{id}/stations``).

A posted station brings the robot pose (and the joint positions, if known) with an image; or
the pose only, and the service grabs from its camera; or nothing, and the service reads the
pose from its robot (which must be at rest: the reading before and after the grab must agree)
and grabs. The board is detected and the station stored by the capture loop's own code
(``Capture.develop_posted``), so posted stations are stored, streamed and calibrated exactly
like captured ones; the answer says at once whether the board was found and why not.

An image is bounded before it is decoded, and decoded and searched in a memory-limited
worker process (``service.jobs.image_worker``): more pixels than allowed is 413
``image_too_large`` at once, and nothing is stored. An image that cannot be used otherwise
(not PNG or JPEG, corrupt, truncated) becomes a skipped station with the reason, like a failed
grab in the capture loop. Stations take the next free index; posts to one run are developed
and stored one at a time, posts to different runs side by side. A run takes at most
``max_stations`` stations (409 ``too_many_stations`` beyond, before the image is developed).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session

from calib import Station as CalibStation
from calib import Target, check_joint_positions, check_ur_pose
from drivers.base import ReportsFreshness, Robot
from drivers.capture import grab_at_rest
from drivers.errors import CameraFrozenError, RobotError
from drivers.frozen import FrameWatch
from service.cell.motion import Motion
from service.errors import ConflictError, UnprocessableError
from service.events import EventBus
from service.jobs.image_worker import ImageWorkers, check_pixels
from service.runs.capture import Capture, PostedOutcome
from service.store import queries
from service.store.records import RunRecord, StationRecord
from service.store.stations import run_target

log = logging.getLogger("cellcal.service")


@dataclass(frozen=True)
class PostedStation:
    """What a cell controller sent for one station (all optional, see the module doc).

    pose : T_base_tcp ``[x, y, z, rx, ry, rz]`` (m, rad) at the image.
    joints : the six joint positions (rad) at the image.
    image : PNG or JPEG bytes, as uploaded.
    """

    pose: list[float] | None = None
    joints: list[float] | None = None
    image: bytes | None = None


class ExternalStations:
    """Adds posted stations to external runs."""

    def __init__(self, motion: Motion, events: EventBus) -> None:
        self.motion = motion
        self.events = events
        #: Decodes and searches posted images.
        self.images = ImageWorkers(motion.settings)
        self._locks: dict[str, threading.Lock] = {}  # run id -> its posts' lock
        self._locks_lock = threading.Lock()
        #: The frames the service grabbed for posts: a frozen camera is refused (503
        #: ``camera_frozen``) instead of giving every station its one frame.
        self._frames = FrameWatch()

    def add(self, run_id: str, posted: PostedStation) -> StationRecord:
        """Store one posted station of an external run that accepts stations; the row."""
        pose, joints = _checked(posted)
        self.motion.storage.check()
        if posted.image is not None:  # before anything else: a refusal costs nothing
            check_pixels(posted.image, self.motion.settings.max_image_pixels)
        with self.motion.db.session() as s:
            run = queries.get_run(s, run_id=run_id)
            _check_accepts(run)
            _check_room(s, run_id, self.motion.settings.max_stations)  # before the image
            token, target = run.owner, run_target(run)
        with self._run_lock(run_id):
            return self._add(run_id, token, target,
                             PostedStation(pose=pose, joints=joints, image=posted.image))

    def _run_lock(self, run_id: str) -> threading.Lock:
        with self._locks_lock:
            return self._locks.setdefault(run_id, threading.Lock())

    def _grab(self, pose: list[float] | None, joints: list[float] | None
              ) -> tuple[np.ndarray, list[float], list[float] | None, str | None]:
        """The service's own grab for a post without an image: the image, the pose (posted,
        or read from the robot at rest), the joints and how the frame was made fresh."""
        if pose is not None:
            _, camera = self.motion.devices.get()
            image = camera.grab(timeout=self.motion.settings.grab_timeout_s)
            self._frames.check(image, np.asarray(pose, dtype=float))
            return image, pose, joints, (camera.freshness if isinstance(camera, ReportsFreshness)
                                         else None)
        robot, camera = self.motion.devices.get()
        with self.motion.robot_lock:
            still = grab_at_rest(robot, camera, grab_timeout=self.motion.settings.grab_timeout_s,
                                 watch=self._frames)
        return (still.image, [float(v) for v in still.tcp_pose],
                _joints(robot) if joints is None else joints, still.freshness)

    def _add(self, run_id: str, token: str | None, target: Target,
             posted: PostedStation) -> StationRecord:
        """Develop and store one station of ``run_id`` (``posted``: pose and joints checked;
        the caller holds the run's lock)."""
        pose, joints = posted.pose, posted.joints
        image, detection, problem, freshness, seen = None, None, None, None, None
        if posted.image is not None:
            developed = self.images.develop(posted.image, target)
            image, detection, seen = developed.image, developed.detection, developed.seen
            if developed.problem is not None:
                problem = (developed.problem, "image_unreadable")
        else:
            try:
                image, pose, joints, freshness = self._grab(pose, joints)
            except CameraFrozenError:
                self.motion.devices.reset()  # opened afresh for the next post
                raise
        assert pose is not None and token is not None
        capture = Capture(self.motion, self.events, run_id=run_id, token=token)
        with self.motion.db.session() as s:
            index = _check_room(s, run_id, self.motion.settings.max_stations)
        taken = None if image is None else CalibStation(
            f"{index:03d}", T_base_tcp=np.asarray(pose, dtype=float), image=image,
            image_size=(image.shape[1], image.shape[0]), detection=detection,
            freshness=freshness)
        stored = capture.develop_posted(index, pose, taken, joints=joints,
                                        outcome=PostedOutcome(problem, seen))
        if not stored:
            raise ConflictError(f"Run {run_id} stopped accepting stations meanwhile; the "
                                "station was not stored.", code="invalid_state")
        with self.motion.db.session() as s:  # a new session sees the new row
            return queries.get_station(s, run_id=run_id, index=index)


def _joints(robot: Robot) -> list[float] | None:
    """The robot's joint positions, or None when it cannot tell them (``joints_unknown``, as
    the mock beyond its kinematic model's reach): a station is kept without them."""
    try:
        return [float(v) for v in robot.joint_positions()]
    except RobotError as exc:
        if exc.code != "joints_unknown":
            raise
        log.info("station stored without joint positions: %s", exc)
        return None


def _checked(posted: PostedStation) -> tuple[list[float] | None, list[float] | None]:
    """The posted pose and joints as floats, checked (422 ``invalid_pose``)."""
    if posted.image is not None and posted.pose is None:
        raise UnprocessableError("An image needs the robot pose it was taken at: send 'pose' "
                                 "with it.", code="invalid_pose")
    try:
        if posted.pose is not None:
            check_ur_pose(np.asarray(posted.pose, dtype=float), "pose")
        if posted.joints is not None:
            check_joint_positions(np.asarray(posted.joints, dtype=float), "joints")
    except ValueError as exc:
        raise UnprocessableError(str(exc), code="invalid_pose") from None
    return (None if posted.pose is None else [float(v) for v in posted.pose],
            None if posted.joints is None else [float(v) for v in posted.joints])


def _check_room(s: Session, run_id: str, limit: int) -> int:
    """The index of the run's next station; 409 ``too_many_stations`` if the run already has
    ``limit`` (``max_stations``), as a robot run may not plan more."""
    index = queries.next_station_index(s, run_id=run_id)
    if index >= limit:
        raise ConflictError(f"Run {run_id} has {index} stations, the most a run may have "
                            f"(CELLCAL_MAX_STATIONS={limit}); finish it and calibrate, or "
                            "start another run.", code="too_many_stations")
    return index


def _check_accepts(run: RunRecord) -> None:
    """409 unless ``run`` is an external run that accepts stations."""
    if run.mode != "external":
        raise ConflictError(f"Run {run.id} is driven by the service ('robot' mode); only runs "
                            "in 'external' mode take posted stations.", code="invalid_mode")
    if run.state != "capturing":
        raise ConflictError(f"Run {run.id} is {run.state}; resume it to post stations.",
                            code="invalid_state")
