"""The one target type: a board's configuration as data (station-set files, REST, settings,
mock scenes), a pydantic union on ``type``, and :func:`board_from_target`.

A configuration without ``type`` is a checkerboard, as every file before ChArUco was.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, TypeAdapter, model_validator

from calib.boards.base import Board
from calib.boards.charuco import Charuco
from calib.boards.checkerboard import Checkerboard
from calib.boards.markers import dictionary

_Count = Annotated[int, Field(ge=2, le=100)]
_Length = Annotated[float, Field(gt=0.0, lt=1.0, allow_inf_nan=False)]


class _TargetBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CheckerboardTarget(_TargetBase):
    """A checkerboard: ``inner_corners`` [cols, rows], nominal ``square_size_m``."""

    type: Literal["checkerboard"] = "checkerboard"
    inner_corners: tuple[_Count, _Count] = Field(
        description="[cols, rows] of inner corners; x runs along cols")
    square_size_m: _Length = Field(description="nominal square size in metres")


class CharucoTarget(_TargetBase):
    """A ChArUco board in OpenCV's layout: ``squares`` [cols, rows], nominal square and
    marker sizes, the ArUco ``dictionary`` by OpenCV's name, ``legacy_pattern`` for boards
    made by OpenCV before 4.6."""

    type: Literal["charuco"]
    squares: tuple[Annotated[int, Field(ge=3, le=100)], Annotated[int, Field(ge=3, le=100)]] = (
        Field(description="[cols, rows] of squares; x runs along cols"))
    square_size_m: _Length = Field(description="nominal square size in metres")
    marker_size_m: _Length = Field(description="nominal marker size in metres")
    dictionary: str = Field(description="OpenCV's ArUco dictionary name, e.g. DICT_5X5_100")
    legacy_pattern: bool = Field(False, description="OpenCV's pre-4.6 ChArUco pattern")

    @model_validator(mode="after")
    def _fits(self) -> CharucoTarget:
        if self.marker_size_m >= self.square_size_m:
            raise ValueError("marker_size_m must be smaller than square_size_m")
        words = len(dictionary(self.dictionary).bytesList)
        needed = (self.squares[0] * self.squares[1]) // 2
        if needed > words:
            raise ValueError(f"a {self.squares[0]}x{self.squares[1]}-square board needs "
                             f"{needed} markers; {self.dictionary} has {words}")
        return self


def _target_type(value: Any) -> str:
    if isinstance(value, dict):
        return value.get("type", "checkerboard")
    return getattr(value, "type", "checkerboard")


#: The one target type: parse with ``TargetAdapter.validate_python`` or as a model field.
Target = Annotated[
    Annotated[CheckerboardTarget, Tag("checkerboard")] | Annotated[CharucoTarget, Tag("charuco")],
    Discriminator(_target_type),
]
TargetAdapter: TypeAdapter[CheckerboardTarget | CharucoTarget] = TypeAdapter(Target)


def board_from_target(target: CheckerboardTarget | CharucoTarget) -> Board:
    """The :class:`Board` a target configuration describes."""
    if isinstance(target, CharucoTarget):
        return Charuco(target.squares, target.square_size_m, target.marker_size_m,
                       target.dictionary, target.legacy_pattern)
    return Checkerboard(target.inner_corners, target.square_size_m)


def target_from_board(board: Board) -> CheckerboardTarget | CharucoTarget:
    """The configuration of ``board`` (inverse of :func:`board_from_target`)."""
    if isinstance(board, Charuco):
        return CharucoTarget(type="charuco", squares=board.squares,
                             square_size_m=board.square_size, marker_size_m=board.marker_size,
                             dictionary=board.dictionary, legacy_pattern=board.legacy_pattern)
    if isinstance(board, Checkerboard):
        return CheckerboardTarget(inner_corners=board.inner_corners,
                                  square_size_m=board.square_size)
    raise TypeError(f"no target configuration for {type(board).__name__}")
