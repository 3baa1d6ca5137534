"""UMAD's shared code: messages, bus, operator runtime, graph, launcher, datasets, models, metrics."""

from pathlib import Path

ASSETS = Path(__file__).resolve().parent / "assets"  # the shipped weights and calibration
DEFAULT_GRAPH = Path(__file__).resolve().parents[1] / "graph.yaml"  # the built-in graph, beside the package
