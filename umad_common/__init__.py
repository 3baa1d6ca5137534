"""UMAD's shared code: messages, bus, operator runtime, graph, launcher, datasets, models, metrics."""

from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]  # holds umad_common/, operators/, replay/ and graph.yaml
ASSETS = REPOSITORY / "umad_common" / "assets"  # the shipped weights and calibration
DEFAULT_GRAPH = REPOSITORY / "graph.yaml"  # the built-in graph, beside the package
LIVE_GRAPH = REPOSITORY / "umad_common" / "graphs" / "live.yaml"  # UMAD alone at 10 Hz (`umad launch --live`)


def recorded_path(path: str | Path) -> str:
    """A path as a file meant for others records it (a model's JSON record, a calibration, a report's
    protocol): relative to the working directory or the repository when it lies inside one of them,
    otherwise as the user named it. Never made absolute, so no record holds this machine's folders."""
    path = Path(path)
    if path.is_absolute():
        real = path.resolve()
        for root in (Path.cwd().resolve(), REPOSITORY):
            if real.is_relative_to(root):
                return real.relative_to(root).as_posix()
    return path.as_posix()
