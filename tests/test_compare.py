"""`umad compare`: two reports side by side on small logs made with the sweep tests' helpers, and
the refusal when two runs did not score the same frames."""

from __future__ import annotations

import copy
import json

import pytest

from tests.test_sweep import synthetic_frames, write_log
from umad_common.cli import main as umad_main
from umad_common.viz.compare import frames_difference, load_results
from umad_common.viz.report import write_report
from umad_replay.sweep import sweep_log


def evaluation(tmp_path_factory, name: str, seed: int, n: int = 6):
    """A report folder from a synthetic log: `seed` changes the scores, `n` the frames per scenario."""
    base = tmp_path_factory.mktemp(name)
    write_log(base / "run.mcap", synthetic_frames(n=n, seed=seed))
    result = sweep_log(base / "run.mcap", progress=False, overlay_frames=0, components=False)
    write_report(result, base / "report", base / "run.mcap")
    return base / "report"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return {
        "a": evaluation(tmp_path_factory, "a", seed=0),
        "b": evaluation(tmp_path_factory, "b", seed=3),
        "short": evaluation(tmp_path_factory, "short", seed=0, n=5),
    }


def test_compare_writes_every_row_with_the_difference(runs, tmp_path, capsys):
    assert umad_main(["compare", str(runs["a"]), str(runs["b"] / "results.json"), "--out", str(tmp_path)]) == 0
    assert "the same 12 frames of 2 drives" in capsys.readouterr().out
    a, b = load_results(runs["a"]), load_results(runs["b"])
    markdown = (tmp_path / "compare.md").read_text()
    row_a = next(r for r in a["rows"] if r["weights_label"] == "abs" and r["masks"] == "no mask")
    row_b = next(r for r in b["rows"] if r["weights_label"] == "abs" and r["masks"] == "no mask")
    delta = 100 * (row_b["AP"] - row_a["AP"])
    cells = [
        c.strip()
        for c in next(line for line in markdown.splitlines() if line.startswith("| abs | no mask |")).split("|")
    ]
    assert cells[3] == f"{100 * row_a['AP']:.2f}" and cells[4].strip("*_") == f"{100 * row_b['AP']:.2f}"
    assert cells[5] == f"{delta:+.2f}"
    assert cells[4].startswith("**") == (delta > 0)  # marked where B is better
    assert markdown.count("\n| ") >= len(a["rows"]) + 1
    low_a, low_b = (
        next(s for s in r["headline"]["settings"] if s["masks"] == "no mask")["lowest_FPR95"] for r in (a, b)
    )
    lowest_line = next(
        line for line in markdown.splitlines() if line.startswith("| no mask |") and line.count("|") == 6
    )
    cells = [c.strip().strip("*_") for c in lowest_line.split("|")]
    assert cells[2] == f"{low_a['weights_label']} / {low_b['weights_label']}"
    assert cells[3:5] == [f"{100 * low_a['FPR95']:.2f}", f"{100 * low_b['FPR95']:.2f}"]
    assert low_a["FPR95"] != low_b["FPR95"] and cells[5] == f"{100 * (low_b['FPR95'] - low_a['FPR95']):+.2f}"
    page = (tmp_path / "compare.html").read_text()
    assert 'class="better num"' in page and "UMAD / MNAD (AP)" in page


def test_compare_prints_markdown_without_out(runs, capsys):
    assert umad_main(["compare", str(runs["a"]), str(runs["a"])]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# UMAD runs compared") and "Same data folder and models" in out
    assert "**" not in out.split("## Every ablation row")[1]  # a run against itself: nothing better


def test_compare_refuses_runs_of_different_frames(runs, capsys):
    assert umad_main(["compare", str(runs["a"]), str(runs["short"])]) == 1
    err = capsys.readouterr().err
    assert "did not score the same frames" in err and "scenario Scenario_a: A scored 6 frames, B 5" in err


def test_frames_difference_names_scenarios_and_every_k(runs):
    a = load_results(runs["a"])
    assert frames_difference(a, copy.deepcopy(a)) is None
    other = copy.deepcopy(a)
    other["protocol"]["sweep_every"] = 2
    assert frames_difference(a, other) == "A scored every frame, B one frame in every 2"
    other = copy.deepcopy(a)
    other["protocol"]["frames_evaluated"]["Scenario_c"] = other["protocol"]["frames_evaluated"].pop("Scenario_b")
    assert frames_difference(a, other) == "only A has 1 scenario(s): Scenario_b; only B has 1 scenario(s): Scenario_c"
    other = copy.deepcopy(a)
    other["protocol"]["frames_evaluated"]["Scenario_b"][2] = 7
    assert frames_difference(a, other) == "scenario Scenario_b: A scored 6 frames, B 6, first differing frame id 2"


def test_compare_names_a_folder_without_results(tmp_path, capsys):
    assert umad_main(["compare", str(tmp_path), str(tmp_path)]) == 2  # refused before reading anything
    assert f"RUN_A {tmp_path / 'results.json'}: no such file; expected an evaluation folder" in capsys.readouterr().err
    (tmp_path / "results.json").write_text(json.dumps({"rows": []}))
    assert umad_main(["compare", str(tmp_path), str(tmp_path)]) == 1
    assert "re-run `umad sweep`" in capsys.readouterr().err
