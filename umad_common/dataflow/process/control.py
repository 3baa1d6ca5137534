"""Commands a replica takes on its control key (`umad set`, `umad op stop`), which only the `control`
certificate and the launcher may reach: each is applied between frames and answered with its
outcome. A rewind's resend request is no command: it has a key of its own (`service_messages.py`)."""

from __future__ import annotations

import json
import logging
import threading
from typing import Any, Protocol

from pydantic import ValidationError

from umad_common.dataflow.api.assignments import GraphError, merge_params
from umad_common.dataflow.api.graph import OperatorSpec
from umad_common.dataflow.api.operator import Operator
from umad_common.dataflow.delivery.stats import Stats


class ControlHost(Protocol):
    """What a command reads or changes of the replica that takes it (`OperatorRuntime`): its stop
    signal, its operator and parameters (checked against the operator's class and the inputs the
    graph wires to it), and its counters and logger."""

    op_id: str
    log: logging.Logger
    stats: Stats
    shutdown: threading.Event
    operator: Operator
    cls: type[Operator]  # the operator's class as the graph names it (a logged source's too)
    spec: OperatorSpec  # the operator's entry in the graph: its wired inputs
    params_meta: dict[str, Any]  # the parameters recorded in every output, set again after a change


def apply_command(host: ControlHost, payload: bytes) -> dict[str, str]:
    """A stop or a parameter change; returns the outcome the asking command prints. A
    change that fails validation, needs an input the graph does not wire to this operator, or
    that the operator refuses (a weight file that does not load), is logged and counted; the old
    parameters stay."""
    try:
        command = json.loads(payload)
        if not isinstance(command, dict):
            raise TypeError(f"expected a JSON object with `set` or `stop`, got {type(command).__name__}")
        if command.get("stop"):
            host.log.info("stop requested on the control key")
            host.shutdown.set()
            return {"status": "stopping"}
        updates = command["set"]
        if not isinstance(updates, dict):
            raise TypeError(f"`set` must map parameter names to values, got {type(updates).__name__}")
        old = host.operator.params
        params = old.model_dump()
        merge_params(params, updates)
        new = host.cls.validate_params(params)
        unwired = host.cls.wiring_problems(new, set(host.spec.inputs))
        if unwired:  # e.g. a segmenter method that reads an input this operator is not wired to
            raise ValueError("; ".join(unwired))
    except (ValueError, KeyError, TypeError, ValidationError, GraphError) as exc:
        host.stats.errors += 1
        host.log.error("rejected parameter change %r: %s", payload[:200], exc)
        return {"status": "refused", "reason": one_line(exc)}
    try:
        host.operator.update_params(new)
    except Exception as exc:  # the operator could not take the change: keep running as before
        host.stats.errors += 1
        host.log.error("parameter change %s refused by %s: %s; keeping the old parameters", updates, host.op_id, exc)
        host.operator.params = old
        return {"status": "refused", "reason": f"{type(exc).__name__}: {exc}"}
    host.params_meta = host.operator.params.model_dump(mode="json")
    host.stats.param_changes += 1
    host.log.info("parameters changed: %s", updates)
    return {"status": "applied"}


def one_line(exc: Exception) -> str:
    """An error as one line for a command's answer (a schema error lists each field on its own line)."""
    if isinstance(exc, ValidationError):
        return "; ".join(f"{'.'.join(str(x) for x in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors())
    return f"{type(exc).__name__}: {exc}".replace("\n", " ")
