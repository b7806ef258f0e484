"""Capture runs: create (and start), list, read, pause / resume / cancel, live events."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request, Response, status
from fastapi.responses import FileResponse, StreamingResponse
from sqlalchemy import Row
from starlette.background import BackgroundTask

from service.api.deps import EventsDep, RunsDep, SessionDep, SettingsDep
from service.api.routing import OneThreadRoute
from service.api.streams import LastEventId, event_stream, stream_doc
from service.errors import ConflictError, NotFoundError
from service.schemas import (
    ColdStartPublic,
    Created,
    ErrorInfo,
    RunCreate,
    RunPublic,
    StationError,
)
from service.stationsets.format import zip_station_set
from service.store import queries
from service.store.pages import Cursor
from service.store.records import Topic
from service.store.stations import captured_station_set, run_target

router = APIRouter(prefix="/runs", tags=["runs"], route_class=OneThreadRoute)

def run_public(session: SessionDep, run_id: str) -> RunPublic:
    """The public view of a run (404 for an unknown id): one small statement (two if a station
    has an error), never loading its stations (with their corners), so polling stays fast on
    long runs."""
    return runs_public(session, [queries.get_run_view(session, run_id=run_id)])[0]


def runs_public(session: SessionDep, runs: list[Row[Any]]) -> list[RunPublic]:
    """The public views of runs read as ``queries.RUN_VIEW_COLUMNS`` rows, with one more
    statement for their stations' errors if any has some, whatever their number (on
    PostgreSQL each statement is a wait for the database server and then for the GIL)."""
    with_errors = [run.id for run in runs if run.errors]
    errors = queries.runs_station_errors(session, run_ids=with_errors) if with_errors else {}
    return [RunPublic(
        id=run.id, state=run.state, mode=run.mode, cell=run.cell, robot=run.robot,
        setup=run.setup, target=run_target(run),
        stations_planned=queries.planned_stations(run.poses, run.cold_start),
        stations_captured=run.captured, stations_skipped=run.stored - run.captured,
        error=None if run.error is None else ErrorInfo(code=run.error_code or "error",
                                                       detail=run.error),
        station_errors=[StationError(index=i, code=code, detail=detail)
                        for i, code, detail in errors.get(run.id, ())],
        cold_start=None if run.cold_start is None else ColdStartPublic.model_validate(
            run.cold_start),
        created_at=run.created_at, updated_at=run.updated_at) for run in runs]


@router.post("", status_code=status.HTTP_201_CREATED, responses={
    409: {"description": "the robot already has an active run"},
    422: {"description": "malformed body, pose outside the workspace, no planning"}})
def create_run(body: Annotated[RunCreate, Body(openapi_examples=RunCreate.EXAMPLES)],
               runs: RunsDep) -> Created:
    """Create a capture run and start capturing in the background."""
    return Created(id=runs.create(body).id)


@router.get("")
def list_runs(session: SessionDep, request: Request, response: Response,
              limit: Annotated[int, Query(ge=1, le=500)] = 50,
              cursor: Annotated[str | None, Query(
                  max_length=100, description="the next page: the cursor of the `Link: <...>; "
                                              "rel=\"next\"` header of the page before")] = None
              ) -> list[RunPublic]:
    """Runs, newest first; a full page's ``Link`` header names the next page (keyset)."""
    runs = queries.list_run_views(session, limit=limit,
                                  cursor=None if cursor is None else Cursor.decode(cursor))
    if len(runs) == limit:
        after = request.url.include_query_params(cursor=Cursor.of(runs[-1]).encode())
        response.headers["Link"] = f'<{after.path}?{after.query}>; rel="next"'
    return runs_public(session, runs)


@router.get("/{run_id}")
def get_run(run_id: str, session: SessionDep) -> RunPublic:
    """State, stations captured / skipped / planned, and errors."""
    return run_public(session, run_id)


@router.post("/{run_id}/pause")
def pause_run(run_id: str, runs: RunsDep, session: SessionDep) -> RunPublic:
    """Stop after the station in progress (idempotent)."""
    runs.pause(run_id)
    return run_public(session, run_id)


@router.post("/{run_id}/resume")
def resume_run(run_id: str, runs: RunsDep, session: SessionDep) -> RunPublic:
    """Continue a paused, interrupted or failed run at its next missing station."""
    runs.resume(run_id)
    return run_public(session, run_id)


@router.post("/{run_id}/cancel")
def cancel_run(run_id: str, runs: RunsDep, session: SessionDep) -> RunPublic:
    """Stop for good (idempotent); stored stations stay available."""
    runs.cancel(run_id)
    return run_public(session, run_id)


@router.post("/{run_id}/finish", responses={
    409: {"description": "a robot-mode run, or a run that is cancelled or failed"}})
def finish_run(run_id: str, runs: RunsDep, session: SessionDep) -> RunPublic:
    """End an external run (idempotent): no more stations; calibrate it next."""
    runs.finish(run_id)
    return run_public(session, run_id)


@router.get("/{run_id}/events", response_class=StreamingResponse, responses=stream_doc(
    "`state` (first, then on every change) and `station` (captured or skipped)"))
async def run_events(run_id: str, events: EventsDep,
                     last_event_id: LastEventId = None) -> StreamingResponse:
    """Progress of a run as server-sent events; ids are stable, so a client that reconnects
    with ``Last-Event-ID`` (browsers do) misses none and sees none twice."""
    return await event_stream(events, Topic("run", run_id), last_event_id)


@router.get("/{run_id}/stationset", response_class=FileResponse, responses={
    200: {"content": {"application/zip": {}},
          "description": "stations.json and the PNGs: unzip and run cellcal calibrate on it"},
    404: {"description": "no such run, no captured station, or an image file is missing"},
    409: {"description": "the run is still capturing"}})
def get_station_set(run_id: str, session: SessionDep, settings: SettingsDep) -> FileResponse:
    """The run's captured stations as a station set (``cellcal/stations@1``, images included,
    zipped): ``cellcal calibrate`` on it solves what ``POST /runs/{id}/calibrations`` solves."""
    if queries.get_run(session, run_id=run_id).state == "capturing":
        raise ConflictError(f"Run {run_id} is still capturing; pause it or wait until it is "
                            "done.", code="invalid_state")
    stations = captured_station_set(session, run_id=run_id)
    if not stations.stations:
        raise NotFoundError(f"Run {run_id} has no captured station.")
    missing = [st.id for st in stations.stations
               if not (settings.data_dir / str(st.image)).is_file()]
    if missing:
        raise NotFoundError(f"The image of station {missing[0]} of run {run_id} is missing "
                            "from the data directory.")
    tmp = Path(tempfile.mkdtemp(prefix="stationset-", dir=settings.data_dir))
    path = zip_station_set(tmp / f"run-{run_id}-stations.zip", stations,
                           source=settings.data_dir)
    return FileResponse(path, media_type="application/zip", filename=path.name,
                        background=BackgroundTask(shutil.rmtree, tmp, ignore_errors=True))
