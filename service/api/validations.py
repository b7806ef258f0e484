"""Validations of a calibration: the dot-hit run (SM eq. 24) on the run's robot."""

from __future__ import annotations

from fastapi import APIRouter, status

from service import store
from service.api.deps import ValidationsDep
from service.api.reads import Read, add_reads
from service.schemas import Created, ValidationCreate, ValidationPublic

router = APIRouter(tags=["validations"])


@router.post("/calibrations/{cal_id}/validations", status_code=status.HTTP_202_ACCEPTED,
             responses={
                 409: {"description": "the calibration is not done, or the robot is busy "
                                      "(an active run or another validation)"},
                 422: {"description": "malformed probe, unknown point id, or a calibration "
                                      "the dot-hit run cannot test (eye-to-hand)"}})
def create_validation(cal_id: str, validations: ValidationsDep,
                      body: ValidationCreate | None = None) -> Created:
    """Touch board points with a probe; poll ``GET /validations/{id}``.

    The robot first looks at the board from where it stands (the board must be in view), so
    the points are reconstructed through the calibration (eq. 24); every commanded pose is
    checked against the workspace limits before the robot moves.
    """
    return Created(id=validations.start(cal_id, body or ValidationCreate()).id)


add_reads(router, ValidationPublic,
          listing=Read("/calibrations/{cal_id}/validations", store.list_validations,
                       "list_validations", "The calibration's validations, oldest first."),
          item=Read("/validations/{val_id}", store.get_validation, "get_validation",
                    "State (``running``, ``done``, ``failed``) and the report."))
