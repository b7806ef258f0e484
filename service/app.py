"""The FastAPI application: routers, the lifespan (``service.runtime``), error mapping.

``create_app(settings)`` builds an app; ``uvicorn --factory service.app:create_app`` serves one
configured from the environment (``cellcal serve`` does the same with command-line options).
Every domain error becomes JSON ``{"detail": <sentence>, "code": <stable code>}`` here, and
only here.
"""

from __future__ import annotations

import gc
import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi_offline import FastAPIOffline
from starlette.exceptions import HTTPException as StarletteHTTPException

from drivers.errors import DeviceError, WorkspaceError
from service.api import (
    active,
    calibrations,
    devices,
    health,
    metrics,
    runs,
    stations,
    validations,
)
from service.api.deps import require_api_key
from service.api.guard import PayloadTooLargeError, RequestGuard
from service.api.idempotency import Idempotency
from service.api.openapi import document_errors
from service.api.short_ids import ShortIds
from service.cell.devices import DeviceOpener, Devices
from service.errors import (
    AuthError,
    ConflictError,
    NotFoundError,
    NotReadyError,
    QueueFullError,
    ServiceError,
    UnprocessableError,
)
from service.runtime import Runtime
from service.settings import Settings
from service.store.db import TRANSIENT_ERRORS, DatabaseUnavailableError
from service.store.storage import STORAGE_ERRNOS, StorageError, storage_error
from service.version import software_version
from service.web import mount_page
from service.web.docs_page import mount_redoc

log = logging.getLogger("cellcal.service")

#: Domain error -> HTTP status; the first class in an exception's MRO that is listed wins.
ERROR_STATUS: dict[type[Exception], int] = {
    AuthError: 401,
    NotFoundError: 404,
    ConflictError: 409,
    PayloadTooLargeError: 413,
    UnprocessableError: 422,
    QueueFullError: 429,
    WorkspaceError: 422,
    DeviceError: 503,
    StorageError: 503,
    NotReadyError: 503,
    ServiceError: 400,
}
_HTTP_CODES = {404: "not_found", 405: "method_not_allowed"}


def create_app(settings: Settings | None = None, *,
               open_devices: DeviceOpener | None = None) -> FastAPI:
    """Build the app; ``open_devices`` replaces opening ``settings.robot`` / ``camera``."""
    settings = settings if settings is not None else Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        rt = Runtime.open(settings, open_devices)
        app.state.runtime, app.state.db, app.state.devices = rt, rt.db, rt.devices
        await run_in_threadpool(_open_early, rt.devices)
        # Start-up objects (modules, the app, the ORM) never die: keep them out of the cyclic
        # collector's full passes, which otherwise stall every thread for ~0.1 s now and then.
        gc.freeze()
        try:
            yield
        finally:
            await run_in_threadpool(rt.close)

    # Swagger UI and ReDoc from assets shipped in fastapi_offline: /docs works without internet
    app = FastAPIOffline(
        redoc_url=None, title="cellcal", version=software_version(), lifespan=lifespan,
        description="Capture calibration stations with a robot and a camera, compute the "
                    "camera intrinsics and the hand-eye transform. Every call but /health "
                    "needs `Authorization: Bearer <CELLCAL_API_KEY>`. Units: metres and "
                    "radians; poses are UR vectors [x, y, z, rx, ry, rz] (T_base_tcp).")
    app.state.settings = settings
    mount_page(app)
    mount_redoc(app)
    app.include_router(health.router)
    # active before calibrations: /calibrations/active is not a calibration id
    for module in (runs, stations, active, calibrations, validations, devices, metrics):
        app.include_router(module.router, dependencies=[Depends(require_api_key)])
    for exc_type in (ServiceError, DeviceError):
        app.add_exception_handler(exc_type, _domain_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    for exc_type in (*TRANSIENT_ERRORS, DatabaseUnavailableError):
        app.add_exception_handler(exc_type, _database_error)
    app.add_exception_handler(Exception, _internal_error)
    app.add_middleware(Idempotency, refuse=error_response)  # sees the full ids
    app.add_middleware(ShortIds, refuse=error_response)  # inside the guard: keyed requests only
    app.add_middleware(RequestGuard, api_key=settings.api_key,
                       max_body_bytes=settings.max_body_bytes, refuse=error_response)
    document_errors(app)
    return app


def _open_early(cell: Devices) -> None:
    """Connect at startup so problems show in the log at once; runs retry later."""
    try:
        cell.get()
    except (DeviceError, ValueError) as exc:
        log.warning("devices not available at startup: %s", exc)


def _error(status: int, detail: str, code: str, **extra: Any) -> JSONResponse:
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"detail": detail, "code": code, **extra}, status_code=status,
                        headers=headers)


def error_response(exc: Exception) -> JSONResponse:
    """The JSON error response of a domain error (``ERROR_STATUS``); ``Retry-After`` for
    work still in progress."""
    status = next(ERROR_STATUS[c] for c in type(exc).__mro__ if c in ERROR_STATUS)
    response = _error(status, str(exc), getattr(exc, "code", "error"))
    if isinstance(exc, NotReadyError):
        response.headers["Retry-After"] = str(exc.retry_after_s)
    return response


async def _domain_error(request: Request, exc: Exception) -> JSONResponse:
    return error_response(exc)


async def _database_error(request: Request, exc: Exception) -> JSONResponse:
    """A database that does not answer (lock timeout, server restart): 503, retry later."""
    why = str(getattr(exc, "orig", None) or exc).splitlines()[0]
    log.warning("%s %s: database unavailable: %s", request.method, request.url.path, why)
    return _error(503, f"The database is not answering ({why}); retry in a moment.",
                  "database_unavailable")


async def _internal_error(request: Request, exc: Exception) -> JSONResponse:
    """Anything unforeseen still gets the JSON error body (the traceback goes to the log); a
    file that cannot be written (read-only or full data directory) is 503, not 500."""
    if isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS:
        log.error("%s %s: %s", request.method, request.url.path, exc)
        return error_response(storage_error(exc, "The data directory cannot be written"))
    log.error("%s %s: %s: %s", request.method, request.url.path, type(exc).__name__, exc)
    return _error(500, f"Internal error ({type(exc).__name__}); see the service log.",
                  "internal_error")


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = exc.errors()
    messages = [f"{_where(e['loc'])}: {e['msg']}" for e in errors]
    more = f" (and {len(messages) - 1} more problems)" if len(messages) > 1 else ""
    return _error(422, (messages[0] if messages else "invalid request") + more,
                  "invalid_request",
                  errors=[{"loc": list(e["loc"]), "msg": e["msg"]} for e in errors])


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    """Starlette's own answers (unknown path, method not allowed) with the JSON error body and
    their headers (``Allow`` on 405, RFC 9110)."""
    assert isinstance(exc, StarletteHTTPException)
    if exc.status_code == 400:  # FastAPI's answer to an optional JSON body it cannot parse
        return _error(422, "body: not valid JSON", "invalid_request",
                      errors=[{"loc": ["body"], "msg": "not valid JSON"}])
    response = _error(exc.status_code, str(exc.detail), _HTTP_CODES.get(exc.status_code,
                                                                        "http_error"))
    response.headers.update(exc.headers or {})
    if exc.status_code == 405:  # every method of the path, not only the first route's
        response.headers["Allow"] = ", ".join(_allowed_methods(request))
    return response


def _allowed_methods(request: Request) -> list[str]:
    """The methods the OpenAPI document has for the request's path (HEAD with GET)."""
    path = request.url.path
    methods: set[str] = set()
    for template, operations in request.app.openapi()["paths"].items():
        if re.fullmatch(re.sub(r"\{[^/]+\}", "[^/]+", template), path):
            methods |= {m.upper() for m in operations}
    if "GET" in methods:
        methods.add("HEAD")
    return sorted(methods)


def _where(loc: tuple[Any, ...] | list[Any]) -> str:
    """``('body', 'poses', 0, 2)`` -> ``body.poses[0][2]``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "request"
