"""Every verb checks what it was given before it starts anything: one line naming the input, what was
wrong and what was expected, exit code 2, no process started, nothing written, within 2 s."""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, umad_env
from umad_common import ASSETS
from umad_common.cli import build_parser, main
from umad_common.commands.checks import InputError
from umad_common.commands.evaluate import check_inputs, every_and_layout

DRIVES_EXPECTED = (
    "expected drives: AnoVox Scenario_* folders, ROS 2 bags (a rosbag2 folder, .mcap or .db3), MCAPs with Foxglove "
    "schemas, or a folder of them; or anomalous/ and normal/"
)


def drive(folder: Path, *sensors: str) -> Path:
    """A drive folder of the benchmark layout with one (empty) file per sensor folder: the checks
    read listings, never pixels."""
    for sensor in ("RGB_IMG", *sensors):
        (folder / sensor).mkdir(parents=True)
        (folder / sensor / f"{sensor}_0.png").write_bytes(b"")
    return folder


@pytest.fixture
def refused(tmp_path, monkeypatch, capsys):
    """Runs `umad ARGS` in this process from an empty working folder; returns its stderr lines after
    checking the exit code is 2, it took under 2 s, no process was started and nothing was written."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)

    def no_process(*args, **kwargs):
        raise AssertionError(f"a process was started: {args}")

    monkeypatch.setattr(subprocess.Popen, "__init__", no_process)

    def run(*argv: str) -> list[str]:
        before = sorted(tmp_path.rglob("*"))
        started = time.perf_counter()
        code = main(list(argv))
        seconds = time.perf_counter() - started
        assert code == 2
        assert seconds < 2.0, f"{seconds:.1f} s"
        assert sorted(tmp_path.rglob("*")) == before
        return capsys.readouterr().err.splitlines()

    return run


def test_eval_refuses_a_data_folder_that_does_not_exist(refused, tmp_path):
    assert refused("eval", "--data", str(tmp_path / "none"), "--out", "out") == [
        f"umad eval: --data {tmp_path / 'none'}: no such folder or file; {DRIVES_EXPECTED} holding them as "
        "`umad generate synthetic` writes"
    ]


def test_eval_says_a_data_folder_has_only_normal_drives(refused, tmp_path):
    drive(tmp_path / "data" / "normal" / "Scenario_a", "SEMANTIC_IMG")
    [line] = refused("eval", "--data", str(tmp_path / "data"), "--out", "out")
    assert (
        f"--data {tmp_path / 'data'}: no anomalous drives: only normal ones (1 in normal/); {DRIVES_EXPECTED}" in line
    )


def test_eval_refuses_drives_without_labels(refused, tmp_path):
    drive(tmp_path / "data" / "Scenario_a", "SEMANTIC_IMG")
    drive(tmp_path / "data" / "Scenario_b")
    [line] = refused("eval", "--data", str(tmp_path / "data"), "--out", "out")
    assert "1 of 2 drives have no anomaly labels (e.g. Scenario_b); expected SEMANTIC_IMG/" in line


def test_eval_names_the_operators_that_run_without_lidar(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    drive(tmp_path / "data" / "anomalous" / "Scenario_a", "SEMANTIC_IMG", "PCD")
    drive(tmp_path / "data" / "anomalous" / "Scenario_b", "SEMANTIC_IMG")
    args = build_parser().parse_args(["eval", "--data", "data", "--out", "out"])
    args.every, _ = every_and_layout(args.protocol, args.every)
    assert check_inputs(args) == (tmp_path / "data" / "anomalous")
    assert capsys.readouterr().err.splitlines() == [
        "note: --data: 1 of 2 drives have no lidar (e.g. Scenario_b); these operators get empty point clouds "
        "there: segment_unsup, world_model"
    ]
    assert not (tmp_path / "out").exists()


def test_eval_refuses_a_model_without_its_record(refused, tmp_path):
    shutil.copy(ASSETS / "mnad.safetensors", tmp_path / "mnad.safetensors")
    assert refused("eval", "--mnad", str(tmp_path / "mnad.safetensors"), "--out", "out") == [
        f"umad eval: --mnad {tmp_path / 'mnad.json'}: no such file; expected the MNAD baseline: mnad.safetensors "
        "with its record mnad.json beside it"
    ]


def test_eval_refuses_a_weight_file_that_is_not_safetensors(refused, tmp_path):
    (tmp_path / "wm.safetensors").write_bytes(b"not a model")
    shutil.copy(ASSETS / "world_model.json", tmp_path / "wm.json")
    assert refused("eval", "--world-model", str(tmp_path / "wm.safetensors"), "--out", "out") == [
        f"umad eval: --world-model {tmp_path / 'wm.safetensors'}: not a safetensors file (no header); expected "
        "the world model as a safetensors file"
    ]


def test_eval_refuses_an_output_folder_under_a_file(refused, tmp_path):
    (tmp_path / "taken").write_text("")
    assert refused("eval", "--out", str(tmp_path / "taken" / "out")) == [
        f"umad eval: --out {tmp_path / 'taken' / 'out'}: {tmp_path / 'taken'} is a file; expected a folder path "
        "under a folder"
    ]


def test_eval_refuses_a_hub_port_in_use(refused):
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        assert refused("eval", "--hub", f"tcp/127.0.0.1:{port}", "--out", "out") == [
            f"umad eval: --hub tcp/127.0.0.1:{port}: port {port} is in use (another graph's hub, or one that did "
            "not stop); expected a free port: stop that graph, or pass --hub tcp/127.0.0.1:<another port>"
        ]


def test_launch_refuses_a_source_that_does_not_exist(refused, tmp_path):
    [line] = refused("launch", "--set", "replayer.source=TYPO")
    assert line.endswith(f"graph.yaml: operator 'replayer': source TYPO: not found at {tmp_path / 'work' / 'TYPO'}")


def test_graph_check_refuses_a_missing_graph(refused, tmp_path):
    assert refused("graph", "check", str(tmp_path / "g.yaml")) == [
        f"umad graph check: {tmp_path / 'g.yaml'}: graph file not found; expected a graph YAML file "
        "(see `umad graph check --help`)"
    ]


def test_launch_refuses_record_views_it_cannot_load(refused, tmp_path):
    """The recorder's views are named by import path: a wrong one is refused before anything starts."""
    text = (REPO / "graph.yaml").read_text().replace("\nname:", "\nrecord_views: nosuch.views:Views\nname:", 1)
    graph = tmp_path / "g.yaml"
    graph.write_text(text)
    [line] = refused("launch", str(graph), "--set", f"replayer.source={REPO / 'graph.yaml'}")
    assert line == (
        f"umad launch: {graph}: cannot import module 'nosuch.views' for record_views 'nosuch.views:Views': "
        "No module named 'nosuch'"
    )


def test_training_refuses_an_output_without_the_suffix(refused, tmp_path):
    drive(tmp_path / "data" / "Scenario_a")
    assert refused("train", "mnad", str(tmp_path / "data"), "--out", "mnad.pt") == [
        "umad train mnad: --out mnad.pt: has the suffix '.pt'; expected a file name ending '.safetensors'"
    ]


def test_sweep_and_compare_refuse_what_is_not_a_run(refused, tmp_path):
    (tmp_path / "run.mcap").write_text("text")
    assert refused("sweep", str(tmp_path / "run.mcap"), "--out", "report") == [
        f"umad sweep: log {tmp_path / 'run.mcap'}: not an MCAP file; expected an MCAP log written by "
        "`umad launch --record` or `umad eval` (OUT/run.mcap)"
    ]
    [line] = refused("compare", str(tmp_path), str(tmp_path))
    assert line.startswith(f"umad compare: RUN_A {tmp_path / 'results.json'}: no such file; expected an evaluation")


def test_an_input_error_is_one_line_naming_input_problem_and_expectation():
    assert str(InputError.of("--data d", "no such folder", "a folder")) == "--data d: no such folder; expected a folder"


def test_eval_with_a_missing_data_folder_exits_2_within_2_s_as_a_user_runs_it(tmp_path):
    """The whole command as a process: interpreter start, imports, parser, the check."""
    started = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-m", "umad_common.cli", "eval", "--data", str(tmp_path / "none")],
        capture_output=True,
        text=True,
        env=umad_env(),
        cwd=REPO,
        timeout=60,
    )
    seconds = time.perf_counter() - started
    assert (result.returncode, result.stdout, len(result.stderr.splitlines())) == (2, "", 1), result.stderr
    assert seconds < 2.0, f"{seconds:.1f} s"
