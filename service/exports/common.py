"""What every export writer shares: the names written into exports, the validated transforms
of a result and number text."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from calib import Result, Transform, check_transforms

#: What ``hand_eye`` / ``target_pose`` mean in each setup (``docs/conventions.md``).
FRAMES = {"eye_in_hand": ("T_tcp_cam", "T_base_target"),
          "eye_to_hand": ("T_base_cam", "T_tcp_target")}


def matrix(transform: Transform, name: str) -> np.ndarray:
    """The transform's matrix, shape (4, 4), checked to be rigid (ValueError naming ``name``)."""
    return check_transforms(np.asarray(transform.matrix, dtype=float), name)[0]


def robot_map_note(result: Result) -> list[str]:
    """What an exported hand-eye needs when the result maps the robot's translations
    (``robot_translation_map``, the model selection's robot-scale term): the map itself and
    that the hand-eye holds for readings corrected by it; lines of plain text, none when the
    result has no map. The figure is the result's ``robot_translation_map`` finding's."""
    S = result.robot_translation_map
    if S is None:
        return []
    rows = "; ".join(", ".join(num(v) for v in row) for row in S)
    shift = next((getattr(f, "largest_shift_m", None) for f in result.quality.findings
                  if f.code == "robot_translation_map"), None) if result.quality else None
    off = "" if shift is None else f" by up to {1e3 * float(shift):.1f} mm over its stations"
    return [f"robot_translation_map S = [{rows}] (3x3, base frame): this hand-eye holds for",
            "the arm's translations corrected to t + S t; combined with the arm's readings as",
            f"they are it is off{off}: correct the readings by S, or calibrate the arm."]


def num(v: float) -> str:
    """Shortest text that reads back as the same float."""
    return repr(float(v))


#: A ROS name segment; frame ids may join segments with '/'.
_NAME = r"[A-Za-z_][A-Za-z0-9_]*"


@dataclass(frozen=True)
class ExportNames:
    """Names written into the exports.

    camera_name : ROS ``camera_name``, prefix of the URDF joint and the launch file's node.
    parent_frame : the frame the camera is fixed to; default ``tool0`` (eye-in-hand) or
        ``base`` (eye-to-hand), UR's ROS names.
    child_frame : the camera's frame; default ``<camera_name>_optical_frame``.
    """

    camera_name: str = "camera"
    parent_frame: str | None = None
    child_frame: str | None = None

    def __post_init__(self) -> None:
        if not re.fullmatch(_NAME, self.camera_name):
            raise ValueError(f"camera name {self.camera_name!r}: use letters, digits and _, "
                             "not starting with a digit")
        for what, frame in (("parent frame", self.parent_frame),
                            ("child frame", self.child_frame)):
            if frame is not None and not re.fullmatch(f"{_NAME}(/{_NAME})*", frame):
                raise ValueError(f"{what} {frame!r}: use letters, digits, _ and /, each part "
                                 "not starting with a digit")

    def frames(self, setup: str) -> tuple[str, str]:
        """(parent, child) frame names for a result of ``setup``."""
        default_parent = "tool0" if setup == "eye_in_hand" else "base"
        return (self.parent_frame or default_parent,
                self.child_frame or f"{self.camera_name}_optical_frame")
