"""Calibrations: solve over a run's captured stations in a worker process, read the result,
export it in the format a user's stack wants."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status
from sqlalchemy import select

from service.api.deps import JobsDep, SessionDep
from service.api.runs import load_run
from service.exports import export
from service.jobs import ConflictError, NotFoundError, UnprocessableError
from service.models import Calibration
from service.schemas import CalibrationCreate, CalibrationPublic, Created, ExportFormat

router = APIRouter(tags=["calibrations"])


def calibration_public(cal: Calibration) -> CalibrationPublic:
    return CalibrationPublic(id=cal.id, run_id=cal.run_id, state=cal.state, options=cal.options,
                             result=cal.result, error=cal.error, created_at=cal.created_at,
                             finished_at=cal.finished_at)


def load_calibration(session: SessionDep, cal_id: str) -> Calibration:
    cal = session.get(Calibration, cal_id)
    if cal is None:
        raise NotFoundError(f"No calibration {cal_id}.")
    return cal


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
    return calibration_public(load_calibration(session, cal_id))


@router.get("/calibrations/{cal_id}/export", response_class=Response, responses={
    200: {"content": {"application/json": {}, "application/yaml": {}, "application/xml": {},
                      "text/plain": {}},
          "description": "the file, named in Content-Disposition"},
    409: {"description": "the calibration is running or failed"},
    422: {"description": "unknown format, or a camera format of a result without camera"}})
def export_calibration(
        cal_id: str, session: SessionDep,
        fmt: Annotated[ExportFormat, Query(  # type: ignore[valid-type]
            alias="format", description="json (the result document), opencv-yaml "
                                        "(cv::FileStorage), ros-camera-info, urdf (camera "
                                        "joint), ur-pose (hand-eye as p[...])")] = "json",
) -> Response:
    """The result as a file for OpenCV, ROS, a URDF or a UR robot program."""
    cal = load_calibration(session, cal_id)
    if cal.state != "done" or cal.result is None:
        raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished calibration "
                            "can be exported.", code="invalid_state")
    try:
        content, media_type, filename = export(cal.result, fmt)
    except ValueError as exc:
        raise UnprocessableError(str(exc), code="export_unavailable") from None
    return Response(content, media_type=media_type,
                    headers={"Content-Disposition": f'attachment; filename="{filename}"'})
