"""Which producers a joining operator's wildcard (`many`) ports wait for: the live operators whose
outputs match a port's wiring. The runtime works this out again only when the live membership
changes, never per frame, and hands it to the joiner with every `pop_ready`."""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable

from umad_common.dataflow.api.graph import Graph, OperatorSpec
from umad_common.dataflow.api.operator import Input


def expected_producers(
    graph: Graph, spec: OperatorSpec, inputs: Iterable[Input], live_ops: Iterable[str]
) -> dict[str, set[str]]:
    """For each `many` port among `inputs` (the operator's declared ports, wired by `spec`), the
    operators of `live_ops` that publish on one of the port's wiring patterns."""
    live_ops = list(live_ops)
    expected = {}
    for port in inputs:
        if port.many:
            expected[port.name] = {
                op
                for op in live_ops
                if not op.startswith("_")  # the recorder's token: a consumer, never a producer
                and any(produces(graph, op, src) for src in spec.sources_of(port.name))
            }
    return expected


def produces(graph: Graph, op: str, source: str) -> bool:
    """Whether operator `op` publishes on wiring pattern `source`; an operator this graph file
    does not know (started from another file) is matched by its id alone."""
    if op in graph.classes:
        return any(p == op for p, _ in graph.producers(source))
    return fnmatch.fnmatchcase(op, source.partition("/")[0])
