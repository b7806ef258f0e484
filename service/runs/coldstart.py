"""A run planned station by station from a cold start (issue 17).

The run knows the board, the setup, the workspace box and that the robot was jogged so that the
camera sees the board; guesses of the hand-eye and the focal length are optional priors. Its
capture thread asks ``calib.explorer.ColdStart`` for each next pose (small exploratory moves
first, then the station that most reduces the predicted uncertainty), checks it against the
box (the tcp, and eye-in-hand the camera under the current estimate) before the robot moves,
captures and detects it as any station, and tells the planner what it saw. A view where the
board was lost is stored with its reason (a skipped station) and informs the next choice.

It stops at its station count (``stations``), or for a tolerance run when the 90 % bound on the
hand-eye's error (``calib.COVERAGE_90`` times its honest 1-σ: what a calibration of the stations
so far reports, ``calib.calibrate`` with its jackknife floor) is within tolerance in
rotation and translation, or at ``max_stations``, or when no feasible view remains. (A stop at
σ <= tolerance would leave the true error beyond the tolerance in about half the runs.) The
run's ``cold_start`` column holds the rule, the progress and the σ history with the bound; each
σ is also a ``sigma`` event. Stations already stored are replayed into
the planner on ``resume``, so a paused or interrupted run continues where it was.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from calib import (
    COVERAGE_90,
    ColdStart,
    ColdStartScene,
    Guess,
    Proposal,
    Station,
    Stations,
    View,
    board_from_target,
    calibrate,
    camera_position,
    hand_eye_rss,
    hand_eye_sigma,
    matrix_from_ur_pose,
    ur_pose_from_matrix,
)
from drivers.errors import WorkspaceError
from service.runs.capture import ATTEMPTS, STORED, Capture
from service.store import queries, writes
from service.store.records import RunRecord
from service.store.stations import run_target, station_of

log = logging.getLogger("cellcal.service")

#: Good stations before the honest σ (a whole calibration with its cross-validation) is
#: computed after each station; before, the history holds the planner's formal estimate.
MIN_HONEST_STATIONS = 8
#: Tolerance the plan aims at when a run gives a station count instead (deg, mm).
DEFAULT_AIM = (0.05, 0.5)
#: Exploratory moves go at this fraction of the configured speed.
EXPLORE_SPEED = 0.5


class ColdStartCapture(Capture):
    """The capture thread of a cold-start run (module docstring)."""

    def _capture_owned(self) -> None:
        self._open_devices()
        read = self._in_session(self._read, f"reading run {self.run_id}")
        if read is None:
            return
        plan, stored = read
        planner = self._planner(plan)
        good = self._replay(planner, stored)
        reason = self._loop(planner, plan, good, next_index=len(stored))
        if self.motion.stopping.is_set():
            self.finish("interrupted", writes.INTERRUPTED, "interrupted")
        elif reason is not None:
            self._update(stop_reason=reason)
            if not good:
                self.finish("failed", "No station was captured: see the station errors.",
                            "nothing_captured")
            else:
                self.finish("done")

    # ---- the run as stored ------------------------------------------------------------------

    def _read(self, s: Session) -> tuple[dict[str, Any], list[tuple[Any, Station]]] | None:
        """The plan and the stored stations (index order), or None if the run is not ours."""
        run = s.get(RunRecord, self.run_id)
        if run is None or run.owner != self.token or run.state != "capturing":
            return None
        self.target = run_target(run)
        self.board = board_from_target(self.target)
        self.setup = run.setup
        rows = queries.list_stations(s, run_id=self.run_id)
        return dict(run.cold_start or {}), [(row.commanded_tcp_pose, station_of(row))
                                         for row in rows]

    def _update(self, **values: Any) -> None:
        """Merge ``values`` into the run's ``cold_start`` record (while the run is ours)."""
        def write(s: Session) -> None:
            if not writes.claim_run(s, run_id=self.run_id, token=self.token):
                return
            run = s.get(RunRecord, self.run_id)
            assert run is not None
            run.cold_start = {**(run.cold_start or {}), **values}
            s.commit()

        self._in_session(write, f"updating run {self.run_id}")

    def _append_pose(self, pose: list[float]) -> None:
        """Record a commanded pose in the run's poses before the robot goes there."""
        def write(s: Session) -> None:
            if writes.claim_run(s, run_id=self.run_id, token=self.token):
                run = s.get(RunRecord, self.run_id)
                assert run is not None
                run.poses = [*run.poses, pose]
                s.commit()

        self._in_session(write, f"recording a pose of run {self.run_id}")

    # ---- the planner ------------------------------------------------------------------------

    def _planner(self, plan: dict[str, Any]) -> ColdStart:
        """The planner of this run, with the configured guesses as priors."""
        rule = plan.get("stop_rule")
        aim_deg, aim_mm = ((rule["tolerance_deg"], rule["tolerance_mm"]) if rule
                           else DEFAULT_AIM)
        lo, hi = (np.asarray(b, dtype=float) for b in self.settings.workspace())
        assert self.board is not None
        scene = ColdStartScene(self.board, self.setup, tuple(plan["image_size"]), (lo, hi),
                      (np.deg2rad(aim_deg), aim_mm * 1e-3))
        hints = self.settings.cell_hints()
        focal = self.settings.focal_px_guess or (None if hints.K is None
                                                 else float(hints.K[0, 0]))
        guess = Guess(hand_eye=hints.hand_eye, focal_px=focal)
        return ColdStart(scene, matrix_from_ur_pose(np.asarray(plan["start_pose"])),
                         guess=guess, seed=int(plan.get("seed", 0)))

    def _replay(self, planner: ColdStart, stored: list[tuple[Any, Station]]) -> list[Station]:
        """Tell the planner about the stations stored before (a resumed run); the good ones."""
        good = []
        for pose, station in stored:
            planner.propose()
            view = _view(station)
            planner.record(matrix_from_ur_pose(np.asarray(pose)), view, station.rejected)
            if view is not None:
                good.append(station)
        return good

    # ---- the loop ---------------------------------------------------------------------------

    def _loop(self, planner: ColdStart, plan: dict[str, Any], good: list[Station], *,
              next_index: int) -> str | None:
        """Visit proposed poses until the stop rule holds; the stop reason, or None if the
        run stopped being ours (or the service stops)."""
        rule = plan.get("stop_rule")
        limit = int(plan["stations"] or rule["max_stations"])
        index = next_index
        while True:
            if len(good) >= limit:
                return "max_stations"
            if index >= 2 * limit + 8:  # far more lost views than stations: give up
                return "no_feasible_view"
            if index >= self.settings.max_stations:  # the service's limit on a run's stations
                return "max_stations"
            if self.motion.stopping.is_set() or not self._owns():
                return None
            proposal = planner.propose()
            if proposal is None:
                return "no_feasible_view"
            station = self._visit(planner, proposal, index)
            if station is None:
                return None
            index += 1
            if station.rejected is None:
                good.append(station)
            self._update(exploratory_moves=planner.log.explore_moves,
                         notes=list(dict.fromkeys(planner.notes)))
            if station.rejected is None and rule is not None and self._sigma(
                    planner, good, rule):
                return "tolerance_met"

    def _visit(self, planner: ColdStart, proposal: Proposal, index: int) -> Station | None:
        """Check, move, capture, detect and store one proposed pose; tell the planner. The
        stored station, or None if the run is no longer ours."""
        self._check_safe(planner, proposal.T_base_tcp)
        pose = ur_pose_from_matrix(proposal.T_base_tcp).tolist()
        self._append_pose(pose)
        options = self.options
        if proposal.kind == "explore":
            self.options = replace(options, speed=EXPLORE_SPEED * options.speed)
        try:
            shot = self._shoot(index, pose, ATTEMPTS)
        finally:
            self.options = options
        if shot is None:
            return None
        self.developed = None
        if self._develop(shot) != STORED or self.developed is None:
            return None
        station = self.developed
        planner.record(proposal.T_base_tcp, _view(station), station.rejected)
        return station

    def _check_safe(self, planner: ColdStart, T_base_tcp: np.ndarray) -> None:
        """Refuse a pose whose tcp, or eye-in-hand camera (under the current estimate), lies
        outside the workspace box: ``WorkspaceError``, the robot is not moved."""
        self.motion.check_workspace(ur_pose_from_matrix(T_base_tcp))
        if self.setup != "eye_in_hand" or planner.estimate is None:
            return
        camera = camera_position(T_base_tcp, planner.estimate.cell.hand_eye, self.setup)
        if (outside := self.motion.outside_workspace([*camera, 0.0, 0.0, 0.0])) is not None:
            raise WorkspaceError(f"The camera would be outside the box there: {outside}; the "
                                 "robot was not moved.")

    def _sigma(self, planner: ColdStart, good: list[Station], rule: dict[str, Any]) -> bool:
        """Record the hand-eye's σ and its 90 % bound after a good station; True when the
        bound (from an honest σ) is within the tolerance."""
        point = None
        if len(good) >= MIN_HONEST_STATIONS:
            point = self._honest_sigma(good)
        if point is None and planner.estimate is not None:
            rot, trans = hand_eye_sigma(planner.estimate.covariance)
            point = {"stations": len(good), "rot_deg": float(np.degrees(rot)),
                     "trans_mm": trans * 1e3, "kind": "estimate"}
        if point is None:
            return False
        k = rule.get("coverage_factor", COVERAGE_90)
        point |= {"bound_rot_deg": k * point["rot_deg"], "bound_trans_mm": k * point["trans_mm"]}
        history = [*self._history(), point]
        self._update(sigma_history=history)
        self._publish({"type": "sigma", "run_id": self.run_id, **point,
                       "tolerance_deg": rule["tolerance_deg"],
                       "tolerance_mm": rule["tolerance_mm"],
                       "message": f"σ {point['rot_deg']:.3f}° / {point['trans_mm']:.2f} mm, "
                                  f"90 % bound {point['bound_rot_deg']:.3f}° / "
                                  f"{point['bound_trans_mm']:.2f} mm ({point['kind']}; "
                                  f"tolerance {rule['tolerance_deg']:g}° / "
                                  f"{rule['tolerance_mm']:g} mm)"})
        return (point["kind"] == "honest" and point["bound_rot_deg"] <= rule["tolerance_deg"]
                and point["bound_trans_mm"] <= rule["tolerance_mm"])

    def _history(self) -> list[dict[str, Any]]:
        return self._in_session(
            lambda s: list((queries.get_run(s, run_id=self.run_id).cold_start or {})
                           .get("sigma_history", [])), "reading the σ history")

    def _honest_sigma(self, good: list[Station]) -> dict[str, Any] | None:
        """The hand-eye σ a calibration of the good stations reports (root-sum-square over
        the axes), or None when they cannot be calibrated yet."""
        try:
            result = calibrate(Stations(self.setup, tuple(good), self.target),
                               self.settings.cold_start_solver())
        except ValueError as exc:
            log.info("run %s: no honest σ yet after %d stations (%s)", self.run_id, len(good),
                     exc)
            return None
        rot, trans = hand_eye_rss(result.sigmas)
        return {"stations": len(good), "rot_deg": float(np.degrees(rot)),
                "trans_mm": trans * 1e3, "kind": "honest"}


def _view(station: Station) -> View | None:
    """The planner's view of a stored station: the reading and corners, None if lost."""
    det = station.detection
    if station.rejected is not None or det is None or not det.ok or station.T_base_tcp is None:
        return None
    return View(matrix_from_ur_pose(np.asarray(station.T_base_tcp)), det.corners, det.ids)
