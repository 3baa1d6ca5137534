"""Imports point one way: operators/ and replay/ (installed as umad_operators and umad_replay) build on
umad_common; umad_common (outside the CLI: cli.py and commands/) imports neither, and the benchmarks
the CLI runs do not import the CLI."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port
from umad_common.dataflow.api.plugins import RENAMED_PACKAGES

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
            ("umad_replay", "umad_operators", "umad_common.commands"),
            ("umad_common/cli.py", "umad_common/commands/", "umad_common/benchmarks/"),
        ),
        ("umad_common/benchmarks", ("umad_replay", "umad_common.commands"), ()),
        ("operators", ("umad_replay", "umad_common.commands"), ()),
    ],
)
def test_imports_point_one_way(folder, forbidden, skip):
    assert offending(folder, forbidden, skip) == {}


def test_no_module_imports_the_repository_folder_names():
    """operators/ and replay/ install as umad_operators and umad_replay: an import of the folder's
    name works in a checkout but not in an installed wheel."""
    old_names = tuple(RENAMED_PACKAGES)
    assert {
        folder: found
        for folder in ("umad_common", "operators", "replay", "tests")
        if (found := offending(folder, old_names))
    } == {}


def test_a_command_to_a_running_graph_imports_no_operator():
    """`umad set` / `umad op` start fast on a busy machine: they never import an operator, and with
    it torch or scikit-learn (that import took 25-50 s on 2 loaded cores), nor even numpy."""
    probe = (
        "import sys; from umad_common.cli import main; "
        f"code = main(['set', 'fusion.weights.abs=0.3', '--connect', 'tcp/127.0.0.1:{free_port()}']); "
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'sklearn', 'skimage', 'umad_operators', 'numpy')); "
        "print(code, heavy)"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.stdout.strip() == "1 []", out.stdout + out.stderr
    assert "no hub at tcp/127.0.0.1:" in out.stderr
