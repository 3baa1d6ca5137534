"""Commands a replica takes on its control key (`umad set`, `umad op stop`), which only the `control`
certificate and the launcher may reach: each is applied between frames and answered with its
outcome. A rewind's resend request is no command: it has a key of its own (`service_messages.py`)."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from pydantic import ValidationError

from umad_common.dataflow.api.assignments import GraphError, merge_params

if TYPE_CHECKING:
    from umad_common.dataflow.process.runtime import OperatorRuntime


def apply_command(rt: OperatorRuntime, payload: bytes) -> dict[str, str]:
    """A stop or a parameter change; returns the outcome the asking command prints. A
    change that fails validation, needs an input the graph does not wire to this operator, or
    that the operator refuses (a weight file that does not load), is logged and counted; the old
    parameters stay."""
    try:
        command = json.loads(payload)
        if not isinstance(command, dict):
            raise TypeError(f"expected a JSON object with `set` or `stop`, got {type(command).__name__}")
        if command.get("stop"):
            rt.log.info("stop requested on the control key")
            rt.shutdown.set()
            return {"status": "stopping"}
        updates = command["set"]
        if not isinstance(updates, dict):
            raise TypeError(f"`set` must map parameter names to values, got {type(updates).__name__}")
        old = rt.operator.params
        params = old.model_dump()
        merge_params(params, updates)
        new = rt.cls.validate_params(params)
        unwired = rt.cls.wiring_problems(new, set(rt.spec.inputs))
        if unwired:  # e.g. a segmenter method that reads an input this operator is not wired to
            raise ValueError("; ".join(unwired))
    except (ValueError, KeyError, TypeError, ValidationError, GraphError) as exc:
        rt.stats.errors += 1
        rt.log.error("rejected parameter change %r: %s", payload[:200], exc)
        return {"status": "refused", "reason": one_line(exc)}
    try:
        rt.operator.update_params(new)
    except Exception as exc:  # the operator could not take the change: keep running as before
        rt.stats.errors += 1
        rt.log.error("parameter change %s refused by %s: %s; keeping the old parameters", updates, rt.op_id, exc)
        rt.operator.params = old
        return {"status": "refused", "reason": f"{type(exc).__name__}: {exc}"}
    rt.params_meta = rt.operator.params.model_dump(mode="json")
    rt.stats.param_changes += 1
    rt.log.info("parameters changed: %s", updates)
    return {"status": "applied"}


def one_line(exc: Exception) -> str:
    """An error as one line for a command's answer (a schema error lists each field on its own line)."""
    if isinstance(exc, ValidationError):
        return "; ".join(f"{'.'.join(str(x) for x in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors())
    return f"{type(exc).__name__}: {exc}".replace("\n", " ")
