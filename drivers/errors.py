"""Typed device errors: a machine-readable ``code`` and a sentence for people.

The service maps these to HTTP statuses in one place; the CLI prints ``str(err)`` on one line.
"""

from __future__ import annotations


class DeviceError(Exception):
    """A device could not do what was asked. ``code`` is stable; the message is for people."""

    code = "device_error"

    def __init__(self, message: str, *, code: str | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code


class RobotError(DeviceError):
    code = "robot_error"


class RobotConnectionError(RobotError):
    """The controller cannot be reached, or the connection dropped."""

    code = "robot_unreachable"


class ProtectiveStopError(RobotError):
    code = "protective_stop"


class EmergencyStopError(RobotError):
    code = "emergency_stop"


class WorkspaceError(RobotError):
    """A requested target lies outside the configured workspace limits."""

    code = "outside_workspace"


class CameraError(DeviceError):
    code = "camera_error"


class CameraTimeoutError(CameraError):
    """One grab got no frame in time; the camera may still deliver the next one."""

    code = "camera_timeout"


class CameraStalledError(CameraError):
    """Several grabs in a row got no frame (``drivers.stall``): the camera stopped delivering
    and was closed; ``open()`` it again once it is fixed. Not a ``CameraTimeoutError``: retrying
    the grab does not help."""

    code = "camera_stalled"
