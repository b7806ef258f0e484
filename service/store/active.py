"""The calibration registry: which calibration is a cell's current one for a setup, since
when, and what was current before.

Activations are rows (``models.Activation``); ``models.ActiveCalibration`` names the current
one per cell and setup, changed in the same transaction, so the history is never rewritten,
only appended to, and many services on one database agree on what is current.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.errors import ConflictError, NotFoundError
from service.schemas import ActivationPublic
from service.store import queries, writes
from service.store.records import ActivationRecord


def activate(s: Session, *, cal_id: str) -> tuple[str, str]:
    """Make a finished calibration the current one of its cell and setup; the cell and
    setup. Activating the current calibration again changes nothing (idempotent)."""
    cal = queries.get_calibration(s, cal_id=cal_id)
    if cal.state != "done" or cal.result is None:
        raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished calibration "
                            "can be activated.", code="invalid_state")
    run = queries.get_run(s, run_id=cal.run_id)
    writes.activate(s, cal_id=cal_id, cell=cal.cell, setup=run.setup, robot=run.robot)
    return cal.cell, run.setup


def current(s: Session, *, cell: str, setup: str,
            history: int) -> tuple[ActivationRecord, list[ActivationPublic]]:
    """The cell's current activation for ``setup`` and its last ``history`` periods, newest
    first (404 ``no_active_calibration`` if none was ever activated)."""
    rows = queries.activations(s, cell=cell, setup=setup, limit=history)
    if not rows:
        raise NotFoundError(f"No {setup} calibration was activated for cell {cell}; activate "
                            "one with POST /calibrations/{id}/activate.",
                            code="no_active_calibration")
    until = [None, *(row.activated_at for row in rows[:-1])]
    return rows[0], [ActivationPublic(calibration_id=row.calibration_id,
                                      active_from=row.activated_at, active_until=end)
                     for row, end in zip(rows, until, strict=True)]
