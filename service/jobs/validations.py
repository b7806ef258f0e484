"""Validations of a calibration, checked, started and recorded: the dot-hit run (SM eq. 24)
and the re-check (``service.jobs.checks``: has the camera mount moved?).

A request is checked against the calibration's result document (``dot_hit_plan``,
``check_plan``), the robot is claimed (``service.cell.motion``), and a thread does the work and
stores the report: the dot-hit run observes the board from where the robot stands and touches
the requested points (``service.jobs.validation_run``); the re-check revisits stations.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib import (
    Detection,
    StoredCell,
    Target,
    check_ur_poses,
    matrix_from_ur_pose,
    ur_pose_from_matrix,
)
from drivers.base import GroundTruthSource, Robot
from drivers.capture import CaptureOptions, read_tcp_pose
from drivers.errors import CameraFrozenError, DeviceError, RobotConnectionError
from service.cell.motion import Motion, MotionJobs
from service.errors import ConflictError, ServiceError, UnprocessableError
from service.events import EventBus
from service.jobs.checks import CheckPlan, check_plan, run_check
from service.jobs.outcomes import Outcomes
from service.jobs.validation_run import (
    BoardEstimate,
    CellChecks,
    GroundTruth,
    Probe,
    probe_points,
    run_dot_hit,
)
from service.results.document import stored_cell
from service.schemas import CheckCreate, ValidationCreate
from service.store import queries, writes
from service.store.records import Topic, ValidationRecord, new_id
from service.store.stations import run_target

log = logging.getLogger("cellcal.service")
#: Where a validation sends its progress events.
Report = Callable[[dict[str, Any]], None]
#: A validation's work: its report document, given where to send progress.
Work = Callable[[Report], dict[str, Any]]


class Validations(MotionJobs):
    """Starts dot-hit runs on the robot and records their reports."""

    def __init__(self, motion: Motion, events: EventBus, outcomes: Outcomes) -> None:
        super().__init__(motion, events)
        self.outcomes = outcomes

    def start(self, cal_id: str, body: ValidationCreate) -> ValidationRecord:
        """Check a dot-hit request, claim the robot and start the run in a thread."""
        target, result, _ = self._calibration(cal_id)
        plan = dot_hit_plan(result or {}, target, body)
        return self._launch(cal_id, "dot_hit", lambda report: self._dot_hit(plan))

    def start_check(self, cal_id: str, body: CheckCreate) -> ValidationRecord:
        """Check a re-check request, claim the robot and start the check in a thread."""
        target, result, stations = self._calibration(cal_id)
        plan = check_plan(result or {}, target, stations, body)
        for k, pose in enumerate(plan.poses):
            if (outside := self.motion.outside_workspace(pose)) is not None:
                raise UnprocessableError(f"poses[{k}]: {outside}; the check was not started.",
                                         code="outside_workspace")
        return self._launch(cal_id, "check", lambda report: self._check(plan, report))

    def _calibration(self, cal_id: str) -> tuple[Target, dict[str, Any] | None,
                                                 list[tuple[int, list[float]]]]:
        """The finished calibration's board, result and captured stations (index, commanded
        pose); 409 if it is not finished, 422 if this service drives another robot."""
        with self.db.session() as s:
            cal = queries.get_calibration(s, cal_id=cal_id)
            if cal.state != "done":
                raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished "
                                    "calibration can be validated.", code="invalid_state")
            run = queries.get_run(s, run_id=cal.run_id)
            stations = [(st.index, st.commanded_tcp_pose)
                        for st in queries.captured_stations(s, run_id=run.id)]
            robot_url, target, result = run.robot, run_target(run), cal.result
        if (run.cell, robot_url) != (self.settings.cell, self.settings.robot):
            raise UnprocessableError(f"Calibration {cal_id} was captured with robot "
                                     f"{robot_url} of cell {run.cell}; this service drives "
                                     f"{self.settings.robot} of cell {self.settings.cell}.",
                                     code="other_robot")
        return target, result, stations

    def _launch(self, cal_id: str, kind: str, work: Work) -> ValidationRecord:
        """Store a running validation of ``kind`` and run ``work`` (its report) in a thread."""
        val_id = new_id()
        with self.motion.claim(f"validation {val_id}") as s:
            val = writes.add_validation(s, id=val_id, cell=self.settings.cell,
                                        robot=self.settings.robot,
                                        instance_id=self.motion.instance_id,
                                        calibration_id=cal_id, kind=kind, state="running")
        self.motion.start(val.id, self._validate, val.id, work,
                          name=f"{kind}-{val.id[:8]}")
        return val

    def _validate(self, val_id: str, work: Work) -> None:
        """The validation thread: do the work holding the robot (its progress events go to the
        validation's stream), store the report, publish the final state."""
        topic = Topic("validation", val_id)

        def report(event: dict[str, Any]) -> None:  # queued: the database is not waited for
            self.events.publish(topic, {**event, "validation_id": val_id})

        values: dict[str, Any] = {"state": "failed"}
        try:
            with self.motion.robot_lock:
                values.update(state="done", result=work(report))
        except (DeviceError, ServiceError, ValueError) as exc:
            if isinstance(exc, RobotConnectionError | CameraFrozenError):
                self.motion.devices.reset()  # opened afresh by the next job
            if self.motion.stopping.is_set():
                values.update(error="The service stopped during the validation; start it "
                                    "again.", error_code="interrupted")
            else:
                values.update(error=str(exc), error_code=exc.code if isinstance(
                    exc, DeviceError | ServiceError) else "validation_failed")
        except Exception as exc:
            log.exception("validation %s", val_id)
            values.update(error=f"Internal error ({type(exc).__name__}: {exc}).",
                          error_code="internal_error")
        self.outcomes.finish(topic, values)

    def _check(self, plan: CheckPlan, report: Report) -> dict[str, Any]:
        """Revisit the plan's stations and compare them with the calibration."""
        robot, camera = self.motion.devices.get()
        options = CaptureOptions(settle_timeout=self.settings.settle_timeout_s,
                                 grab_timeout=self.settings.grab_timeout_s,
                                 speed=self.settings.move_speed)
        return run_check(robot, camera, plan, options, report)

    def _dot_hit(self, plan: DotHitPlan) -> dict[str, Any]:
        """Observe the board from where the robot stands (eq. 24 needs a current view), then
        touch each point; the report document."""
        robot, camera = self.motion.devices.get()
        tcp_pose = read_tcp_pose(robot)
        image = camera.grab(timeout=self.settings.grab_timeout_s)
        det = plan.cell.board.detect(image)
        if not det.ok:
            raise UnprocessableError(
                f"The board is not in view at the robot's current pose ({det.reason}); move "
                "the robot so the camera sees the board, then validate again.",
                code="board_not_visible")
        P = matrix_from_ur_pose(tcp_pose)
        C, rms_px = plan.observe(det, P)
        truth = self._ground_truth(robot, plan)
        report = run_dot_hit(
            robot, plan.points, BoardEstimate(plan.cell.setup, plan.cell.hand_eye,
                                              observation=(P, C)),
            Probe(plan.probe), CellChecks(workspace_check=self.motion.check_workspace,
                                          ground_truth=None if truth is None else truth[0]))
        return {"kind": "dot_hit", "probe": ur_pose_from_matrix(plan.probe).tolist(),
                "observation": {"tcp_pose": [float(v) for v in tcp_pose],
                                "cam_T_target": ur_pose_from_matrix(C).tolist(),
                                "rms_px": rms_px},
                "ground_truth": None if truth is None else truth[1],
                **report.to_json()}

    @staticmethod
    def _ground_truth(robot: Robot, plan: DotHitPlan) -> tuple[GroundTruth, str] | None:
        """The cell's truth if the robot knows it (``GroundTruthSource``, a simulated cell):
        the true board and the robot's true pose, and where the truth comes from.

        The points are given on the calibration's (κ, ν-scaled) grid; the scale to the true
        grid is folded into ``board_pose`` so each point maps to its true corner.
        """
        if not isinstance(robot, GroundTruthSource):
            return None
        board, cell = robot.true_board(), plan.cell
        s = board.square_size_m / (cell.board.square_size * cell.kappa)
        scale = np.diag([s * board.nu / cell.nu, s, 1.0, 1.0])
        return GroundTruth(board_pose=board.T_base_target @ scale,
                           tcp_pose=robot.true_tcp_pose), board.source


@dataclass(frozen=True)
class DotHitPlan:
    """A checked dot-hit request with the calibration it tests (arrays in metres)."""

    cell: StoredCell
    probe: np.ndarray  # shape (4, 4), T_tcp_probe
    points: dict[str, np.ndarray]  # id -> shape (3,), (κ, ν-scaled) target frame

    def observe(self, det: Detection, T_base_tcp: np.ndarray) -> tuple[np.ndarray, float]:
        """T_cam_target (4, 4) at true scale by PnP on the κ, ν-scaled board, and its RMS (px).

        A symmetric board's origin is taken at the end the calibration predicts
        (``StoredCell.observe``)."""
        assert det.corners is not None
        try:
            view = self.cell.observe(T_base_tcp, det.corners, ids=det.ids,
                                     ambiguous=det.ambiguous)
        except ValueError:
            raise UnprocessableError("PnP failed on the board seen at the robot's current "
                                     "pose.", code="board_not_visible") from None
        return view.C_obs, float(np.sqrt(np.mean(np.sum(view.residuals_px ** 2, axis=1))))


def dot_hit_plan(result: dict[str, Any], target: Target, body: ValidationCreate) -> DotHitPlan:
    """Check a dot-hit request against a result document and the run's board (422 if not)."""
    if result.get("setup") != "eye_in_hand":
        raise UnprocessableError(
            "The dot-hit validation probes the calibration board, which an eye-to-hand cell "
            "carries on the tool; it is available for eye-in-hand calibrations only.",
            code="unsupported_setup")
    cell = stored_cell(result, target, use="The dot-hit validation")
    try:
        probe = check_ur_poses(np.asarray(body.probe, dtype=float), "probe")[0]
    except ValueError as exc:
        raise UnprocessableError(str(exc), code="invalid_probe") from None
    if np.linalg.norm(probe[:3, 3]) > 1.0:
        raise UnprocessableError(f"probe: the tip is {np.linalg.norm(probe[:3, 3]):.3g} m from "
                                 "the TCP, more than 1 m: give metres.", code="invalid_probe")
    points = probe_points(cell.board, kappa=cell.kappa, nu=cell.nu)
    if body.points is not None:
        unknown = [p for p in body.points if p not in points]
        if unknown:
            raise UnprocessableError(f"points: unknown id {unknown[0]!r}; choose from "
                                     f"{', '.join(points)}.", code="unknown_point")
        points = {p: points[p] for p in dict.fromkeys(body.points)}
    return DotHitPlan(cell=cell, probe=probe, points=points)
