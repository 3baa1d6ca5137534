"""Parameter assignments as the command line writes them (`OP.PARAM=VALUE`, for `--set` and
`umad set`), merging them into an operator's parameters, and the error every graph problem raises.
Only yaml is imported here: a command that steers a running graph parses its arguments without
importing the graph's operators (numpy, torch, ...), so it starts fast on a busy machine."""

from __future__ import annotations

from typing import Any

import yaml


class GraphError(ValueError):
    """graph.yaml is invalid; `problems` lists every culprit found."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("invalid graph:\n  - " + "\n  - ".join(problems))


def merge_params(target: dict[str, Any], updates: dict[str, Any]) -> None:
    """Merge `{"weights.ssim": 0.5}`-style dotted keys into a nested params dict."""
    for dotted, value in updates.items():
        node = target
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise GraphError([f"parameter {dotted!r}: {part!r} is not a mapping"])
        node[leaf] = value


def parse_sets(sets: list[str]) -> dict[str, dict[str, Any]]:
    """`["fusion.weights.ssim=0.5", ...]` -> `{"fusion": {"weights.ssim": 0.5}}` (the one `--set` parser)."""
    overrides: dict[str, dict[str, Any]] = {}
    for text in sets:
        op, param, value = parse_assignment(text)
        overrides.setdefault(op, {})[param] = value
    return overrides


def parse_assignment(text: str) -> tuple[str, str, Any]:
    """`OP.PARAM=VALUE` (PARAM may be dotted, VALUE is YAML) -> (op, param, value)."""
    key, sep, raw = text.partition("=")
    op, dot, param = key.partition(".")
    if not sep or not dot or not op or not param:
        raise GraphError([f"{text!r}: expected OP.PARAM=VALUE, e.g. fusion.weights.ssim=0.5"])
    return op, param, yaml.safe_load(raw)
