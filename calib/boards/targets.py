"""The one target type: every board type's configuration (a :class:`BoardTarget` subclass
that its board module defines), collected into one pydantic union on ``type``, for station-set
files, REST, settings and mock scenes; :func:`board_from_target` makes the board.

The union is built from the modules of this package, so adding a board type is adding its
module (its :class:`Board` class and its :class:`BoardTarget`) and nothing else. A
configuration without ``type`` is a checkerboard, as every file before ChArUco was.
"""

from __future__ import annotations

import importlib
import pkgutil
from functools import reduce
from operator import or_
from pathlib import Path
from typing import Annotated, Any, get_args

from pydantic import Discriminator, Tag, TypeAdapter

from calib.boards.base import Board, BoardTarget

#: The ``type`` of a configuration that names none.
DEFAULT_TYPE = "checkerboard"


def _target_types() -> dict[str, type[BoardTarget]]:
    """Every :class:`BoardTarget` subclass defined in a module of this package, by ``type``."""
    found: dict[str, type[BoardTarget]] = {}
    for info in pkgutil.iter_modules([str(Path(__file__).parent)]):
        module = importlib.import_module(f"{__package__}.{info.name}")
        for obj in vars(module).values():
            if (isinstance(obj, type) and issubclass(obj, BoardTarget)
                    and obj is not BoardTarget and obj.__module__ == module.__name__):
                (kind,) = get_args(obj.model_fields["type"].annotation)
                found[kind] = obj
    return dict(sorted(found.items(), key=lambda item: (item[0] != DEFAULT_TYPE, item[0])))


#: Board type name -> its configuration model.
TARGET_TYPES = _target_types()


def _target_type(value: Any) -> str:
    if isinstance(value, dict):
        return value.get("type", DEFAULT_TYPE)
    return getattr(value, "type", DEFAULT_TYPE)


#: The one target type: parse with ``TargetAdapter.validate_python`` or as a model field.
Target = Annotated[reduce(or_, [Annotated[model, Tag(kind)]  # type: ignore[valid-type]
                                for kind, model in TARGET_TYPES.items()]),
                   Discriminator(_target_type)]
TargetAdapter: TypeAdapter[BoardTarget] = TypeAdapter(Target)


def board_from_target(target: BoardTarget) -> Board:
    """The :class:`Board` a target configuration describes."""
    return target.board()


def target_from_board(board: Board) -> BoardTarget:
    """The configuration of ``board`` (inverse of :func:`board_from_target`)."""
    return board.target()
