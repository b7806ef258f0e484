"""Request dependencies as ``Annotated`` aliases, so tests can swap them with
``app.dependency_overrides``; the app keeps the shared objects in ``app.state``."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from service.calibrations import Calibrations
from service.devices import Devices
from service.errors import AuthError
from service.runs import RunManager
from service.settings import Settings
from service.validations import Validations

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


def get_devices(request: Request) -> Devices:
    return request.app.state.devices


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]
RunsDep = Annotated[RunManager, Depends(get_runs)]
CalibrationsDep = Annotated[Calibrations, Depends(get_calibrations)]
ValidationsDep = Annotated[Validations, Depends(get_validations)]
DevicesDep = Annotated[Devices, Depends(get_devices)]


def require_api_key(settings: SettingsDep,
                    credentials: Annotated[HTTPAuthorizationCredentials | None,
                                           Depends(_bearer)]) -> None:
    """Accept only ``Authorization: Bearer <CELLCAL_API_KEY>`` (401 otherwise)."""
    if settings.api_key is None:
        raise AuthError("This service has no API key configured; set CELLCAL_API_KEY and "
                        "restart it.", code="no_api_key")
    if credentials is None:
        raise AuthError("Missing credentials: send 'Authorization: Bearer <CELLCAL_API_KEY>'.")
    expected = settings.api_key.get_secret_value().encode()
    if not secrets.compare_digest(credentials.credentials.encode(), expected):
        raise AuthError("Invalid API key.", code="invalid_api_key")
