"""Dot-hit validation run (Zhao & Liu, eq. 24): the robot touches board points with a probe.

The board points are reconstructed in the base frame *through the calibration*, the robot is
commanded to put its probe tip on each of them, and the reached positions are reported. Where
the truth is known (a simulated cell) the distance between the probe tip and the true point is
the end-to-end error of the calibration, the number a user of the cell cares about.

Reconstruction (eq. 24, ``D_r = C⁻¹ X D_c`` with ``C⁻¹`` = T_base_tcp). From an observation
``(T_base_tcp, T_cam_target)`` of the board, the board lies at

* eye-in-hand: T_base_target = ``T_base_tcp @ X @ T_cam_target`` (``X`` = T_tcp_cam);
* eye-to-hand: T_base_target = ``X @ T_cam_target`` (``X`` = T_base_cam), for a board placed
  in the cell for the test (the calibration board rides on the tool, out of the probe's reach).

The observation must be at the true board scale (translation times κ) and the points in the
true (κ, ν-scaled) target frame. Without an observation, eye-in-hand uses the calibration's
target pose, which is eq. 24 averaged over the calibration stations; a fresh observation also
catches a hand-eye that is inconsistent with the target pose.

Probe. ``T_tcp_probe`` puts the probe tip at its origin with the probe pointing along its z
axis. It touches a point pointing into the board's front (along target +z, which points away
from a camera looking at the front, ``docs/conventions.md``), rotated as little as possible
from the robot's orientation at the start, after an approach from ``approach`` metres straight
out of the board.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from calib import (
    SETUPS,
    Board,
    check_transforms,
    invert,
    make_transform,
    matrix_from_ur_pose,
    ur_pose_from_matrix,
)
from drivers.base import Robot
from drivers.capture import read_tcp_pose

#: Approach distance (m) above each point, along the board normal.
DEFAULT_APPROACH_M = 0.03


@dataclass(frozen=True)
class GroundTruth:
    """What a simulated cell knows exactly.

    Attributes
    ----------
    board_pose : shape (4, 4)
        True T_base_target of the probed board; the points' true positions are ``board_pose @ p``.
    tcp_pose : callable returning shape (4, 4), optional
        True T_base_tcp at rest (e.g. ``lambda: mock_robot.true_pose``); default: the robot's
        reading.
    """

    board_pose: np.ndarray
    tcp_pose: Callable[[], np.ndarray] | None = None


@dataclass(frozen=True)
class DotHitPoint:
    """One touched point; positions in the base frame, metres."""

    target_id: str
    point_target: np.ndarray  # shape (3,), target frame (true geometry)
    commanded: np.ndarray  # shape (3,), reconstructed through the calibration
    reached: np.ndarray  # shape (3,), probe tip from the robot's reading at the touch
    error_m: float | None  # |true probe tip - true point|, when the truth is known


@dataclass(frozen=True)
class DotHitReport:
    """Result of :func:`run_dot_hit`."""

    points: list[DotHitPoint]

    @property
    def errors_m(self) -> np.ndarray | None:
        """Per-point errors (m), shape (n,), or None without ground truth."""
        if any(p.error_m is None for p in self.points):
            return None
        return np.array([p.error_m for p in self.points])

    def to_json(self) -> dict[str, Any]:
        """JSON document: per-point positions and errors in metres, plus their summary."""
        errors = self.errors_m
        return {
            "points": [{"id": p.target_id, "point_target": p.point_target.tolist(),
                        "commanded": p.commanded.tolist(), "reached": p.reached.tolist(),
                        "error_m": p.error_m} for p in self.points],
            "error_m": None if errors is None else {
                "mean": float(errors.mean()), "max": float(errors.max())},
        }

    def summary(self) -> str:
        """One line per point for people, in millimetres."""
        lines = []
        for p in self.points:
            err = "" if p.error_m is None else f", error {p.error_m * 1e3:.2f} mm"
            gap = np.linalg.norm(p.reached - p.commanded) * 1e3
            lines.append(f"{p.target_id}: reached {gap:.2f} mm from the commanded point{err}")
        return "\n".join(lines)


def probe_points(board: Board, *, kappa: float = 1.0, nu: float = 1.0) -> dict[str, np.ndarray]:
    """The default points to touch: the four outermost corners of the board's point grid and
    the grid's centre.

    Returns id -> position, shape (3,), in the (κ, ν-scaled) target frame; corner ids are
    ``corner_i_j`` with (i, j) the point's grid index, its nominal position over the square
    size (``docs/conventions.md``; the same for a checkerboard and a ChArUco board).
    """
    ids = board.point_ids
    grid_index = np.rint(board.points(ids)[:, :2] / board.square_size).astype(int)
    scaled = board.points(ids, kappa=kappa, nu=nu)
    at = {(int(i), int(j)): p for (i, j), p in zip(grid_index, scaled, strict=True)}
    (i0, j0), (i1, j1) = grid_index.min(axis=0), grid_index.max(axis=0)
    out = {f"corner_{i}_{j}": at[(int(i), int(j))] for j in (j0, j1) for i in (i0, i1)}
    out["centre"] = (at[(int(i0), int(j0))] + at[(int(i1), int(j1))]) / 2
    return out


def board_in_base(hand_eye: np.ndarray, *, setup: str, target_pose: np.ndarray | None = None,
                  observation: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """T_base_target of the probed board reconstructed through the calibration, (4, 4).

    Parameters
    ----------
    hand_eye : shape (4, 4), T_tcp_cam (eye-in-hand) or T_base_cam (eye-to-hand).
    setup : ``eye_in_hand`` or ``eye_to_hand``.
    target_pose : shape (4, 4), the calibration's T_base_target; eye-in-hand, used when no
        observation is given.
    observation : (T_base_tcp, T_cam_target), shapes (4, 4): the robot reading and the camera
        pose of the board (true scale) at one station. Required eye-to-hand.
    """
    if setup not in SETUPS:
        raise ValueError(f"unknown setup '{setup}': choose eye_in_hand or eye_to_hand")
    if observation is None:
        if setup == "eye_to_hand":
            raise ValueError("eye-to-hand dot-hit needs an observation of a board placed in "
                             "the cell: the calibration board rides on the tool")
        if target_pose is None:
            raise ValueError("dot-hit needs the calibration's target_pose or an observation")
        return target_pose
    T_base_tcp, T_cam_target = observation
    if setup == "eye_in_hand":
        return T_base_tcp @ hand_eye @ T_cam_target
    return hand_eye @ T_cam_target


def tcp_pose_for_probe(point: np.ndarray, direction: np.ndarray, T_tcp_probe: np.ndarray,
                       reference: np.ndarray) -> np.ndarray:
    """T_base_tcp putting the probe tip on ``point`` pointing along ``direction``, (4, 4).

    Of all such poses, the one that rotates least from the ``reference`` tcp pose (4, 4): the
    reference probe turned along the shortest arc from its axis to ``direction``, so it does
    not spin about its own axis. ``point`` and ``direction`` shape (3,), base frame.
    """
    R_ref = (reference @ T_tcp_probe)[:3, :3]
    arc, _ = Rotation.align_vectors(np.asarray(direction, dtype=float)[None], R_ref[None, :, 2])
    T_base_probe = make_transform(arc.as_matrix() @ R_ref, point)
    return T_base_probe @ invert(T_tcp_probe)


def approach_pose(T_base_tcp: np.ndarray, T_tcp_probe: np.ndarray, distance: float) -> np.ndarray:
    """The tcp pose (4, 4) with the probe backed off ``distance`` m along its own axis."""
    back = make_transform(np.eye(3), [0.0, 0.0, -distance])
    return T_base_tcp @ T_tcp_probe @ back @ invert(T_tcp_probe)


@dataclass(frozen=True)
class BoardEstimate:
    """The calibration and the board's observation that place the board, see
    :func:`board_in_base`."""

    setup: str
    hand_eye: np.ndarray  # shape (4, 4)
    target_pose: np.ndarray | None = None  # shape (4, 4)
    observation: tuple[np.ndarray, np.ndarray] | None = None  # (T_base_tcp, T_cam_target)


@dataclass(frozen=True)
class Probe:
    """The probe and how it touches: ``T_tcp_probe`` (4, 4), the probe tip in the tcp frame
    with the probe along its z axis; ``approach`` metres out of the board before and after
    each touch; ``speed`` and ``touch_speed`` m/s of the travel and of the final approach."""

    T_tcp_probe: np.ndarray
    approach: float = DEFAULT_APPROACH_M
    speed: float = 0.1
    touch_speed: float = 0.02


@dataclass(frozen=True)
class CellChecks:
    """What the cell adds to a run: ``workspace_check``, called with each commanded UR pose
    (6,) and raising to refuse it (e.g. ``Workspace.check``); ``ground_truth`` of a simulated
    cell, for ``error_m``."""

    workspace_check: Callable[[np.ndarray], None] | None = None
    ground_truth: GroundTruth | None = None


def run_dot_hit(robot: Robot, points: Mapping[str, ArrayLike], board: BoardEstimate,
                probe: Probe, cell: CellChecks = CellChecks()) -> DotHitReport:
    """Touch each point with the probe and report where the probe got to.

    Every commanded pose (approach, touch, and the return to the start) is computed and passed
    to ``cell.workspace_check`` first, so a run that would leave the workspace is refused
    before the robot moves. Per point: straight to the approach pose, slowly down to the touch,
    settle, read the TCP pose, back to the approach pose; finally back to where the robot
    started.

    Parameters
    ----------
    robot : a connected ``drivers.base.Robot``.
    points : id -> position, shape (3,), true target frame (e.g. :func:`probe_points`).
    board, probe, cell : see :class:`BoardEstimate`, :class:`Probe`, :class:`CellChecks`.
    """
    T_base_target = _checked_board(board)
    T_tcp_probe = check_transforms(probe.T_tcp_probe, "T_tcp_probe")[0]
    if not points:
        raise ValueError("dot-hit needs at least one point to touch")
    if probe.approach <= 0.0:
        raise ValueError("approach must be a positive distance in metres, got "
                         f"{probe.approach}")
    ids = list(points)
    p_target = np.array([np.asarray(points[i], dtype=float).reshape(3) for i in ids])
    commanded = p_target @ T_base_target[:3, :3].T + T_base_target[:3, 3]

    start = matrix_from_ur_pose(read_tcp_pose(robot))
    touch = [tcp_pose_for_probe(p, T_base_target[:3, 2], T_tcp_probe, start) for p in commanded]
    above = [approach_pose(T, T_tcp_probe, probe.approach) for T in touch]
    if cell.workspace_check is not None:
        for T in [*touch, *above, start]:
            cell.workspace_check(ur_pose_from_matrix(T))

    out = []
    for target_id, p, p_cmd, T_touch, T_above in zip(ids, p_target, commanded, touch, above,
                                                       strict=True):
        robot.move_linear(ur_pose_from_matrix(T_above), speed=probe.speed)
        robot.move_linear(ur_pose_from_matrix(T_touch), speed=probe.touch_speed)
        robot.wait_settled()
        reading = matrix_from_ur_pose(read_tcp_pose(robot))
        reached = (reading @ T_tcp_probe)[:3, 3]
        error = None
        if (truth := cell.ground_truth) is not None:
            T_base_tcp = reading if truth.tcp_pose is None else truth.tcp_pose()
            T_true = truth.board_pose
            error = float(np.linalg.norm((T_base_tcp @ T_tcp_probe)[:3, 3]
                                         - (T_true[:3, :3] @ p + T_true[:3, 3])))
        robot.move_linear(ur_pose_from_matrix(T_above), speed=probe.speed)
        out.append(DotHitPoint(target_id=target_id, point_target=p, commanded=p_cmd,
                               reached=reached, error_m=error))
    robot.move_linear(ur_pose_from_matrix(start), speed=probe.speed)
    return DotHitReport(points=out)


def _checked_board(board: BoardEstimate) -> np.ndarray:
    """T_base_target (4, 4) of a checked ``BoardEstimate``."""
    observation = board.observation
    if observation is not None:
        observation = (check_transforms(observation[0], "observation T_base_tcp")[0],
                       check_transforms(observation[1], "observation T_cam_target")[0])
    target_pose = (None if board.target_pose is None
                   else check_transforms(board.target_pose, "target_pose")[0])
    return board_in_base(check_transforms(board.hand_eye, "hand_eye")[0], setup=board.setup,
                         target_pose=target_pose, observation=observation)
