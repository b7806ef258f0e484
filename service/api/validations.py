"""Validations of a calibration: the dot-hit run (SM eq. 24) on the run's robot."""

from __future__ import annotations

from fastapi import APIRouter, status
from sqlalchemy import select

from service.api.calibrations import load_calibration
from service.api.deps import JobsDep, SessionDep
from service.jobs import NotFoundError
from service.models import Validation
from service.schemas import Created, ValidationCreate, ValidationPublic

router = APIRouter(tags=["validations"])


def validation_public(val: Validation) -> ValidationPublic:
    return ValidationPublic(id=val.id, calibration_id=val.calibration_id, kind=val.kind,
                            state=val.state, result=val.result, error=val.error,
                            created_at=val.created_at, finished_at=val.finished_at)


@router.post("/calibrations/{cal_id}/validations", status_code=status.HTTP_202_ACCEPTED,
             responses={
                 409: {"description": "the calibration is not done, or the robot is busy "
                                      "(an active run or another validation)"},
                 422: {"description": "malformed probe, unknown point id, or a calibration "
                                      "the dot-hit run cannot test (eye-to-hand)"}})
def create_validation(cal_id: str, jobs: JobsDep,
                      body: ValidationCreate | None = None) -> Created:
    """Touch board points with a probe; poll ``GET /validations/{id}``.

    The robot first looks at the board from where it stands (the board must be in view), so
    the points are reconstructed through the calibration (eq. 24); every commanded pose is
    checked against the workspace limits before the robot moves.
    """
    return Created(id=jobs.start_validation(cal_id, body or ValidationCreate()).id)


@router.get("/calibrations/{cal_id}/validations")
def list_validations(cal_id: str, session: SessionDep) -> list[ValidationPublic]:
    """The calibration's validations, oldest first."""
    load_calibration(session, cal_id)
    vals = session.scalars(select(Validation).where(Validation.calibration_id == cal_id)
                           .order_by(Validation.created_at))
    return [validation_public(v) for v in vals]


@router.get("/validations/{val_id}")
def get_validation(val_id: str, session: SessionDep) -> ValidationPublic:
    """State (``running``, ``done``, ``failed``) and the report."""
    val = session.get(Validation, val_id)
    if val is None:
        raise NotFoundError(f"No validation {val_id}.")
    return validation_public(val)
