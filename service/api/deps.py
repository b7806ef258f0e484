"""Request dependencies as ``Annotated`` aliases, so tests can swap them with
``app.dependency_overrides``; the app keeps the shared objects in ``app.state``.

They are coroutines that do no I/O, so FastAPI runs them on the event loop instead of handing
each to a worker thread (``service.api.routing`` says why that matters); ``writable_storage``,
which does, is the exception.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from service.api.guard import check_api_key
from service.cell.devices import Devices
from service.events import EventBus
from service.jobs.calibrations import Calibrations
from service.jobs.validations import Validations
from service.runs import RunManager
from service.settings import Settings

_bearer = HTTPBearer(auto_error=False, description="CELLCAL_API_KEY")


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_session(request: Request) -> Session:
    """A session for the request, made on the event loop (it connects on first use). Only
    endpoints of a ``service.api.routing.OneThreadRoute`` take it: the route closes it in its
    worker thread, in the endpoint's own call. A plain coroutine, not a ``yield`` dependency:
    FastAPI enters each of those in the request's exit stack inside a cancel scope, about 5 %
    of a GET's CPU on the event loop (issue 21), only to close what the route closed already;
    a session no endpoint used never connected and holds nothing. A ``GET`` only reads: its
    session runs no transaction (``Database.new_session(read_only=True)``)."""
    return request.app.state.db.new_session(read_only=request.method in ("GET", "HEAD"))


async def get_runs(request: Request) -> RunManager:
    return request.app.state.runtime.runs


async def get_calibrations(request: Request) -> Calibrations:
    return request.app.state.runtime.calibrations


async def get_validations(request: Request) -> Validations:
    return request.app.state.runtime.validations


async def get_events(request: Request) -> EventBus:
    return request.app.state.runtime.events


async def get_devices(request: Request) -> Devices:
    return request.app.state.devices


def writable_storage(request: Request) -> None:
    """503 ``storage_unavailable`` or ``disk_full`` while the data directory takes no writes:
    a calibration, validation or activation started then was stored in a database file that
    no longer had a name and lost at the next start (issue 22, row 5), as new runs are.

    The one dependency that does I/O (a file made in the directory, its free space, maybe the
    space reserve written): a plain function, so FastAPI runs it in a worker thread and a
    data directory that hangs (a network mount, a failing disk) holds this request, not the
    event loop and with it every other request and ``/health``."""
    request.app.state.runtime.motion.storage.check()


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]
RunsDep = Annotated[RunManager, Depends(get_runs)]
CalibrationsDep = Annotated[Calibrations, Depends(get_calibrations)]
ValidationsDep = Annotated[Validations, Depends(get_validations)]
DevicesDep = Annotated[Devices, Depends(get_devices)]
EventsDep = Annotated[EventBus, Depends(get_events)]


async def require_api_key(settings: SettingsDep,
                          credentials: Annotated[HTTPAuthorizationCredentials | None,
                                                 Depends(_bearer)]) -> None:
    """Accept only ``Authorization: Bearer <CELLCAL_API_KEY>`` (401 otherwise).

    ``service.api.guard.RequestGuard`` already checked it before the body was read; this
    dependency declares the scheme in the OpenAPI document and guards apps built without it.
    """
    check_api_key(settings.api_key, None if credentials is None else credentials.credentials)
