"""Imports point one way: operators/ and replay/ build on umad_common; umad_common (outside the
CLI in commands/) imports neither, and the benchmarks the CLI runs do not import the CLI."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    """Every module a file imports at run time, at the top or inside a function (imports for type
    checkers only, under `if TYPE_CHECKING:`, do not count)."""
    names: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            return
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text()))
    return names


def offending(folder: str, forbidden: tuple[str, ...], skip: tuple[str, ...] = ()) -> dict[str, list[str]]:
    found = {}
    for path in sorted((REPO / folder).rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if rel.startswith(skip):
            continue
        bad = sorted(m for m in imported_modules(path) if any(m == f or m.startswith(f + ".") for f in forbidden))
        if bad:
            found[rel] = bad
    return found


@pytest.mark.parametrize(
    ("folder", "forbidden", "skip"),
    [
        (
            "umad_common",
            ("replay", "operators", "umad_common.commands"),
            ("umad_common/commands/", "umad_common/benchmarks/"),
        ),
        ("umad_common/benchmarks", ("replay", "umad_common.commands"), ()),
        ("operators", ("replay", "umad_common.commands"), ()),
    ],
)
def test_imports_point_one_way(folder, forbidden, skip):
    assert offending(folder, forbidden, skip) == {}
