"""Request dependencies as ``Annotated`` aliases, so tests can swap them with
``app.dependency_overrides``; the app keeps the shared objects in ``app.state``."""

from __future__ import annotations

from collections.abc import Iterator
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


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    with request.app.state.db.session() as session:
        yield session


def get_runs(request: Request) -> RunManager:
    return request.app.state.runtime.runs


def get_calibrations(request: Request) -> Calibrations:
    return request.app.state.runtime.calibrations


def get_validations(request: Request) -> Validations:
    return request.app.state.runtime.validations


def get_events(request: Request) -> EventBus:
    return request.app.state.runtime.events


def get_devices(request: Request) -> Devices:
    return request.app.state.devices


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]
RunsDep = Annotated[RunManager, Depends(get_runs)]
CalibrationsDep = Annotated[Calibrations, Depends(get_calibrations)]
ValidationsDep = Annotated[Validations, Depends(get_validations)]
DevicesDep = Annotated[Devices, Depends(get_devices)]
EventsDep = Annotated[EventBus, Depends(get_events)]


def require_api_key(settings: SettingsDep,
                    credentials: Annotated[HTTPAuthorizationCredentials | None,
                                           Depends(_bearer)]) -> None:
    """Accept only ``Authorization: Bearer <CELLCAL_API_KEY>`` (401 otherwise).

    ``service.api.guard.RequestGuard`` already checked it before the body was read; this
    dependency declares the scheme in the OpenAPI document and guards apps built without it.
    """
    check_api_key(settings.api_key, None if credentials is None else credentials.credentials)
