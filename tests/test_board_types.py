"""A board type is one module of ``calib/boards`` (issue 12): its ``Board`` class and its
``BoardTarget`` join the one target union by themselves, every boundary parses that union,
and nothing outside ``calib`` names a board type or calls a detector by name (issue 9)."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

import calib.boards.charuco
import calib.boards.checkerboard
from calib import BoardTarget, TargetAdapter, board_from_target, target_from_board
from calib.boards import TARGET_TYPES
from drivers.base import CellHints
from service.schemas import RunCreate
from service.settings import Settings
from service.stationset import StationSet

ROOT = Path(__file__).resolve().parents[1]
#: One configuration of each board type.
EXAMPLES = {
    "checkerboard": {"inner_corners": [9, 6], "square_size_m": 0.025},
    "charuco": {"type": "charuco", "squares": [8, 6], "square_size_m": 0.04,
                "marker_size_m": 0.03, "dictionary": "DICT_5X5_100"},
}
#: What only ``calib.boards`` may name: the board classes, their configurations, detectors.
BOARD_NAMES = {"Checkerboard", "Charuco", "CheckerboardTarget", "CharucoTarget",
               "detect_checkerboard", "detect_charuco", "board_points"}


def test_every_board_module_joins_the_union_by_itself() -> None:
    defined = {model for module in (calib.boards.checkerboard, calib.boards.charuco)
               for _, model in inspect.getmembers(module, inspect.isclass)
               if issubclass(model, BoardTarget) and model.__module__ == module.__name__}
    assert set(TARGET_TYPES.values()) == defined
    assert list(TARGET_TYPES) == ["checkerboard", "charuco"]  # the default type first


@pytest.mark.parametrize("kind", list(EXAMPLES))
def test_each_boundary_parses_each_board_type(kind: str) -> None:
    target = TargetAdapter.validate_python(EXAMPLES[kind])
    assert target.type == kind and isinstance(target, TARGET_TYPES[kind])
    board = board_from_target(target)
    assert board.kind == kind and target_from_board(board) == target
    assert RunCreate.model_validate({"stations": 5, "target": EXAMPLES[kind]}).target == target
    dumped = TargetAdapter.dump_python(target, mode="json")
    station_set = StationSet.model_validate({
        "format": "cellcal/stations@1", "target": dumped,
        "stations": [{"id": "000", "tcp_pose": [0.4, 0, 0.5, 3.1, 0, 0], "image": "000.png"}]})
    assert station_set.target == target and station_set.model().target == target
    settings = Settings(data_dir=ROOT, target=dumped)
    assert settings.run_target() == target
    assert CellHints(target=target).target == target


def _names_used(path: Path) -> set[str]:
    """Names ``path`` imports or reads as attributes."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.Attribute):
            found.add(node.attr)
    return found


@pytest.mark.parametrize("package", ["service", "drivers"])
def test_no_board_type_is_named_outside_calib(package: str) -> None:
    named = {str(p.relative_to(ROOT)): sorted(_names_used(p) & BOARD_NAMES)
             for p in (ROOT / package).rglob("*.py")}
    assert {p: n for p, n in named.items() if n} == {}
