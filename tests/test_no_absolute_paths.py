"""No tracked file holds an absolute path of the machine that wrote it.

Model records, calibrations and docs travel with every clone: a home, temporary or work folder of
one machine in them means nothing elsewhere and tells the world how that machine is laid out.
Records name paths relative to the repository or as the user named them (`recorded_path`).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from umad_common import recorded_path

REPO = Path(__file__).resolve().parents[1]
MACHINE_FOLDERS = ("work", "home", "root", "tmp", "Users")  # top-level folders of a Unix or macOS machine
ABSOLUTE_PATH = re.compile(
    r"(?<![\w.~$-])/(?:" + "|".join(MACHINE_FOLDERS) + r")/"  # a machine folder at the root, not data/home/
    r"|(?<![\w])[A-Z]:\\{1,2}(?=[A-Za-z])"  # a Windows drive letter, one or two backslashes, a folder
)
BINARY_SUFFIXES = (".safetensors", ".png", ".jpg", ".jpeg", ".mcap", ".pt", ".pth", ".npy", ".npz", ".gz", ".zip")


def absolute_paths(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line of `text` that holds an absolute machine path."""
    return [(number, line.strip()) for number, line in enumerate(text.splitlines(), 1) if ABSOLUTE_PATH.search(line)]


def tracked_text_files() -> list[Path]:
    """The repository's tracked files that are text (binary suffixes and files with a NUL byte skipped)."""
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip(f"{REPO}: not a git checkout; the tracked files cannot be listed")
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    files = []
    for name in listed.decode().split("\0"):
        path = REPO / name
        if not name or name.endswith(BINARY_SUFFIXES) or not path.is_file():
            continue
        if b"\0" in path.read_bytes()[:8192]:
            continue
        files.append(path)
    return files


def test_no_tracked_file_holds_an_absolute_machine_path():
    offenders = [
        f"{path.relative_to(REPO)}:{number}: {line}"
        for path in tracked_text_files()
        for number, line in absolute_paths(path.read_text(encoding="utf-8", errors="replace"))
    ]
    assert not offenders, (
        "absolute paths of a machine in tracked files; record them relative to the repository or as "
        "the user named them (umad_common.recorded_path):\n" + "\n".join(offenders)
    )


@pytest.mark.parametrize(
    "line",
    [
        '"data": "' + "/" + "work/data/synth" + '",',
        "features at " + "/" + "home/alice/umad/feature_net.safetensors",
        "hub: unixsock-stream/" + "/" + "tmp/umad.sock",
        "cd " + "/" + "Users/bob/umad",
        '"data": "C:' + "\\\\" + "Users" + "\\\\" + "carol" + "\\\\" + 'synth"',
        "copied from C:" + "\\" + "data" + "\\" + "synth",
    ],
)
def test_an_absolute_machine_path_is_found(line):
    assert absolute_paths(f"first line\n{line}\n") == [(2, line)]


@pytest.mark.parametrize(
    "line",
    [
        '"data": "data/synth",',
        "umad_common/assets/feature_net.safetensors",
        "$TMPDIR/umad-eval and ~/umad",
        "see https://example.org/home/page and docs/work/notes.md",
        'print(f"{name}:\\n")',
        "ratio 1.02x; a:b",
    ],
)
def test_relative_paths_and_urls_pass(line):
    assert absolute_paths(line) == []


def test_recorded_path_is_relative_inside_the_repository_and_as_named_outside(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert recorded_path(tmp_path / "data" / "synth") == "data/synth"  # inside the working directory
    assert recorded_path(REPO / "umad_common" / "assets" / "feature_net.safetensors") == (
        "umad_common/assets/feature_net.safetensors"
    )  # inside the repository
    assert recorded_path("data/synth") == "data/synth"  # relative: as named, not resolved
    assert recorded_path("../elsewhere/synth") == "../elsewhere/synth"
    outside = tmp_path.parent / "elsewhere"
    assert recorded_path(outside) == str(outside)  # outside both: as named
