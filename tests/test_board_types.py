"""A board type is one module of ``calib/boards`` (issue 12): its ``Board`` class and its
``BoardTarget`` join the one target union by themselves, every boundary parses that union,
and nothing outside ``calib`` names a board type or calls a detector by name (issue 9)."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest
from pydantic import ValidationError

import calib.boards.charuco
import calib.boards.checkerboard
from calib import BoardTarget, TargetAdapter, board_from_target, target_from_board
from calib.boards import TARGET_TYPES
from drivers.base import CellHints
from service.schemas import RunCreate
from service.settings import Settings
from service.stationsets.format import StationSet

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


#: Board configurations no cell has (issue 22, row 11): sizes outside 1 mm – 1 m, a marker
#: not smaller than its square, corner counts no board has.
BAD_TARGETS = [
    {"inner_corners": [9, 6], "square_size_m": 1e-320},
    {"inner_corners": [9, 6], "square_size_m": 0.0009},
    {"inner_corners": [9, 6], "square_size_m": 1.5},
    {"inner_corners": [9, 6], "square_size_m": -0.025},
    {"inner_corners": [9, 6], "square_size_m": 0},
    {"inner_corners": [1, 6], "square_size_m": 0.025},
    {"inner_corners": [9, 1000], "square_size_m": 0.025},
    {"inner_corners": [9, 6, 4], "square_size_m": 0.025},
    {**EXAMPLES["charuco"], "marker_size_m": 0.04},
    {**EXAMPLES["charuco"], "marker_size_m": 0.05},
    {**EXAMPLES["charuco"], "marker_size_m": 1e-320},
    {**EXAMPLES["charuco"], "square_size_m": 1e-320, "marker_size_m": 1e-321},
    {**EXAMPLES["charuco"], "square_size_m": 2.0, "marker_size_m": 1.5},
    {**EXAMPLES["charuco"], "squares": [2, 6]},
    {**EXAMPLES["charuco"], "squares": [8, 6000]},
]


@pytest.mark.parametrize("bad", BAD_TARGETS)
def test_each_boundary_refuses_a_board_no_cell_has(bad: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        TargetAdapter.validate_python(bad)
    with pytest.raises(ValidationError):
        RunCreate.model_validate({"stations": 5, "target": bad})
    with pytest.raises(ValidationError):
        StationSet.model_validate({
            "format": "cellcal/stations@1", "target": bad,
            "stations": [{"id": "000", "tcp_pose": [0.4, 0, 0.5, 3.1, 0, 0],
                          "image": "000.png"}]})
    with pytest.raises(ValidationError):
        Settings(data_dir=ROOT, target=bad)
    if "inner_corners" in bad:  # the older pair of settings
        with pytest.raises(ValidationError):
            Settings(data_dir=ROOT, target_inner_corners=bad["inner_corners"],
                     target_square_size_m=bad["square_size_m"])


@pytest.mark.parametrize("square_size_m", [1e-3, 1.0])
def test_the_bounds_themselves_are_boards(square_size_m: float) -> None:
    target = TargetAdapter.validate_python({"inner_corners": [9, 6],
                                            "square_size_m": square_size_m})
    assert board_from_target(target).kind == "checkerboard"
