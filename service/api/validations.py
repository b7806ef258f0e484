"""Validations of a calibration on the run's robot: the dot-hit run (SM eq. 24) and the
re-check (has the camera mount moved?)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from fastapi import APIRouter, Depends, status
from fastapi.responses import StreamingResponse

from service.api.deps import EventsDep, ValidationsDep, writable_storage
from service.api.reads import Read, add_reads
from service.api.routing import OneThreadRoute
from service.api.streams import LastEventId, event_stream, stream_doc
from service.schemas import CheckCreate, Created, ValidationCreate, ValidationPublic
from service.store import queries
from service.store.records import Topic

router = APIRouter(tags=["validations"], route_class=OneThreadRoute)
F = TypeVar("F", bound=Callable[..., Created])


def starts_validation(path: str, unprocessable: str) -> Callable[[F], F]:
    """The route of a request that starts a validation: 202, 409 when the calibration is not
    done or the robot is busy, 422 when ``unprocessable``."""
    busy = "the calibration is not done, or the robot is busy (an active run or another " \
           "validation)"
    return router.post(path, status_code=status.HTTP_202_ACCEPTED,
                       dependencies=[Depends(writable_storage)],
                       responses={409: {"description": busy},
                                  422: {"description": unprocessable}})


@starts_validation("/calibrations/{cal_id}/validations",
                   "malformed probe, unknown point id, or a calibration the dot-hit run "
                   "cannot test (eye-to-hand)")
def create_validation(cal_id: str, validations: ValidationsDep,
                      body: ValidationCreate | None = None) -> Created:
    """Touch board points with a probe; poll ``GET /validations/{id}``.

    The robot first looks at the board from where it stands (the board must be in view), so
    the points are reconstructed through the calibration (eq. 24); every commanded pose is
    checked against the workspace limits before the robot moves.
    """
    return Created(id=validations.start(cal_id, body or ValidationCreate()).id)


@starts_validation("/calibrations/{cal_id}/checks",
                   "malformed poses, more stations than the run captured, or a result "
                   "without camera model or cross-validation")
def create_check(cal_id: str, validations: ValidationsDep,
                 body: CheckCreate | None = None) -> Created:
    """Has the cell changed since the calibration? Poll ``GET /validations/{id}``.

    The robot revisits ``stations`` of the calibration's run (default 5, spread over its
    captured stations) or the given ``poses``; at each the board is detected and compared with
    the calibration's prediction from the robot pose. The report's ``state`` is ``degraded``
    when the camera pose seen differs from the predicted one consistently (a moved mount) by
    more than twice the calibration's cross-validated error, else ``ok``; each station has its
    corner error and its own ``ok | degraded``.
    """
    return Created(id=validations.start_check(cal_id, body or CheckCreate()).id)


add_reads(router, ValidationPublic,
          listing=Read("/calibrations/{cal_id}/validations", queries.list_validations,
                       "list_validations", "The calibration's validations, oldest first."),
          item=Read("/validations/{val_id}", queries.get_validation, "get_validation",
                    "State (``running``, ``done``, ``failed``) and the report."))


@router.get("/validations/{val_id}/events", response_class=StreamingResponse,
            responses=stream_doc("`state` (first, and the final `done` or `failed`) and, for a "
                                 "re-check, `progress` (station k of N and how it compared)"))
async def validation_events(val_id: str, events: EventsDep,
                            last_event_id: LastEventId = None) -> StreamingResponse:
    """Progress of a validation (re-check or dot-hit run) as server-sent events, resumable
    with ``Last-Event-ID``."""
    return await event_stream(events, Topic("validation", val_id), last_event_id)
