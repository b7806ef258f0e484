"""The safety box of the emulated UR controller (``python -m mocks.ur_emulator --box``).

A real controller's safety configuration bounds the flange and a few *tool positions* (points
fixed to the flange, such as a camera's) by safety planes, and stops the arm with a protective
stop before one of them crosses a plane. Here the planes form an axis-aligned box in the base
frame; a motion is refused before it starts when the flange or a tool point would leave the
box anywhere along its path (``SAMPLES`` points of it), and the refusal is counted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calib import matrix_from_ur_pose

#: Points of a motion's path checked against the box.
SAMPLES = 11


@dataclass(frozen=True)
class SafetyBox:
    """``lo`` and ``hi`` (3,) corners of the box in the base frame (m); ``tool_points``
    (k, 3) points in the flange frame checked besides the flange itself (m)."""

    lo: np.ndarray
    hi: np.ndarray
    tool_points: np.ndarray

    @classmethod
    def parse(cls, box: str, tool_points: list[str]) -> SafetyBox:
        """From ``--box X0,Y0,Z0,X1,Y1,Z1`` and ``--tool-point X,Y,Z`` options; ValueError
        for a malformed one."""
        corners = parse_floats(box, 6, "--box")
        points = [parse_floats(p, 3, "--tool-point") for p in tool_points]
        lo, hi = np.array(corners[:3]), np.array(corners[3:])
        if not (lo < hi).all():
            raise ValueError(f"--box {box}: each lower corner must be below the upper one")
        return cls(lo, hi, np.array(points, dtype=float).reshape(-1, 3))

    def refuses(self, pose_at: Callable[[float], np.ndarray]) -> str | None:
        """Why a motion whose UR pose at path fraction s is ``pose_at(s)`` (6,) must not
        start, or None when the flange and every tool point stay inside along it."""
        for s in np.linspace(0.0, 1.0, SAMPLES):
            T = matrix_from_ur_pose(pose_at(float(s)))
            points = np.vstack([T[:3, 3], self.tool_points @ T[:3, :3].T + T[:3, 3]])
            outside = ~((points >= self.lo) & (points <= self.hi)).all(axis=1)
            if outside.any():
                i = int(outside.argmax())  # 0 the flange, then the tool points
                name = "the flange" if i == 0 else f"tool point {i - 1}"
                return (f"{name} would leave the safety box at {s:.0%} of the move "
                        f"({np.round(points[i], 4).tolist()} m)")
        return None


def parse_floats(text: str, n: int, option: str) -> list[float]:
    """``n`` comma-separated numbers of a command-line option; ValueError otherwise."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != n or not np.isfinite(values).all():
        raise ValueError(f"{option} {text!r}: give {n} comma-separated numbers")
    return values
