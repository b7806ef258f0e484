"""The one board interface: what the calibration needs to know about a printed target, and
the base of every board type's configuration (:class:`BoardTarget`)."""

from __future__ import annotations

from typing import Annotated, Any, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from calib.boards.detection import Detection

#: A nominal length of a board configuration (metres): 1 mm to 1 m, the boards that are
#: printed or milled for a robot cell (a length beyond either end is a unit mistake, and a
#: subnormal one broke the solver long after the board was accepted).
MIN_TARGET_LENGTH_M, MAX_TARGET_LENGTH_M = 1e-3, 1.0


def _unit_hint(value: Any) -> Any:
    """A length beyond 1 m was meant in millimetres (30 for a 30 mm square): say so, with the
    value in metres, instead of only the bound."""
    if isinstance(value, int | float) and MAX_TARGET_LENGTH_M < value <= 1000.0:
        raise ValueError(f"{value:g} m is longer than any board's square or marker (at most "
                         f"{MAX_TARGET_LENGTH_M:g} m): millimetres? {value:g} mm is "
                         f"{value / 1000:g} m")
    return value


TargetLength = Annotated[float, Field(ge=MIN_TARGET_LENGTH_M, le=MAX_TARGET_LENGTH_M,
                                      allow_inf_nan=False), BeforeValidator(_unit_hint)]


@runtime_checkable
class Board(Protocol):
    """A printed calibration target.

    ``point_ids`` numbers the board's points; ``points(ids)`` gives their positions in the
    target frame with the print's scale κ and aspect ν (true point (κν x, κ y, 0), Strobl &
    Hirzinger eq. 4); ``detect`` finds the points in an image, with their ids; ``outline``
    is the printed edge, for planning views; ``target`` its configuration. Implementations:
    :class:`Checkerboard`, :class:`Charuco`.
    """

    kind: str
    square_size: float

    @property
    def point_ids(self) -> np.ndarray:
        """All point ids, shape (N,), int64."""
        ...

    def points(self, ids: np.ndarray | None = None, *, kappa: float = 1.0,
               nu: float = 1.0) -> np.ndarray:
        """Points ``ids`` (all when None) in the target frame, shape (N, 3), metres."""
        ...

    def detect(self, image: np.ndarray) -> Detection:
        """The board's points in one image, with ids, or the reason it is unusable."""
        ...

    def outline(self, per_side: int = 8) -> np.ndarray:
        """Points along the printed board's outer edge, shape (4 * per_side, 3)."""
        ...

    def target(self) -> BoardTarget:
        """The board's configuration (the inverse of :meth:`BoardTarget.board`)."""
        ...


@runtime_checkable
class ChecksConfiguration(Protocol):
    """Capability of a board: it tells from one image that its configuration is wrong (a
    board of another size in view), before a search for the configured board that could not
    succeed."""

    def mismatch(self, image: np.ndarray) -> str | None:
        """What the image shows instead of the configured board ("found a 9x6 grid, you
        configured 12x9"), or None when it shows the configured board or cannot tell."""
        ...


class BoardTarget(BaseModel):
    """Base of every board type's configuration, as station-set files, REST, settings and
    mock scenes give it: a pydantic model whose ``type`` literal names the board type and
    whose :meth:`board` makes the :class:`Board`.

    A board module defines its subclass next to its :class:`Board` class;
    ``calib.boards.targets`` finds every subclass in the package's modules and makes the one
    target union of them, so a new board type is one new module.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    type: str

    def board(self) -> Board:
        """The :class:`Board` this configuration describes."""
        raise NotImplementedError(f"{type(self).__name__} makes no board")
