"""Liveness, without authentication (load balancers and cell controllers poll it)."""

from __future__ import annotations

from fastapi import APIRouter

from service.results import software_version
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/health")
def health() -> Health:
    """The service is up and answering."""
    return Health(version=software_version())
