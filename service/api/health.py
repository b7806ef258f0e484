"""Liveness, without authentication (load balancers and cell controllers poll it)."""

from __future__ import annotations

from fastapi import APIRouter

from service.schemas import Health
from service.version import software_version

router = APIRouter(tags=["health"])


@router.get("/health")
def health() -> Health:
    """The service is up and answering."""
    return Health(version=software_version())
