"""What every delivery path does with a frame it decided to finish: run the operator on it (or pass
its marker on without computing), cache the result for a re-sent input, publish it, and ack it end
to end from a sink; and a run's end-of-run marker, which calls the operator's `end_run` once.

The delivery paths (`delivery/replay.py`, `delivery/ordered.py`, `delivery/live.py`) decide which
frames to finish and when; this module is the one place that finishes them (`FrameProcessor` fits
their `FrameFinisher`). It reaches the runtime only through `FrameHost`.
"""

from __future__ import annotations

import logging
import time
from typing import Protocol

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import Frame, Operator, Output
from umad_common.dataflow.delivery.joiner import OutputCache
from umad_common.dataflow.delivery.stats import Stats

COMPUTE_EMA = 0.2  # weight of the newest frame in the running mean of an operator's compute time


class FrameHost(Protocol):
    """What the frame processor uses of the runtime that runs it (`OperatorRuntime`): its id,
    counters and logger, whether it acks frames end to end (a sink), and encoding and publishing
    a frame's outputs."""

    op_id: str
    log: logging.Logger
    stats: Stats
    is_sink: bool

    def encode_outputs(
        self, run: str, seq: int, stamp_ns: int, outputs: dict[str, Output], extra_meta: dict
    ) -> list[tuple[str, bytes]]: ...

    def markers(self, run: str, seq: int, stamp_ns: int, meta: dict) -> list[tuple[str, bytes]]: ...

    def publish(self, payloads: list[tuple[str, bytes]], count: bool = True) -> None: ...

    def ack(self, run: str, seq: int) -> None: ...


class FrameProcessor:
    """Finishes the frames of one replica: computes, caches, publishes and acks them."""

    def __init__(self, host: FrameHost, operator: Operator, *, ordered: bool):
        """`ordered`: an in-order operator, which processes a skipped frame for its state."""
        self.host = host
        self.operator = operator
        self.ordered = ordered
        self.cache = OutputCache()  # recent outputs, re-published for a duplicate input
        self.ended: dict[str, list[tuple[str, bytes]]] = {}  # run -> its end-of-run payloads
        self.compute_s = 0.0  # running mean of the wall time `process` takes (live mode's catch-up)

    def answer_duplicate(self, key: tuple[str, int]) -> bool:
        """A frame this replica already finished came again (a re-send): re-publish its cached
        outputs, at most once a second, without computing. False when the frame is not cached."""
        if key not in self.cache:
            return False
        self.host.stats.duplicates += 1
        republish = self.cache.due_for_republish(key)
        if republish:
            self.publish_and_ack(key[0], key[1], republish)
        return True

    def finish(self, frame: Frame) -> None:
        """Process one joined frame (or pass on its marker: `marker_meta`), cache and publish the result."""
        self.host.stats.frames_in += 1
        payloads = self.payloads_for(frame)
        self.cache.put((frame.run, frame.seq), payloads)
        self.publish_and_ack(frame.run, frame.seq, payloads)

    def marker_meta(self, frame: Frame) -> dict | None:
        """The meta of the marker a frame is passed on as, without computing: an input's error, a
        superseded input (live mode: an operator before this one passed the frame over), or a skip
        for an operator that is not ordered (an in-order operator still processes a skipped frame
        for its state); None for a frame to compute."""
        received = frame_messages(frame)
        failed = [m for m in received if m.meta.get("error")]
        if failed:
            return {"error": failed[0].meta["error"]}
        if any(m.meta.get("superseded") for m in received):
            return {"superseded": True}
        if not self.ordered and any(m.meta.get("skip") for m in received):
            return {"skip": True}
        return None

    def payloads_for(self, frame: Frame) -> list[tuple[str, bytes]]:
        """A frame's outputs: a marker passed on (`marker_meta`), or what `process` returned (a skip
        marker for a skipped frame an in-order operator processed for its state), or the error it
        raised."""
        host = self.host
        marker = self.marker_meta(frame)
        if marker is not None:
            return host.markers(frame.run, frame.seq, frame.stamp_ns, marker)
        skipped = any(m.meta.get("skip") for m in frame_messages(frame))
        start, cpu_start = time.perf_counter(), time.process_time()
        try:
            outputs = self.operator.process(frame)
            host.stats.cpu_s += time.process_time() - cpu_start
            if host.stats.computed:  # an operator's first frame is start-up (first calls, memory): not counted
                took = time.perf_counter() - start
                self.compute_s = (1 - COMPUTE_EMA) * self.compute_s + COMPUTE_EMA * took if self.compute_s else took
            host.stats.computed += 1
            if skipped:  # an in-order operator saw the frame for its state; nobody scores it
                payloads = host.markers(frame.run, frame.seq, frame.stamp_ns, {"skip": True})
            else:
                payloads = host.encode_outputs(
                    frame.run, frame.seq, frame.stamp_ns, outputs, {"partial": True} if frame.partial else {}
                )
        except Exception as exc:  # one bad frame must not stop the operator
            host.stats.errors += 1
            host.log.exception("frame %s failed: %s", frame.frame_id, exc)
            payloads = host.markers(
                frame.run, frame.seq, frame.stamp_ns, {"error": f"{host.op_id}: {type(exc).__name__}: {exc}"}
            )
        host.stats.latency.add(time.perf_counter() - start)
        return payloads

    def end_run(self, msg: Message) -> list[tuple[str, bytes]] | None:
        """A run's end-of-run marker: call the operator's `end_run` once and return the marker's
        payloads, for the delivery path to publish once it has closed the run. A re-sent marker is
        answered here from what the first one published (None)."""
        host, run = self.host, msg.run
        if run in self.ended:
            if (run, msg.seq) not in self.cache:  # answer a re-sent marker at most once a second
                self.cache.put((run, msg.seq), self.ended[run])
            republish = self.cache.due_for_republish((run, msg.seq))
            if republish:
                self.publish_and_ack(run, msg.seq, republish)
            return None
        meta = {"eos": True, "frames": msg.meta.get("frames", msg.seq)}
        try:
            outputs = self.operator.end_run(run)
            payloads = host.encode_outputs(run, msg.seq, msg.stamp_ns, outputs, meta)
            covered = {p for p, _ in payloads}
            payloads += [(p, b) for p, b in host.markers(run, msg.seq, msg.stamp_ns, meta) if p not in covered]
        except Exception as exc:
            host.stats.errors += 1
            host.log.exception("end of run %s failed: %s", run, exc)
            payloads = host.markers(run, msg.seq, msg.stamp_ns, meta)
        self.ended[run] = payloads
        self.cache.put((run, msg.seq), payloads)
        self.cache.last_republish[(run, msg.seq)] = time.monotonic()
        return payloads

    def publish_and_ack(self, run: str, seq: int, payloads: list[tuple[str, bytes]]) -> None:
        """Publish a frame's (or an end-of-run marker's) payloads; a sink then acks it end to end."""
        self.host.publish(payloads)
        if self.host.is_sink:
            self.host.ack(run, seq)

    def pass_over(self, run: str, seq: int, stamp_ns: int) -> None:
        """Live mode: send a superseded marker for a frame this operator will not process (counted
        in `superseded`); it is cached like a finished frame, for a re-sent input."""
        host = self.host
        host.stats.superseded += 1
        payloads = host.markers(run, seq, stamp_ns, {"superseded": True})
        self.cache.put((run, seq), payloads)
        host.publish(payloads, count=False)
        if host.is_sink:
            host.ack(run, seq)


def frame_messages(frame: Frame) -> list[Message]:
    """Every input message of a joined frame, single and `many` ports alike."""
    return [*frame.inputs.values(), *(m for port in frame.many.values() for m in port.values())]
