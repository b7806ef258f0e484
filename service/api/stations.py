"""Stations of a run: robot pose, detection, and the captured image (PNG)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse

from service import store
from service.api.deps import SessionDep, SettingsDep
from service.errors import NotFoundError
from service.models import Station
from service.schemas import DetectionPublic, ErrorInfo, StationPublic

router = APIRouter(prefix="/runs/{run_id}/stations", tags=["stations"])


def station_public(station: Station, *, corners: bool) -> StationPublic:
    det = None
    if station.detection is not None:
        det = DetectionPublic(**{**station.detection,
                                 "corners": station.detection["corners"] if corners else None})
    return StationPublic(
        index=station.index, state=station.state, target_pose=station.target_pose,
        tcp_pose=station.tcp_pose, detection=det, image_size=station.image_size,
        image_url=None if station.image_path is None
        else f"/runs/{station.run_id}/stations/{station.index}/image",
        error=None if station.error is None else ErrorInfo(code=station.error_code or "error",
                                                           detail=station.error),
        attempts=station.attempts, captured_at=station.captured_at)


@router.get("")
def list_stations(run_id: str, session: SessionDep) -> list[StationPublic]:
    """Stored stations in index order (corner lists left out)."""
    return [station_public(s, corners=False) for s in store.list_stations(session, run_id=run_id)]


@router.get("/{index}")
def get_station(run_id: str, index: int, session: SessionDep) -> StationPublic:
    """One station with its detected corners."""
    return station_public(store.get_station(session, run_id=run_id, index=index), corners=True)


@router.get("/{index}/image", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}})
def get_station_image(run_id: str, index: int, session: SessionDep,
                      settings: SettingsDep) -> FileResponse:
    """The captured image as PNG."""
    station = store.get_station(session, run_id=run_id, index=index)
    path = None if station.image_path is None else settings.data_dir / station.image_path
    if path is None or not path.is_file():
        raise NotFoundError(f"Station {index} of run {run_id} has no image.")
    return FileResponse(path, media_type="image/png")
