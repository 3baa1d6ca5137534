"""The dataflow engine: messages, the operator API, the bus and its payload rings, the runtime that
runs one operator, delivery (joining, acks, stats), the graph, the launcher, the hub and the MCAP log.

Operator authors import the operator API from here:

    from umad_common.dataflow import Context, Frame, Input, Operator, Output, Source, SourceFrame
    from umad_common.dataflow import JoinParams, SourceParams  # a joining operator's, a source's pacing
    from umad_common.dataflow import input_array  # an input's array, or MissingInputError naming it

The names load on first use, so `import umad_common.dataflow.transport.bus` (what `umad set` and `umad op`
need) does not import numpy or pydantic.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from umad_common.dataflow.api.operator import (
        Context,
        Frame,
        Input,
        MissingInputError,
        NoParams,
        Operator,
        Output,
        Source,
        SourceFrame,
        input_array,
    )
    from umad_common.dataflow.api.pacing import JoinParams, SourceParams

OPERATOR_API = {  # name -> the engine module that defines it
    "Context": "api.operator",
    "Frame": "api.operator",
    "Input": "api.operator",
    "MissingInputError": "api.operator",
    "input_array": "api.operator",
    "NoParams": "api.operator",
    "Operator": "api.operator",
    "Output": "api.operator",
    "Source": "api.operator",
    "SourceFrame": "api.operator",
    "JoinParams": "api.pacing",
    "SourceParams": "api.pacing",
}
__all__ = [
    "Context",
    "Frame",
    "Input",
    "JoinParams",
    "MissingInputError",
    "NoParams",
    "Operator",
    "Output",
    "Source",
    "SourceFrame",
    "SourceParams",
    "input_array",
]


def __getattr__(name: str) -> Any:
    if name in OPERATOR_API:
        return getattr(importlib.import_module(f"umad_common.dataflow.{OPERATOR_API[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
