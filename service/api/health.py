"""Liveness, without authentication (load balancers and cell controllers poll it)."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from service.api.routing import OneThreadRoute
from service.schemas import ErrorInfo
from service.version import software_version


class Health(BaseModel):
    status: Literal["ok", "degraded"] = Field(
        "ok", description="degraded: the service answers, but its data directory takes no "
                          "writes (new runs are refused 503 until it is fixed)")
    version: str
    problem: ErrorInfo | None = Field(None, description="what is degraded (storage_unavailable, "
                                                        "disk_full)")


router = APIRouter(tags=["health"], route_class=OneThreadRoute)


@router.get("/health")
def health(request: Request) -> Health:
    """The service is up and answering; ``degraded`` (still 200) while its data directory
    takes no writes, with the reason."""
    runtime = getattr(request.app.state, "runtime", None)
    problem = None if runtime is None else runtime.motion.storage.problem()
    if problem is None:
        return Health(version=software_version())
    return Health(status="degraded", version=software_version(),
                  problem=ErrorInfo(code=problem.code, detail=str(problem)))
