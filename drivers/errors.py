"""Typed device errors: a machine-readable ``code`` and a sentence for people.

The service maps these to HTTP statuses in one place; the CLI prints ``str(err)`` on one line.
"""

from __future__ import annotations


class CodedError(Exception):
    """An error with a stable machine-readable ``code`` and a message for people.

    Subclasses name their code in the class line (``class X(CodedError, code="x")``); one
    instance may carry a more specific one (``X("...", code="y")``).
    """

    code = "error"

    def __init_subclass__(cls, *, code: str | None = None, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        if code is not None:
            cls.code = code

    def __init__(self, message: str, *, code: str | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code


class DeviceError(CodedError, code="device_error"):
    """A device could not do what was asked."""


class RobotError(DeviceError, code="robot_error"):
    """The robot refused or failed a command."""


class RobotConnectionError(RobotError, code="robot_unreachable"):
    """The controller cannot be reached, or the connection dropped."""


class ProtectiveStopError(RobotError, code="protective_stop"):
    """The robot stopped itself (a collision or a safety limit); unlock it, then retry."""


class EmergencyStopError(RobotError, code="emergency_stop"):
    """An emergency stop is pressed."""


class WorkspaceError(RobotError, code="outside_workspace"):
    """A requested target lies outside the configured workspace limits."""


class CameraError(DeviceError, code="camera_error"):
    """The camera failed, or is not there."""


class CameraTimeoutError(CameraError, code="camera_timeout"):
    """One grab got no frame in time; the camera may still deliver the next one."""


class CameraStalledError(CameraError, code="camera_stalled"):
    """Several grabs in a row got no frame (``drivers.stall``): the camera stopped delivering
    and was closed; ``open()`` it again once it is fixed. Not a ``CameraTimeoutError``: retrying
    the grab does not help."""


class CameraFrozenError(CameraError, code="camera_frozen"):
    """The camera handed out the frame of an earlier station again although the robot moved
    (``drivers.frozen``): its stream or driver hangs on one frame. Retrying the grab does not
    help; restart the camera or its stream."""
