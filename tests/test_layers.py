"""The layers of docs/architecture.md, read from the code's own imports (AST, every import,
also those inside functions): no circle between modules or packages, and neither the service,
the drivers nor the math imports the simulator."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calib", "drivers", "mocks", "service")
#: What each package may import (besides itself), from docs/architecture.md.
ALLOWED = {
    "calib": set(),
    "drivers": {"calib"},
    "mocks": {"calib", "drivers", "service"},
    "service": {"calib", "drivers"},
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(name: str, modules: set[str]) -> str | None:
    """The longest project module that ``name`` starts with."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The project modules ``path`` imports: ``from a.b import c`` is ``a.b.c`` if that is a
    module (a submodule), else ``a.b`` (a name defined there)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{alias.name}"
                     if f"{node.module}.{alias.name}" in modules else node.module
                     for alias in node.names]
        else:
            continue
        found.update(m for name in names if (m := _resolve(name, modules)) is not None)
    return found


def _graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports. A package's own ``__init__`` is left out of
    its submodules' imports: Python runs it before any of them anyway, so it is no edge."""
    files = {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    modules = set(files)
    return {m: {d for d in _imports(p, modules) if d != m and not m.startswith(f"{d}.")}
            for m, p in files.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path, or None (depth-first search, three colours)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state and (found := visit(nxt)) is not None:
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)) is not None:
            return found
    return None


def _package(module: str) -> str:
    return module.split(".")[0]


def test_no_import_circle_between_modules() -> None:
    assert _cycle(_graph()) is None


def test_no_import_circle_between_packages() -> None:
    packages: dict[str, set[str]] = {}
    for module, deps in _graph().items():
        packages.setdefault(_package(module), set()).update(
            _package(d) for d in deps if _package(d) != _package(module))
    assert _cycle(packages) is None, packages


@pytest.mark.parametrize("package", PACKAGES)
def test_packages_import_only_their_layers(package: str) -> None:
    wrong = {(m, d) for m, deps in _graph().items() if _package(m) == package
             for d in deps if _package(d) not in ALLOWED[package] | {package}}
    assert not wrong, sorted(wrong)


def test_the_checker_sees_a_circle() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_calib_is_used_through_its_public_surface() -> None:
    inner = {(m, d) for m, deps in _graph().items() if _package(m) != "calib"
             for d in deps if _package(d) == "calib" and d != "calib"}
    assert not inner, sorted(inner)


#: The one module that adds, merges or deletes rows (docs/architecture.md).
WRITER = ROOT / "service" / "store" / "writes.py"


def _session_writes(path: Path) -> list[str]:
    """``s.add(...)``, ``session.merge(...)`` and the like in ``path``: calls of a session's
    writing methods on a name that holds a session (``s``, ``session``)."""
    return [f"{path.relative_to(ROOT)}:{node.lineno}"
            for node in ast.walk(ast.parse(path.read_text(), str(path)))
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr in ("add", "add_all", "merge", "delete")
            and isinstance(node.func.value, ast.Name) and node.func.value.id in ("s", "session")]


def test_only_the_writer_adds_merges_or_deletes_rows() -> None:
    found = [hit for p in sorted((ROOT / "service").rglob("*.py")) if p != WRITER
             for hit in _session_writes(p)]
    assert not found, found
    assert _session_writes(WRITER), "the checker sees no write in the writer"
