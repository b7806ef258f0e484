"""Where a run goes: stations planned around the board seen from the robot's current pose,
or poses given by the user, checked against the robot's limits and the workspace box; or a
cold start (``service.runs.coldstart``), planned station by station as the run goes."""

from __future__ import annotations

from typing import Any

import numpy as np

from calib import (
    CellGuess,
    ChecksConfiguration,
    Pinhole,
    PlanOptions,
    Target,
    board_from_target,
    camera_from_robot,
    check_ur_poses,
    matrix_from_ur_pose,
    plan_stations,
    rough_target_from_image,
    ur_pose_from_matrix,
)
from drivers import registry
from drivers.capture import read_tcp_pose
from service.cell.motion import Motion
from service.errors import UnprocessableError


def plan_poses(motion: Motion, *, n: int, target: Target,
               setup: str) -> list[list[float]]:
    """Plan ``n`` stations around the board as seen from the robot's current pose.

    Only for a backend that knows its cell (``informed_backend``: a simulator that describes
    its scene); every other cell plans from a cold start. The board pose comes from one image
    at the current pose; the hand-eye and the camera from the configured rough guesses or,
    failing those, from what the backend knows (``Settings.cell_hints``). The distance band is
    0.8 to 1.3 times the current camera-to-board distance.
    """
    settings = motion.settings
    hints = settings.cell_hints()  # an informed backend's (``informed_backend``), or guesses
    assert hints.hand_eye is not None
    X, K, dist = hints.hand_eye, hints.K, hints.dist
    robot, camera = motion.devices.get()
    with motion.robot_lock:
        P0 = matrix_from_ur_pose(read_tcp_pose(robot))
        image = camera.grab(timeout=settings.grab_timeout_s)
    h, w = image.shape[:2]
    if K is None:
        f = float(settings.focal_px_guess or 0.0)
        K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    board = board_from_target(target)
    if isinstance(board, ChecksConfiguration) and (seen := board.mismatch(image)) is not None:
        raise UnprocessableError(f"Cannot plan: wrong board configuration: {seen}; correct "
                                 "the run's target.", code="board_mismatch")
    det = board.detect(image)
    if not det.ok:
        raise UnprocessableError(
            f"Cannot plan: the board is not in view at the robot's current pose "
            f"({det.reason}). Move the robot so the camera sees the whole board.",
            code="planning_failed")
    try:
        pinhole = Pinhole(K, dist)
        Y = rough_target_from_image(det.corners, pinhole, board, CellGuess(P0, X, setup=setup),
                                    det.ids)
        d0 = float(np.linalg.norm(camera_from_robot(P0, X, Y, setup)[:3, 3]))
        plan = plan_stations(n, CellGuess(P0, X, Y, setup), pinhole, board, PlanOptions(
            image_size=(w, h), distance_band=(0.8 * d0, 1.3 * d0),
            workspace=settings.workspace()))
    except ValueError as exc:
        raise UnprocessableError(f"Cannot plan {n} stations: {exc}.",
                                 code="planning_failed") from None
    return ur_pose_from_matrix(plan.tcp_poses).tolist()


def informed_backend(motion: Motion) -> bool:
    """Whether the robot's backend itself knows the hand-eye and the camera (a simulator
    that describes its scene): then ``stations`` runs keep the one-shot plan, which needs
    no exploration; a real cell, or a blind simulator, plans from a cold start."""
    known = registry.describe_cell(motion.settings.robot, motion.settings.scene)
    return known.hand_eye is not None and known.K is not None


def cold_start_plan(motion: Motion, *, target: Target, stations: int | None,
                    stop_rule: dict[str, Any] | None) -> dict[str, Any]:
    """The stored plan of a cold-start run from the robot's current pose (the run's
    ``cold_start`` column): one image there must show the board (422 ``planning_failed``),
    and the pose must lie in the workspace box (422 ``outside_workspace``)."""
    robot, camera = motion.devices.get()
    with motion.robot_lock:
        start = read_tcp_pose(robot)
        image = camera.grab(timeout=motion.settings.grab_timeout_s)
    if (outside := motion.outside_workspace(start)) is not None:
        raise UnprocessableError(f"The robot's current pose: {outside}; jog it into the box "
                                 "where the camera sees the board.", code="outside_workspace")
    det = board_from_target(target).detect(image)
    if not det.ok:
        raise UnprocessableError(
            f"Cannot start: the board is not in view at the robot's current pose "
            f"({det.reason}). Jog the robot so the camera sees the board.",
            code="planning_failed")
    h, w = image.shape[:2]
    return {"stations": stations, "stop_rule": stop_rule,
            "start_pose": [float(v) for v in start], "image_size": [w, h],
            "seed": int(np.random.default_rng().integers(2**31)), "stop_reason": None,
            "exploratory_moves": 0, "sigma_history": [], "notes": []}


def check_station_count(motion: Motion, n: int) -> None:
    """422 ``too_many_stations`` if a run of ``n`` stations passes ``max_stations``: the
    service's limit holds for every kind of run (planned, given poses, a cold start or a
    tolerance, and external runs as they grow)."""
    limit = motion.settings.max_stations
    if n > limit:
        raise UnprocessableError(f"{n} stations asked for; a run may have at most {limit} "
                                 "(CELLCAL_MAX_STATIONS).", code="too_many_stations")


def check_poses(motion: Motion, poses: list[list[float]]) -> list[list[float]]:
    """Refuse poses that are too many, malformed, implausible or outside the workspace box
    (422)."""
    check_station_count(motion, len(poses))
    try:
        check_ur_poses(np.asarray(poses, dtype=float), "poses")
    except ValueError as exc:
        raise UnprocessableError(str(exc), code="invalid_pose") from None
    for k, pose in enumerate(poses):
        if (outside := motion.outside_workspace(pose)) is not None:
            raise UnprocessableError(f"poses[{k}]: {outside}; the run was not started.",
                                     code="outside_workspace")
    return [[float(v) for v in pose] for pose in poses]
