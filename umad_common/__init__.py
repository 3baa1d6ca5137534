"""UMAD's shared code: messages, bus, operator runtime, graph, launcher, datasets, models, metrics.

The files the verbs need beside the code (the built-in graphs, the shipped models, the report
templates, the SAM environment script) are package data, found through `importlib.resources`: the
same names work in a checkout, an editable install and an installed wheel.
"""

from importlib.resources import files
from pathlib import Path

PACKAGE_NAME = "umad_common"


def _package_folder() -> Path:
    """The folder of this package on disk; shipped files are read by path (weights, graphs)."""
    folder = files(PACKAGE_NAME)
    if not isinstance(folder, Path):
        raise ImportError(f"{PACKAGE_NAME}: installed as {folder!r}; expected a folder on disk (install unzipped)")
    return folder


PACKAGE = _package_folder()
ASSETS = PACKAGE / "assets"  # the shipped weights and calibration
DEFAULT_GRAPH = PACKAGE / "graphs" / "graph.yaml"  # the built-in graph (in a checkout, the top-level graph.yaml)
LIVE_GRAPH = PACKAGE / "graphs" / "live.yaml"  # UMAD alone at 10 Hz (`umad launch --live`)
SAM_ENV_SCRIPT = PACKAGE / "scripts" / "sam_env.sh"  # builds the `sam` segmenter's own environment


def shipped_file(path: str | Path) -> Path | None:
    """The shipped file a relative path such as `umad_common/assets/mnad.safetensors` names (as seen
    from the folder holding the package), or None when the package ships no such file."""
    parts = Path(path).parts
    if len(parts) < 2 or parts[0] != PACKAGE_NAME:
        return None
    candidate = PACKAGE.joinpath(*parts[1:])
    return candidate if candidate.exists() else None


def resolve_path(path: str | Path, base_dir: Path) -> Path:
    """A path from a graph's parameters: absolute; else relative to `base_dir` (the graph's folder)
    when it exists there; else the shipped file it names (`umad_common/assets/...` from any graph);
    else relative to `base_dir`, so a missing file's error names where it was looked for."""
    p = Path(path).expanduser()
    if p.is_absolute():
        return p
    local = base_dir / p
    if local.exists():
        return local
    return shipped_file(p) or local


def recorded_path(path: str | Path) -> str:
    """A path as a file meant for others records it (a model's JSON record, a calibration, a report's
    protocol): relative to the working directory or the folder holding the package when it lies
    inside one of them (so a shipped model reads `umad_common/assets/...` installed or not),
    otherwise as the user named it. Never made absolute, so no record holds this machine's folders."""
    path = Path(path)
    if path.is_absolute():
        real = path.resolve()
        for root in (Path.cwd().resolve(), PACKAGE.resolve().parent):
            if real.is_relative_to(root):
                return real.relative_to(root).as_posix()
    return path.as_posix()
