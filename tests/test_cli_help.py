"""The CLI explains itself: `umad --version`, what each verb group does with an example, and the
steps `umad eval` runs."""

from __future__ import annotations

import platform
import re
from importlib import metadata

import pytest

from umad_common.cli import COMMANDS, GROUPS, main


def help_of(capsys, *words: str) -> str:
    with pytest.raises(SystemExit) as stop:
        main([*words, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


def test_version_names_umad_torch_and_zenoh(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == (
        f"umad {metadata.version('umad')} (torch {metadata.version('torch')}, "
        f"zenoh {metadata.version('eclipse-zenoh')}, python {platform.python_version()})\n"
    )


@pytest.mark.parametrize("group", sorted(GROUPS))
def test_every_verb_group_says_what_it_does_with_an_example(capsys, group):
    what, example = GROUPS[group]
    text = help_of(capsys, group)
    assert what in text and f"example: {example}" in text
    assert example.startswith(f"umad {group} ")


@pytest.mark.parametrize("words", sorted(COMMANDS))
def test_every_verb_gives_an_example(capsys, words):
    example = COMMANDS[words][2]
    assert example.startswith("umad " + " ".join(words) + " ")
    assert re.search(r"example: umad " + " ".join(words), help_of(capsys, *words))


def test_eval_help_lists_its_steps(capsys):
    text = help_of(capsys, "eval")
    assert [line[:2] for line in text.splitlines() if re.match(r"\d\. ", line)] == ["0.", "1.", "2.", "3."]
    assert "0. checks: every input" in text and "3. the sweep computes the paper's ablation table" in text
