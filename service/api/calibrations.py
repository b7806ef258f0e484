"""Calibrations: solve over a run's captured stations in a worker process, read the result,
export it in the format a user's stack wants."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response, status
from fastapi.responses import FileResponse, HTMLResponse, StreamingResponse

from calib import parse_result
from drivers.base import RobotIdentity
from service.api.deps import (
    CalibrationsDep,
    EventsDep,
    SessionDep,
    SettingsDep,
    writable_storage,
)
from service.api.finished import calibration_view
from service.api.reads import Read, add_reads
from service.api.routing import OneThreadRoute
from service.api.streams import LastEventId, event_stream, stream_doc
from service.errors import ConflictError, UnprocessableError
from service.exports import ExportNames, export
from service.results.identity import ReportIdentity
from service.results.report_cache import ReportJob
from service.schemas import CalibrationCreate, CalibrationPublic, Created, ExportQuery
from service.stationsets.format import captured_set_sha256
from service.store import queries
from service.store.records import Topic
from service.store.stations import captured_station_set

router = APIRouter(tags=["calibrations"], route_class=OneThreadRoute)


@router.post("/runs/{run_id}/calibrations", status_code=status.HTTP_202_ACCEPTED,
             dependencies=[Depends(writable_storage)], responses={
    409: {"description": "the run is still capturing"},
    422: {"description": "malformed options or too few captured stations"},
    429: {"description": "max_queued_calibrations solves are already queued or running"}})
def create_calibration(run_id: str, calibrations: CalibrationsDep,
                       body: CalibrationCreate | None = None) -> Created:
    """Start computing intrinsics, κ / ν and the hand-eye; poll ``GET /calibrations/{id}``."""
    body = body or CalibrationCreate()
    return Created(id=calibrations.start(run_id, body.options).id)


add_reads(router, CalibrationPublic,
          listing=Read("/runs/{run_id}/calibrations", queries.list_calibrations,
                       "list_calibrations", "The run's calibrations, oldest first."),
          item=Read("/calibrations/{cal_id}", calibration_view, "get_calibration",
                    "State (``running``, ``done``, ``failed``) and the ``cellcal/result@1`` "
                    "document."))


@router.get("/calibrations/{cal_id}/events", response_class=StreamingResponse,
            responses=stream_doc("`state` (first, and the final `done` or `failed`) and "
                                 "`progress` (the stage: detecting station k of N, "
                                 "intrinsics, hand-eye, ...)"))
async def calibration_events(cal_id: str, events: EventsDep,
                             last_event_id: LastEventId = None) -> StreamingResponse:
    """Progress of a calibration as server-sent events, resumable with ``Last-Event-ID``."""
    return await event_stream(events, Topic("calibration", cal_id), last_event_id)


@router.get("/calibrations/{cal_id}/export", response_class=Response, responses={
    200: {"content": {"application/json": {}, "application/yaml": {}, "application/xml": {},
                      "text/plain": {}, "text/x-python": {}},
          "description": "the file, named in Content-Disposition"},
    409: {"description": "the calibration is running or failed"},
    422: {"description": "unknown format, bad frame names, or a format the result lacks the "
                         "data for (camera model or hand-eye)"}})
def export_calibration(cal_id: str, session: SessionDep,
                       query: Annotated[ExportQuery, Query()]) -> Response:
    """The result as a file for OpenCV, ROS (camera_info, ROS 2 static transform launch file),
    a URDF or a UR robot program."""
    cal = queries.get_calibration(session, cal_id=cal_id)
    if cal.state != "done" or cal.result is None:
        raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished calibration "
                            "can be exported.", code="invalid_state")
    try:
        names = ExportNames(camera_name=query.camera_name, parent_frame=query.parent_frame,
                            child_frame=query.child_frame)
        content, media_type, filename = export(parse_result(cal.result), query.format, names)
    except ValueError as exc:
        raise UnprocessableError(str(exc), code="export_unavailable") from None
    return Response(content, media_type=media_type,
                    headers={"Content-Disposition": f'attachment; filename="{filename}"'})


@router.get("/calibrations/{cal_id}/report", response_class=HTMLResponse, responses={
    200: {"content": {"text/html": {}},
          "description": "one self-contained HTML page (plots embedded, no external links)"},
    409: {"description": "the calibration is running or failed"},
    503: {"description": "the page is still being rendered (`report_rendering`): ask again "
                         "after `Retry-After` seconds",
          "headers": {"Retry-After": {"description": "seconds to wait",
                                      "schema": {"type": "integer"}}}}})
def calibration_report(cal_id: str, session: SessionDep, settings: SettingsDep,
                       calibrations: CalibrationsDep) -> Response:
    """The report a person reads, prints and files: verdict, findings, plots, stations.
    Rendered once, in a worker process, then served from the data directory."""
    cal = queries.get_calibration(session, cal_id=cal_id)
    if cal.state != "done" or cal.result is None:
        raise ConflictError(f"Calibration {cal_id} is {cal.state}; only a finished calibration "
                            "has a report.", code="invalid_state")

    def job() -> ReportJob:  # only when the page must be rendered
        rows = queries.list_stations(session, run_id=cal.run_id)
        images = {f"{row.index:03d}": str(Path(settings.data_dir) / row.image_path)
                  for row in rows if row.image_path}
        run = queries.get_run(session, run_id=cal.run_id)
        captured = captured_station_set(session, run_id=cal.run_id)
        robot = RobotIdentity(**run.robot_identity or {})
        identity = ReportIdentity(
            cell=run.cell, robot=run.robot, camera=settings.camera, robot_model=robot.model,
            robot_serial=robot.serial, controller_version=robot.controller_version,
            board=json.dumps(run.target, sort_keys=True),
            stations=f"{len(rows)} of run {run.id}",
            input_sha256=captured_set_sha256(captured, source=settings.data_dir))
        return ReportJob(parse_result(cal.result), images, identity)

    try:
        page = calibrations.reports.page(cal_id, job)
    except ValueError as exc:  # a stored result edited by hand
        raise UnprocessableError(str(exc), code="invalid_result") from None
    if isinstance(page, Path):
        return FileResponse(page, media_type="text/html; charset=utf-8")
    return HTMLResponse(page)
