"""What the wheel carries and how the verbs find it: the package list in pyproject.toml covers every
folder of code and data, shipped files are found through the package (never the checkout), a user's
graph resolves its own relative paths, and an import path with the repository's folder name still
loads with a one-line notice. `.ci/wheel_smoke.sh` builds and runs the wheel itself."""

from __future__ import annotations

import logging
import os
import subprocess
import tomllib
from pathlib import Path

import pytest

from umad_common import ASSETS, DEFAULT_GRAPH, LIVE_GRAPH, SAM_ENV_SCRIPT, resolve_path, shipped_file
from umad_common.dataflow.api import plugins
from umad_common.dataflow.api.graph import graph_base_dir, is_builtin_graph
from umad_common.dataflow.api.operator import UnknownOperatorError, load_operator_class
from umad_operators.fusion import Fusion

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]


def installed_name(folder: Path) -> str:
    """The import name a folder of the repository installs under (pyproject's package-dir mapping)."""
    parts = folder.relative_to(REPO).parts
    by_folder = {source: name for name, source in PYPROJECT["package-dir"].items()}
    return ".".join((by_folder.get(parts[0], parts[0]), *parts[1:]))


def test_every_folder_of_code_or_data_is_a_listed_package():
    folders = {
        path.parent
        for top in ("umad_common", "operators", "replay")
        for path in (REPO / top).rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    assert sorted(installed_name(f) for f in folders) == sorted(PYPROJECT["packages"])


def test_no_installed_top_level_name_is_the_repository_folder():
    top_level = {name.split(".")[0] for name in PYPROJECT["packages"]}
    assert top_level == {"umad_common", "umad_operators", "umad_replay"}


def test_shipped_files_lie_in_the_package():
    for path in (ASSETS / "world_model.safetensors", DEFAULT_GRAPH, LIVE_GRAPH, SAM_ENV_SCRIPT):
        assert path.is_file() and path.is_relative_to(REPO / "umad_common"), path
    assert DEFAULT_GRAPH.resolve() == (REPO / "graph.yaml").resolve()  # the checkout's graph.yaml is the default


def test_a_shipped_path_resolves_to_the_package_file():
    assert shipped_file("umad_common/assets/mnad.safetensors") == ASSETS / "mnad.safetensors"
    assert shipped_file("umad_common/assets/no_such.safetensors") is None
    assert shipped_file("data/synthetic/anomalous") is None
    assert shipped_file("umad_common") is None


def test_a_graphs_relative_paths_resolve_against_its_folder_first(tmp_path):
    own = tmp_path / "umad_common" / "assets" / "mnad.safetensors"  # the user's file shadows the shipped one
    own.parent.mkdir(parents=True)
    own.write_bytes(b"")
    assert resolve_path("umad_common/assets/mnad.safetensors", tmp_path) == own
    assert resolve_path("umad_common/assets/world_model.safetensors", tmp_path) == ASSETS / "world_model.safetensors"
    assert resolve_path("data/drives", tmp_path) == tmp_path / "data" / "drives"  # missing: named where looked for
    assert resolve_path(tmp_path / "x", Path("/elsewhere")) == tmp_path / "x"


def test_a_builtin_graph_resolves_against_the_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    copy = tmp_path / "mine" / "graph.yaml"
    copy.parent.mkdir()
    copy.write_text(DEFAULT_GRAPH.read_text())
    assert is_builtin_graph(DEFAULT_GRAPH) and is_builtin_graph(REPO / "graph.yaml") and is_builtin_graph(LIVE_GRAPH)
    assert not is_builtin_graph(copy)
    assert graph_base_dir(DEFAULT_GRAPH, None) == tmp_path
    assert graph_base_dir(copy, None) == copy.parent
    assert graph_base_dir(copy, "..") == copy.parent / ".."


def test_an_old_import_path_loads_with_one_notice_naming_the_new(caplog, monkeypatch):
    monkeypatch.setattr(plugins, "_noticed", set())
    with caplog.at_level(logging.WARNING, logger="umad.plugins"):
        cls = load_operator_class(uses="operators.fusion:Fusion")
        assert load_operator_class(uses="operators.fusion:Fusion") is cls  # a graph is validated again: no notice
    assert cls is Fusion
    assert [r.getMessage() for r in caplog.records] == [
        "operator 'operators.fusion:Fusion': deprecated, package 'operators' is now 'umad_operators'; "
        "use 'umad_operators.fusion:Fusion'"
    ]


def test_a_current_import_path_loads_without_notice(caplog, monkeypatch):
    monkeypatch.setattr(plugins, "_noticed", set())
    with caplog.at_level(logging.WARNING, logger="umad.plugins"):
        assert load_operator_class(uses="umad_operators.fusion:Fusion") is Fusion
        with pytest.raises(UnknownOperatorError, match="umad_replay.nothing"):
            load_operator_class(uses="replay.nothing:Thing")
    assert len(caplog.records) == 1 and "'umad_replay.nothing:Thing'" in caplog.records[0].getMessage()


def test_the_sam_script_refuses_a_source_that_is_not_umad(tmp_path):
    result = subprocess.run(
        ["bash", str(SAM_ENV_SCRIPT), str(tmp_path / "venv"), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=30,
        env={**os.environ, "PYTHON": "false"},
    )
    assert result.returncode == 2
    assert f"UMAD_SOURCE {tmp_path}: expected a umad checkout" in result.stderr
    assert not (tmp_path / "venv").exists()
