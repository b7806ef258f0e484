"""``GET /metrics``: the service's figures for Prometheus (``service.metrics``)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool

from service.api.routing import OneThreadRoute
from service.metrics import CONTENT_TYPE_LATEST, exposition

router = APIRouter(tags=["metrics"], route_class=OneThreadRoute)


@router.get("/metrics", response_class=Response, responses={
    200: {"content": {CONTENT_TYPE_LATEST: {}},
          "description": "Prometheus text format; scrape with the API key as bearer token"}})
async def metrics(request: Request) -> Response:
    """Runs, stations captured / skipped, calibration durations, and per setup the newest
    calibration's RMS and cross-validated errors and its verdict."""
    body = await run_in_threadpool(exposition, request.app.state.db)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
