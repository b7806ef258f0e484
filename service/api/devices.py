"""The cell's devices as the service sees them (connecting if needed) and the motion limits."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from drivers.capture import read_tcp_pose
from drivers.errors import CameraError, DeviceError, RobotError
from service.api.deps import DevicesDep, SettingsDep
from service.api.routing import OneThreadRoute
from service.schemas import ErrorInfo


class RobotInfo(BaseModel):
    url: str
    connected: bool
    ready: bool = False
    mode: str | None = None
    protective_stop: bool = False
    emergency_stop: bool = False
    tcp_pose: list[float] | None = None
    error: ErrorInfo | None = None


class CameraInfo(BaseModel):
    url: str
    opened: bool
    resolution: list[int] | None = None
    error: ErrorInfo | None = None


class DevicesPublic(BaseModel):
    robot: RobotInfo
    camera: CameraInfo
    workspace: dict[str, list[float]] = Field(description="TCP box, base frame, metres")


router = APIRouter(prefix="/devices", tags=["devices"], route_class=OneThreadRoute)


def _error(exc: Exception) -> ErrorInfo:
    code = exc.code if isinstance(exc, DeviceError) else "invalid_configuration"
    return ErrorInfo(code=code, detail=str(exc))


@router.get("")
def get_devices(devices: DevicesDep, settings: SettingsDep) -> DevicesPublic:
    """Robot state and TCP pose, camera resolution, workspace box; errors per device."""
    workspace = {"min": list(settings.workspace_min), "max": list(settings.workspace_max)}
    robot_info = RobotInfo(url=settings.robot, connected=False)
    camera_info = CameraInfo(url=settings.camera, opened=False)
    try:
        robot, camera = devices.get()
    except (DeviceError, ValueError) as exc:
        # The robot is opened first and the camera after it: a robot error leaves the camera
        # untried (not failed), a camera error is the camera's alone.
        if not isinstance(exc, CameraError):
            robot_info.error = _error(exc)
        if not isinstance(exc, RobotError):
            camera_info.error = _error(exc)
        return DevicesPublic(robot=robot_info, camera=camera_info, workspace=workspace)
    try:
        st = robot.status()
        robot_info = RobotInfo(url=settings.robot, connected=st.connected, ready=st.ready,
                               mode=st.mode, protective_stop=st.protective_stop,
                               emergency_stop=st.emergency_stop,
                               tcp_pose=[float(v) for v in read_tcp_pose(robot)])
    except DeviceError as exc:
        robot_info.error = _error(exc)
    try:
        camera_info = CameraInfo(url=settings.camera, opened=camera.opened,
                                 resolution=list(camera.resolution))
    except DeviceError as exc:
        camera_info.error = _error(exc)
    return DevicesPublic(robot=robot_info, camera=camera_info, workspace=workspace)
