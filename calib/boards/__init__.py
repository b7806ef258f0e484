"""Calibration boards: the one :class:`Board` interface, its implementations and the target
configuration that names them.

* ``base`` — the :class:`Board` protocol and :class:`BoardTarget`, the base of every board
  type's configuration;
* ``detection`` — :class:`Detection` (corners with ids) and the image helpers all boards use;
* ``checkerboard`` — :class:`Checkerboard` (full views, origin rule, ambiguity) and its
  configuration :class:`CheckerboardTarget`;
* ``charuco`` — :class:`Charuco` (OpenCV's ChArUco layout, partial views) and
  :class:`CharucoTarget`;
* ``markers`` — ArUco markers in view, for the reasons a board was not found;
* ``targets`` — the pydantic target union of every board type found in this package and
  :func:`board_from_target`.
"""

from calib.boards.base import Board, BoardTarget, ChecksConfiguration
from calib.boards.charuco import MIN_CHARUCO_CORNERS, Charuco, CharucoTarget, detect_charuco
from calib.boards.checkerboard import (
    Checkerboard,
    CheckerboardTarget,
    board_points,
    detect_checkerboard,
    order_corners,
)
from calib.boards.detection import MIN_CONTRAST, MIN_SHARPNESS, Detection, opencv_out_of_memory
from calib.boards.targets import (
    TARGET_TYPES,
    Target,
    TargetAdapter,
    board_from_target,
    target_from_board,
)

__all__ = [
    "MIN_CHARUCO_CORNERS",
    "MIN_CONTRAST",
    "MIN_SHARPNESS",
    "TARGET_TYPES",
    "Board",
    "BoardTarget",
    "Charuco",
    "CharucoTarget",
    "Checkerboard",
    "CheckerboardTarget",
    "ChecksConfiguration",
    "Detection",
    "Target",
    "TargetAdapter",
    "board_from_target",
    "board_points",
    "detect_charuco",
    "detect_checkerboard",
    "opencv_out_of_memory",
    "order_corners",
    "target_from_board",
]
