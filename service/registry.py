"""The calibration registry: which calibration is a robot cell's current one, since when, and
what was current before.

Activations are rows (``models.Activation``); the newest one of a robot is its current
calibration, so the history is never rewritten, only appended to.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from service import store
from service.errors import ConflictError, NotFoundError
from service.models import Activation
from service.schemas import ActivationPublic


def activate(s: Session, *, cal_id: str) -> str:
    """Make a finished calibration its run's robot's current one; the robot. Activating the
    current calibration again changes nothing (idempotent)."""
    cal = store.get_calibration(s, cal_id=cal_id)
    if cal.state != "done" or cal.result is None:
        raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished calibration "
                            "can be activated.", code="invalid_state")
    robot = store.get_run(s, run_id=cal.run_id).robot
    current = store.activations(s, robot=robot, limit=1)
    if not current or current[0].calibration_id != cal_id:
        store.activate(s, cal_id=cal_id, robot=robot)
    return robot


def current(s: Session, *, robot: str, history: int) -> tuple[Activation,
                                                              list[ActivationPublic]]:
    """The robot's current activation and its last ``history`` periods, newest first
    (404 ``no_active_calibration`` if none was ever activated)."""
    rows = store.activations(s, robot=robot, limit=history)
    if not rows:
        raise NotFoundError(f"No calibration was activated for robot {robot}; activate one "
                            "with POST /calibrations/{id}/activate.",
                            code="no_active_calibration")
    until = [None, *(row.activated_at for row in rows[:-1])]
    return rows[0], [ActivationPublic(calibration_id=row.calibration_id,
                                      active_from=row.activated_at, active_until=end)
                     for row, end in zip(rows, until, strict=True)]
