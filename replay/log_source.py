"""Frames of a recorded source, as the exact payload bytes it published: the input of `umad replay`."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from replay.log import LogError, read_log
from umad_common.bus import Keys
from umad_common.messages import MessageError, decode
from umad_common.operator import SourceFrame


def recorded_frames(
    path: str | Path, graph_name: str, op_id: str, outputs: tuple[str, ...], allow_truncated: bool = False
) -> Iterator[SourceFrame]:
    """Yield each recorded `(run, seq)` of `op_id` once, when all its outputs were read.

    Retransmissions in the log are skipped (first copy wins) and end-of-run markers are left to the
    source driver, which sends fresh ones after each run drains.
    """
    keys = Keys(graph_name)
    port_of = {keys.data(op_id, out): out for out in outputs}
    pending: dict[tuple[str, int], SourceFrame] = {}
    done: set[tuple[str, int]] = set()
    found = False
    for rec in read_log(path, allow_truncated):
        port = port_of.get(rec.topic)
        if port is None:
            continue
        found = True
        try:
            msg = decode(rec.data)
        except MessageError as exc:
            raise LogError(f"{path}: message on {rec.topic} is not a valid frame message: {exc}") from None
        key = (msg.run, msg.seq)
        if msg.meta.get("eos") or key in done:
            continue
        frame = pending.setdefault(key, SourceFrame(msg.run, msg.seq, msg.stamp_ns))
        frame.raw.setdefault(port, bytes(rec.data))
        if len(frame.raw) == len(outputs):
            done.add(key)
            yield pending.pop(key)
    if not found:
        raise LogError(f"{path}: no messages of operator {op_id!r} in graph {graph_name!r} (topics {sorted(port_of)})")
