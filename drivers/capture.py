"""Capture calibration stations (move, settle, grab, read pose) and write them as a station set.

A captured set is written in the ``cellcal/stations@1`` format of ``product.md`` (one PNG per
station), so ``cellcal calibrate`` reads a capture directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from calib import Station, check_ur_pose, check_ur_vector, matrix_from_ur_pose, pose_error
from drivers.base import Camera, ReportsFreshness, Robot
from drivers.errors import RobotError
from drivers.frozen import FrameWatch


@dataclass(frozen=True)
class CapturedStation:
    """One captured station: the frame and the robot reading that belongs to it.

    Timestamps are wall-clock seconds (``time.time()``), so they can be compared with logs.
    """

    image: np.ndarray  # shape (H, W) or (H, W, 3), uint8
    tcp_pose: np.ndarray  # shape (6,), T_base_tcp read after the grab
    target_tcp_pose: np.ndarray  # shape (6,), the commanded pose
    moved_at: float  # move command sent
    settled_at: float  # robot at rest
    grabbed_at: float  # frame returned by the camera
    pose_read_at: float  # tcp_pose read
    freshness: str | None = None  # how the camera made sure the frame is fresh, if it says

    def station(self, station_id: str) -> Station:
        """The one station model of this capture (the pixels as its image)."""
        height, width = self.image.shape[:2]
        return Station(id=station_id, T_base_tcp=self.tcp_pose, image=self.image,
                       image_size=(width, height), freshness=self.freshness)


@dataclass(frozen=True)
class CaptureOptions:
    """How a station is visited: ``settle_timeout`` and ``grab_timeout`` in seconds, the move's
    ``speed`` (m/s) and ``acceleration`` (m/s^2), and ``max_drift`` (metres, radians): how far
    the robot may move while the image is taken (``grab_at_rest``)."""

    settle_timeout: float = 5.0
    grab_timeout: float = 2.0
    speed: float = 0.25
    acceleration: float = 1.2
    max_drift: tuple[float, float] = (1e-4, 1e-3)


def capture_station(robot: Robot, camera: Camera, tcp_target: np.ndarray,
                    options: CaptureOptions = CaptureOptions(),
                    watch: FrameWatch | None = None) -> CapturedStation:
    """Move to ``tcp_target`` (UR pose, shape (6,)), settle, grab a fresh frame, read the pose.

    The pose is read *after* the grab, and compared with a reading taken just before it. The
    camera returns a frame exposed after the grab call, so the reading after it describes a
    state no earlier than the exposure; if the two readings differ by more than
    ``options.max_drift`` the robot moved while the image was taken (it had not really
    settled, or was bumped) and the station is refused with ``RobotError`` (code
    ``moved_during_grab``) rather than pairing an image with the wrong pose. ``watch``, kept
    over a capture's stations, refuses a frozen camera (``drivers.frozen``).
    """
    check_ur_pose(tcp_target, "tcp_target")
    target = np.asarray(tcp_target, dtype=float)
    moved_at = time.time()
    robot.move_linear(target, speed=options.speed, acceleration=options.acceleration)
    robot.wait_settled(timeout=options.settle_timeout)
    settled_at = time.time()
    still = grab_at_rest(robot, camera, grab_timeout=options.grab_timeout,
                         max_drift=options.max_drift, watch=watch)
    return CapturedStation(image=still.image, tcp_pose=still.tcp_pose, target_tcp_pose=target,
                           moved_at=moved_at, settled_at=settled_at,
                           grabbed_at=still.grabbed_at, pose_read_at=still.pose_read_at,
                           freshness=still.freshness)


def read_tcp_pose(robot: Robot) -> np.ndarray:
    """The robot's TCP pose reading, shape (6,), checked as a commanded pose is: finite, a
    rotation vector within π rad, a translation in metres. A reading that is not (a driver
    or controller fault: NaN, degrees, millimetres) raises ``RobotError`` (code
    ``invalid_reading``) instead of being stored with an image, planned from or shown."""
    try:
        return check_ur_vector(np.asarray(robot.tcp_pose(), dtype=float),
                               "the robot's TCP pose reading")
    except ValueError as exc:
        raise RobotError(f"{exc}; the reading was not used.", code="invalid_reading") from None


@dataclass(frozen=True)
class Still:
    """A frame of a robot at rest and the pose read after it (``grab_at_rest``)."""

    image: np.ndarray  # shape (H, W) or (H, W, 3), uint8
    tcp_pose: np.ndarray  # shape (6,), T_base_tcp read after the grab
    grabbed_at: float  # frame returned by the camera, time.time()
    pose_read_at: float  # tcp_pose read, time.time()
    freshness: str | None = None  # the camera's ``ReportsFreshness.freshness`` of the frame


def grab_at_rest(robot: Robot, camera: Camera, *, grab_timeout: float = 2.0,
                 max_drift: tuple[float, float] = (1e-4, 1e-3),
                 watch: FrameWatch | None = None) -> Still:
    """Grab a frame where the robot stands and read its pose, refusing a robot in motion.

    The pose is read after the grab and compared with a reading taken just before it; if they
    differ by more than ``max_drift`` (metres, radians) the robot moved while the image was
    taken and ``RobotError`` (code ``moved_during_grab``) is raised rather than pairing an
    image with the wrong pose. ``watch`` (the capture's earlier frames) raises
    ``CameraFrozenError`` for a frame that an earlier grab got although the robot moved since.
    """
    before = read_tcp_pose(robot)
    image = camera.grab(timeout=grab_timeout)
    grabbed_at = time.time()
    after = read_tcp_pose(robot)
    pose_read_at = time.time()
    angle, dist = pose_error(matrix_from_ur_pose(before), matrix_from_ur_pose(after))
    if dist > max_drift[0] or angle > max_drift[1]:
        raise RobotError(
            f"The robot moved by {dist * 1e3:.2f} mm / {np.rad2deg(angle):.3f} deg while the "
            "image was taken; it had not settled. Increase the settle time and retry.",
            code="moved_during_grab")
    if watch is not None:
        watch.check(image, after)
    return Still(image=image, tcp_pose=np.asarray(after, dtype=float), grabbed_at=grabbed_at,
                 pose_read_at=pose_read_at,
                 freshness=camera.freshness if isinstance(camera, ReportsFreshness) else None)
