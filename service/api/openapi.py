"""The error answers in the OpenAPI document as the service really sends them.

Every error is JSON ``{"detail", "code"}`` (``errors`` added for 422: where and what, per
problem), whatever raised it; FastAPI's generated document instead shows a list-valued
``detail`` for 422 and nothing for the statuses the service's own checks answer. Here each
operation gets the statuses it can answer, all with ``ErrorBody``: 401 (the API key, every
route but ``/health``), 404 (an unknown id in the path), 413 (a body over the size limit),
422 (malformed parameters or body), 500 and 503 (a database that does not answer), plus those
the route itself declares (409, 429). The operations that start work also declare the
``Idempotency-Key`` header (``service.api.idempotency``, a middleware FastAPI cannot see) and
its answers: 400 for a malformed key, 409 while the first request runs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from pydantic import BaseModel, Field

from service.api import idempotency

#: Paths reachable without the API key.
OPEN_PATHS = ("/health",)
_DESCRIPTIONS = {
    "400": "a malformed Idempotency-Key",
    "401": "no API key, or a wrong one",
    "404": "no such id",
    "413": "the request body is larger than the service accepts",
    "409": "a conflict: the detail says with what",
    "422": "malformed parameters or body; errors says where",
    "500": "an internal error (a bug: the detail names it)",
    "503": "the database is not answering (retry in a moment), or, for a request that "
           "writes, the data directory takes none (storage_unavailable, disk_full: see "
           "/health)",
}


class ErrorItem(BaseModel):
    """One problem of a malformed request."""

    loc: list[str | int] = Field(description="where: body, then field names and indices")
    msg: str


class ErrorBody(BaseModel):
    """Every error answer of the service."""

    detail: str = Field(description="what went wrong and what to do, for people")
    code: str = Field(description="stable machine-readable code, e.g. invalid_request")
    errors: list[ErrorItem] | None = Field(None, description="422 only: each problem")


def document_errors(app: FastAPI) -> None:
    """Make ``app``'s OpenAPI document declare ``ErrorBody`` on every error status."""
    generate: Callable[[], dict[str, Any]] = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = _with_errors(generate())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def _with_errors(doc: dict[str, Any]) -> dict[str, Any]:
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    body = ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(body.pop("$defs", {}))
    schemas["ErrorBody"] = body
    content = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}
    for path, operations in doc["paths"].items():
        if "post" in operations and idempotency.START_TEMPLATES.fullmatch(path):
            operations["post"].setdefault("parameters", []).append(idempotency.PARAMETER)
        for op in operations.values():
            responses = op.setdefault("responses", {})
            for status in _statuses(path, op):
                responses.setdefault(status, {"description": _DESCRIPTIONS[status]})
            for status, response in responses.items():
                if int(status) >= 400:
                    response["content"] = content
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    return doc


def _statuses(path: str, op: dict[str, Any]) -> list[str]:
    """The error statuses every operation like ``op`` at ``path`` can answer."""
    statuses = ["500", "503"]
    if path not in OPEN_PATHS:
        statuses += ["401", "422"]
    if "{" in path:
        statuses.append("404")
    if "requestBody" in op:
        statuses.append("413")
    if idempotency.PARAMETER in op.get("parameters", ()):
        statuses += ["400", "409"]
    return statuses
