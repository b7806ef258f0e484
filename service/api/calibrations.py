"""Calibrations: solve over a run's captured stations in a worker process, read the result."""

from __future__ import annotations

from fastapi import APIRouter, status
from sqlalchemy import select

from service.api.deps import JobsDep, SessionDep
from service.api.runs import load_run
from service.jobs import NotFoundError
from service.models import Calibration
from service.schemas import CalibrationCreate, CalibrationPublic, Created

router = APIRouter(tags=["calibrations"])


def calibration_public(cal: Calibration) -> CalibrationPublic:
    return CalibrationPublic(id=cal.id, run_id=cal.run_id, state=cal.state, options=cal.options,
                             result=cal.result, error=cal.error, created_at=cal.created_at,
                             finished_at=cal.finished_at)


@router.post("/runs/{run_id}/calibrations", status_code=status.HTTP_202_ACCEPTED, responses={
    409: {"description": "the run is still capturing"},
    422: {"description": "malformed options or too few captured stations"}})
def create_calibration(run_id: str, jobs: JobsDep,
                       body: CalibrationCreate | None = None) -> Created:
    """Start computing intrinsics, κ / ν and the hand-eye; poll ``GET /calibrations/{id}``."""
    body = body or CalibrationCreate()
    return Created(id=jobs.start_calibration(run_id, body.options).id)


@router.get("/runs/{run_id}/calibrations")
def list_calibrations(run_id: str, session: SessionDep) -> list[CalibrationPublic]:
    """The run's calibrations, oldest first."""
    load_run(session, run_id)
    cals = session.scalars(select(Calibration).where(Calibration.run_id == run_id)
                           .order_by(Calibration.created_at))
    return [calibration_public(c) for c in cals]


@router.get("/calibrations/{cal_id}")
def get_calibration(cal_id: str, session: SessionDep) -> CalibrationPublic:
    """State (``running``, ``done``, ``failed``) and the ``cellcal/result@1`` document."""
    cal = session.get(Calibration, cal_id)
    if cal is None:
        raise NotFoundError(f"No calibration {cal_id}.")
    return calibration_public(cal)
