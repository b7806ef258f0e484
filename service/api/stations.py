"""Stations of a run: robot pose, detection, and the captured image (PNG); stations posted
by a cell controller to an external run."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, UploadFile, status
from fastapi.responses import FileResponse
from pydantic import TypeAdapter

from service.api.deps import RunsDep, SessionDep, SettingsDep
from service.api.routing import OneThreadRoute
from service.errors import NotFoundError, UnprocessableError
from service.runs.external import PostedStation
from service.schemas import (
    DetectionPublic,
    ErrorInfo,
    StationIndex,
    StationPublic,
    StrictFiniteFloat,
)
from service.store import queries
from service.store.records import StationRecord
from service.store.stations import station_of

router = APIRouter(prefix="/runs/{run_id}/stations", tags=["stations"], route_class=OneThreadRoute)


def station_public(row: StationRecord, *, corners: bool) -> StationPublic:
    """The public view of a stored station: the one station model (``calib.Station``, read
    by ``store.stations.station_of``) with the row's capture bookkeeping (index, commanded pose,
    joints, attempts, error code, time); ``corners`` adds the detected corners and ids."""
    station = station_of(row)
    return StationPublic(
        index=row.index, state=row.state, commanded_tcp_pose=row.commanded_tcp_pose,
        freshness=station.freshness,
        tcp_pose=None if station.T_base_tcp is None else station.T_base_tcp.tolist(),
        joint_positions=row.joint_positions,
        detection=None if station.detection is None
        else DetectionPublic.of(station.detection, corners=corners),
        image_size=None if station.image_size is None else list(station.image_size),
        image_url=None if row.image_path is None
        else f"/runs/{row.run_id}/stations/{row.index}/image",
        error=None if station.rejected is None
        else ErrorInfo(code=row.error_code or "error", detail=station.rejected),
        attempts=row.attempts, captured_at=row.captured_at)


@router.get("")
def list_stations(run_id: str, session: SessionDep) -> list[StationPublic]:
    """Stored stations in index order (corner lists left out)."""
    return [station_public(s, corners=False) for s in queries.list_stations(session, run_id=run_id)]


@router.post("", status_code=status.HTTP_201_CREATED, responses={
    409: {"description": "not an external run, or it does not accept stations now"},
    413: {"description": "the upload is larger than CELLCAL_MAX_BODY_BYTES, or the image "
                         "has more pixels than CELLCAL_MAX_IMAGE_PIXELS (from its header) or "
                         "needs more memory than CELLCAL_IMAGE_WORKER_MEMORY_MB"},
    422: {"description": "malformed pose or joints, an image without its pose, or an image "
                         "whose board search passed CELLCAL_IMAGE_CPU_S"},
    503: {"description": "the camera or robot the service had to read failed (e.g. "
                         "camera_frozen), or the data directory takes no writes "
                         "(storage_unavailable, disk_full)"}})
def post_station(
        run_id: str, runs: RunsDep,
        pose: Annotated[str | None, Form(
            description="JSON [x, y, z, rx, ry, rz] (m, rad), T_base_tcp at the image; "
                        "without it the service reads the pose from its robot")] = None,
        joints: Annotated[str | None, Form(
            description="JSON six joint positions (rad), if known")] = None,
        image: Annotated[UploadFile | None, File(
            description="PNG or JPEG; without it the service grabs from its camera")] = None,
) -> StationPublic:
    """Add a station to an external run; the answer says whether the board was found and
    why not (``state``, ``detection.reason``, ``error``). A station whose image cannot be
    read is stored as skipped with the reason."""
    posted = PostedStation(pose=_vector(pose, "pose"), joints=_vector(joints, "joints"),
                           image=None if image is None else image.file.read())
    station = runs.external.add(run_id, posted)
    return station_public(station, corners=False)


_VECTOR = TypeAdapter(list[StrictFiniteFloat])


def _vector(text: str | None, name: str) -> list[float] | None:
    """A form field holding a JSON list of numbers (422 ``invalid_pose`` if it is not)."""
    if text is None:
        return None
    try:
        value: Any = json.loads(text)
        return _VECTOR.validate_python(value)
    except (ValueError, RecursionError):  # not JSON, too many digits, nested too deep
        raise UnprocessableError(f"{name}: expected a JSON list of numbers like "
                                 "[0.4, -0.1, 0.5, 3.14, 0.0, 0.0], got "
                                 f"{text[:80]!r}", code="invalid_pose") from None


@router.get("/{index}")
def get_station(run_id: str, index: StationIndex, session: SessionDep) -> StationPublic:
    """One station with its detected corners."""
    return station_public(queries.get_station(session, run_id=run_id, index=index), corners=True)


@router.get("/{index}/image", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}})
def get_station_image(run_id: str, index: StationIndex, session: SessionDep,
                      settings: SettingsDep) -> FileResponse:
    """The captured image as PNG."""
    station = queries.get_station(session, run_id=run_id, index=index)
    path = None if station.image_path is None else settings.data_dir / station.image_path
    if path is None or not path.is_file():
        raise NotFoundError(f"Station {index} of run {run_id} has no image.")
    return FileResponse(path, media_type="image/png")
