"""Frames of a recorded source, as the exact payload bytes it published: the input of `umad replay`."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from pydantic import BaseModel

from umad_common.dataflow.api.messages import MessageError, decode
from umad_common.dataflow.api.operator import Context, Source, SourceFrame
from umad_common.dataflow.record.mcap_log import LogError, read_log
from umad_common.dataflow.transport.bus import Keys


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


def recorded_frame(
    path: str | Path, graph_name: str, op_id: str, outputs: tuple[str, ...], run: str, seq: int, cache: dict
) -> SourceFrame:
    """Frame `run#seq` of a recorded source. The first request of a run reads the log once and
    keeps that run's frames in `cache` (a restarted world model asks for a run's frames in a row)."""
    if run not in cache:
        cache.clear()
        cache[run] = {f.seq: f for f in recorded_frames(path, graph_name, op_id, outputs, True) if f.run == run}
    try:
        return cache[run][seq]
    except KeyError:
        raise KeyError(f"{path}: frame {run}#{seq} of {op_id!r} is not in the log") from None


class LoggedSource(Source):
    """Stands in for a graph's source during `umad replay`: its recorded frames, byte for byte.

    It takes the source's parameters (for pacing: window, acks, rate) but never builds the
    recorded operator, so a log replays without the dataset or device it was recorded from.
    """

    def __init__(
        self,
        path: str | Path,
        recorded: type[Source],
        *,
        params: BaseModel,
        context: Context,
        allow_truncated: bool,
    ):
        self.context, self.params = context, params  # the recorded source's parameters, validated
        self.path, self.allow_truncated = Path(path), allow_truncated
        self.outputs = recorded.outputs
        self._run_cache: dict = {}

    def frames(self) -> Iterator[SourceFrame]:
        c = self.context
        return recorded_frames(self.path, c.graph_name, c.op_id, self.outputs, self.allow_truncated)

    def frame_at(self, run: str, seq: int) -> SourceFrame:
        c = self.context
        return recorded_frame(self.path, c.graph_name, c.op_id, self.outputs, run, seq, self._run_cache)
