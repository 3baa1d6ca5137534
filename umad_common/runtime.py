"""The operator runtime: one process runs one replica of one operator from the graph.

It owns everything an operator module should not have to write: the Zenoh session, joining inputs by
`(run, seq)`, in-order delivery, the replica split, the output cache that answers retransmissions,
end-to-end acks, end-of-run markers, stats, runtime parameter changes, and a clean shutdown.

Delivery protocol (lossless by design):
  - a source keeps at most `window` frames in flight and forgets a frame once every sink of the
    graph has acked it; an un-acked frame is re-sent after a timeout (at-least-once);
  - every operator caches its recent outputs, so a re-sent input re-publishes the cached output
    instead of recomputing (exactly-once effect, state untouched);
  - a frame whose processing raised travels on as an error marker (meta `error`), so sinks still
    ack it and the stream never stalls on it;
  - after the last frame of a run is acked the source sends an end-of-run marker (meta `eos`),
    which each operator passes on after calling its `end_run`.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import logging
import os
import queue
import sys
import threading
import time
from collections import OrderedDict, defaultdict, deque
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zenoh
from pydantic import ValidationError

from replay.log import LogError
from umad_common.bus import Keys, ShutdownSignal, close_session, open_client
from umad_common.graph import Graph, GraphError, load_graph, merge_params, parse_assignment
from umad_common.messages import Message, MessageError, decode, encode
from umad_common.operator import Context, Frame, Operator, Output, Source, SourceFrame

log = logging.getLogger("umad.runtime")

OUTPUT_CACHE_FRAMES = 64
MAX_PENDING_FRAMES = 256
REPUBLISH_INTERVAL_S = 1.0
STATS_INTERVAL_S = 1.0
BAD_MESSAGE_LOG_FIRST = 10  # malformed messages logged one by one; later ones are summarised
BAD_MESSAGE_LOG_INTERVAL_S = 5.0
LIVE_WAIT_S = 60.0
LOST_GRACE_S = 15.0
REWIND_RETRY_S = 10.0
EXIT_CONFIG = 3  # an operator that exits with this failed on its configuration: restarting cannot help


class LatencyWindow:
    """The last N latencies, for p50/p99 in stats."""

    def __init__(self, size: int = 1000):
        self.values: deque[float] = deque(maxlen=size)

    def add(self, seconds: float) -> None:
        self.values.append(seconds)

    def percentiles_ms(self) -> dict[str, float | None]:
        if not self.values:
            return {"p50_ms": None, "p99_ms": None}
        arr = np.fromiter(self.values, dtype=np.float64) * 1e3
        return {"p50_ms": float(np.percentile(arr, 50)), "p99_ms": float(np.percentile(arr, 99))}


@dataclass
class Stats:
    frames_in: int = 0
    frames_out: int = 0
    errors: int = 0
    bad_messages: int = 0
    duplicates: int = 0
    dropped: int = 0
    retransmits: int = 0
    param_changes: int = 0
    busy_s: float = 0.0  # sources: first send to last ack
    acked: int = 0  # sources: frames every sink has acked
    total_frames: int | None = None  # sources: frames the stream will have, when known
    latency: LatencyWindow = field(default_factory=LatencyWindow)

    def snapshot(self, queue_depth: int) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "latency"}
        return {**d, **self.latency.percentiles_ms(), "queue_depth": queue_depth}


@dataclass
class _Pending:
    first_seen: float
    stamp_ns: int
    single: dict[str, Message] = field(default_factory=dict)
    many: dict[str, dict[str, Message]] = field(default_factory=lambda: defaultdict(dict))


class FrameJoiner:
    """Collects the inputs of each `(run, seq)` and hands out complete frames.

    A frame is complete when every single port has its message and every `many` port has a message
    from each producer expected right now (the live operators matching its wildcard). With a
    deadline, a frame that waited longer is handed out as partial. At most `max_pending` frames
    wait; beyond that the oldest is dropped and counted (the source's retransmission recovers it).
    """

    def __init__(self, single_ports: list[str], many_ports: list[str], max_pending: int = MAX_PENDING_FRAMES):
        self.single_ports = single_ports
        self.many_ports = many_ports
        self.max_pending = max_pending
        self.pending: OrderedDict[tuple[str, int], _Pending] = OrderedDict()
        self.dropped = 0

    def add(self, port: str, producer: str, msg: Message) -> None:
        key = (msg.run, msg.seq)
        entry = self.pending.get(key)
        if entry is None:
            entry = self.pending[key] = _Pending(time.monotonic(), msg.stamp_ns)
            if len(self.pending) > self.max_pending:
                self.pending.popitem(last=False)
                self.dropped += 1
        if port in self.many_ports:
            entry.many[port][producer] = msg
        else:
            entry.single[port] = msg

    def discard(self, key: tuple[str, int]) -> None:
        self.pending.pop(key, None)

    def pop_ready(self, expected: dict[str, set[str]], deadline_s: float = 0.0) -> list[Frame]:
        now = time.monotonic()
        ready = []
        for key, entry in list(self.pending.items()):
            if len(entry.single) < len(self.single_ports):
                continue
            complete = all(entry.many[p] and expected.get(p, set()) <= set(entry.many[p]) for p in self.many_ports)
            late = (
                deadline_s > 0 and now - entry.first_seen > deadline_s and all(entry.many[p] for p in self.many_ports)
            )
            if complete or late:
                del self.pending[key]
                ready.append(
                    Frame(
                        run=key[0],
                        seq=key[1],
                        stamp_ns=entry.stamp_ns,
                        inputs=dict(entry.single),
                        many={p: dict(entry.many[p]) for p in self.many_ports},
                        partial=not complete,
                    )
                )
        return ready


class Membership:
    """Which replicas of which operators are in the graph now, from liveliness tokens.

    A token that vanishes without a goodbye (a crash, or the hub restarting under everyone) is kept
    for `grace_s`: waiting a little for a restarted replica beats completing frames without its
    output. A replica that stops on purpose says so on the `_left` key first and drops out at once.
    """

    def __init__(self, grace_s: float = LOST_GRACE_S):
        self.grace_s = grace_s
        self.live: dict[str, set[str]] = defaultdict(set)
        self.lost: dict[tuple[str, str], float] = {}
        self.left: set[tuple[str, str]] = set()

    def put(self, op: str, rep: str) -> None:
        self.live[op].add(rep)
        self.lost.pop((op, rep), None)
        self.left.discard((op, rep))

    def delete(self, op: str, rep: str) -> None:
        self.live[op].discard(rep)
        if (op, rep) in self.left:
            self.left.discard((op, rep))
        else:
            self.lost[(op, rep)] = time.monotonic()

    def leave(self, op: str, rep: str) -> None:
        if self.lost.pop((op, rep), None) is None:
            self.left.add((op, rep))

    def expire(self) -> bool:
        """Forget replicas lost longer than the grace period; True if any was forgotten."""
        now = time.monotonic()
        gone = [k for k, t in self.lost.items() if now - t > self.grace_s]
        for k in gone:
            del self.lost[k]
        return bool(gone)

    def replicas(self, op: str) -> set[str]:
        return self.live.get(op, set()) | {rep for (o, rep) in self.lost if o == op}

    def ops(self) -> set[str]:
        return {op for op, reps in self.live.items() if reps} | {op for op, _ in self.lost}


class OutputCache:
    """Recent outputs by `(run, seq)`: a duplicate input re-publishes these bytes, never recomputes."""

    def __init__(self, size: int = OUTPUT_CACHE_FRAMES):
        self.size = size
        self.entries: OrderedDict[tuple[str, int], list[tuple[str, bytes]]] = OrderedDict()
        self.last_republish: dict[tuple[str, int], float] = {}

    def __contains__(self, key: tuple[str, int]) -> bool:
        return key in self.entries

    def put(self, key: tuple[str, int], payloads: list[tuple[str, bytes]]) -> None:
        self.entries[key] = payloads
        while len(self.entries) > self.size:
            old, _ = self.entries.popitem(last=False)
            self.last_republish.pop(old, None)

    def due_for_republish(self, key: tuple[str, int]) -> list[tuple[str, bytes]]:
        """The cached payloads, at most once per REPUBLISH_INTERVAL_S per frame (one duplicate per port arrives)."""
        now = time.monotonic()
        if now - self.last_republish.get(key, 0.0) < REPUBLISH_INTERVAL_S:
            return []
        self.last_republish[key] = now
        return self.entries[key]


class OperatorRuntime:
    """Runs one replica of one operator of `graph` on a connected Zenoh session."""

    def __init__(
        self,
        graph: Graph,
        op_id: str,
        replica: int,
        session: zenoh.Session,
        shutdown: threading.Event,
        max_frames: int | None = None,
        replay_log: str | None = None,
        allow_truncated: bool = False,
    ):
        self.graph = graph
        self.replay_log = replay_log
        self.allow_truncated = allow_truncated
        self.spec = graph.op(op_id)
        self.cls = graph.classes[op_id]
        self.op_id = op_id
        self.replica = replica
        self.replica_id = f"r{replica}"
        self.session = session
        self.shutdown = shutdown
        self.max_frames = max_frames
        self.keys = Keys(graph.name)
        self.stats = Stats()
        self.log = logging.getLogger(f"umad.{op_id}")
        context = Context(op_id, replica, graph.name, graph.base_dir, self.log)
        if replay_log and issubclass(self.cls, Source):
            from replay.log_source import LoggedSource

            params = self.cls.validate_params(self.spec.params)
            self.operator: Operator = LoggedSource(replay_log, self.cls, params, context, allow_truncated)
        else:
            self.operator = self.cls(self.spec.params, context)
        self.data_q: queue.Queue = queue.Queue(maxsize=64)
        self.ctl_q: queue.Queue = queue.Queue()
        self.members = Membership()
        self.resend_requests: list[dict] = []  # sources: frames a restarted ordered operator needs again
        self._rewinds: dict[str, float] = {}  # ordered operators: run -> when frames were last re-requested
        self.publishers = {
            out: session.declare_publisher(self.keys.data(op_id, out), congestion_control=zenoh.CongestionControl.BLOCK)
            for out in self.cls.outputs
        }
        self.ack_pub = session.declare_publisher(self.keys.ack, congestion_control=zenoh.CongestionControl.BLOCK)
        self.stats_pub = session.declare_publisher(
            self.keys.stats(op_id, self.replica_id), congestion_control=zenoh.CongestionControl.DROP
        )
        self.joiner = FrameJoiner(
            [p.name for p in self.cls.inputs if not p.many], [p.name for p in self.cls.inputs if p.many]
        )
        self._subscribers: list[Any] = []
        self._last_stats = 0.0
        self._last_bad_log = 0.0

    # -- wiring -----------------------------------------------------------------------------------

    def _subscribe_inputs(self) -> None:
        for port in self.spec.inputs:
            for source in self.spec.sources_of(port):
                self._subscribers.append(
                    self.session.declare_subscriber(
                        self.keys.pattern(source), lambda s, port=port: self.data_q.put((port, s))
                    )
                )

    def _subscribe_service(self) -> None:
        self._subscribers.append(
            self.session.declare_subscriber(self.keys.control(self.op_id), lambda s: self.ctl_q.put(("ctl", s)))
        )
        self._subscribers.append(self.session.declare_subscriber(self.keys.left, lambda s: self.ctl_q.put(("left", s))))
        self._subscribers.append(
            self.session.liveliness().declare_subscriber(
                self.keys.live_all, lambda s: self.ctl_q.put(("live", s)), history=True
            )
        )

    @property
    def is_sink(self) -> bool:
        return self.op_id in self.graph.sinks()

    def _owns(self, seq: int) -> bool:
        """Replicas split frames by seq over the sorted live replica set."""
        replicas = sorted(self.members.replicas(self.op_id) | {self.replica_id})
        if len(replicas) == 1:
            return True
        return replicas[seq % len(replicas)] == self.replica_id

    def _produces(self, op: str, source: str) -> bool:
        """Whether operator `op` publishes on wiring pattern `source`; an operator this graph file
        does not know (started from another file) is matched by its id alone."""
        if op in self.graph.classes:
            return any(p == op for p, _ in self.graph.producers(source))
        return fnmatch.fnmatchcase(op, source.partition("/")[0])

    def _expected(self) -> dict[str, set[str]]:
        expected = {}
        for port in self.cls.inputs:
            if port.many:
                expected[port.name] = {
                    op
                    for op in self.members.ops()
                    if any(self._produces(op, src) for src in self.spec.sources_of(port.name))
                }
        return expected

    # -- service messages ---------------------------------------------------------------------------

    def _handle_service(self) -> bool:
        """Apply queued control and liveliness events; True when the set of live operators changed."""
        changed = self.members.expire()
        while True:
            try:
                kind, sample = self.ctl_q.get_nowait()
            except queue.Empty:
                return changed
            if kind == "live":
                op, rep = self.keys.parse_live(str(sample.key_expr))
                if sample.kind == zenoh.SampleKind.PUT:
                    self.members.put(op, rep)
                else:
                    self.members.delete(op, rep)
                changed = True
            elif kind == "left":
                try:
                    note = msgpack.unpackb(sample.payload.to_bytes())
                    self.members.leave(str(note["op"]), str(note["replica"]))
                    changed = True
                except Exception:
                    self.stats.bad_messages += 1
            else:
                self._apply_control(sample.payload.to_bytes())

    def _apply_control(self, payload: bytes) -> None:
        """Stop, resend or a parameter change. A change that fails validation, or that the operator
        refuses (a weight file that does not load), is logged and counted; the old parameters stay."""
        try:
            command = json.loads(payload)
            if not isinstance(command, dict):
                raise TypeError(f"expected a JSON object with `set`, `stop` or `resend`, got {type(command).__name__}")
            if command.get("stop"):
                self.log.info("stop requested on the control key")
                self.shutdown.set()
                return
            if "resend" in command:
                self.resend_requests.append(command["resend"])
                return
            updates = command["set"]
            if not isinstance(updates, dict):
                raise TypeError(f"`set` must map parameter names to values, got {type(updates).__name__}")
            old = self.operator.params
            params = old.model_dump()
            merge_params(params, updates)
            new = self.cls.validate_params(params)
        except (ValueError, KeyError, TypeError, ValidationError, GraphError) as exc:
            self.stats.errors += 1
            self.log.error("rejected parameter change %r: %s", payload[:200], exc)
            return
        try:
            self.operator.update_params(new)
        except Exception as exc:  # the operator could not take the change: keep running as before
            self.stats.errors += 1
            self.log.error(
                "parameter change %s refused by %s: %s; keeping the old parameters", updates, self.op_id, exc
            )
            self.operator.params = old
            return
        self.stats.param_changes += 1
        self.log.info("parameters changed: %s", updates)

    def _live_mode(self) -> bool:
        """Live (a source paces in real time): joins may give up at their deadline. Lossless (the
        default): every expected input is waited for."""
        return any(self.graph.op(src).params.get("pacing") == "realtime" for src in self.graph.sources())

    def _request_rewind(self, run: str, seq: int) -> None:
        """An ordered operator that (re)started mid-run rebuilds its state by re-observing the run
        from its first frame: ask the sources to send frames [0, seq) again. Every other consumer
        sees those as duplicates and answers from its cache."""
        now = time.monotonic()
        if now - self._rewinds.get(run, -1e9) < REWIND_RETRY_S:
            return
        self._rewinds[run] = now
        self.log.warning(
            "frame %s#%d arrived without the frames before it: asking the sources to resend them", run, seq
        )
        for source in self.graph.sources():
            request = {"resend": {"run": run, "from": 0, "to": seq, "for": self.op_id}}
            self.session.put(self.keys.control(source), json.dumps(request))

    def _publish_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_stats >= STATS_INTERVAL_S:
            self._last_stats = now
            self.stats.dropped = self.joiner.dropped
            snap = self.stats.snapshot(self.data_q.qsize())
            self.stats_pub.put(json.dumps({"op": self.op_id, "replica": self.replica_id, **snap}).encode())

    def _warn_bad_message(self, key: str, exc: MessageError) -> None:
        """Log the first few malformed messages in full, then one summary line per interval: a flood
        of garbage must not turn into a flood of log lines (stats count every one)."""
        now = time.monotonic()
        if self.stats.bad_messages <= BAD_MESSAGE_LOG_FIRST:
            self.log.warning("bad message on %s: %s", key, exc)
        elif now - self._last_bad_log >= BAD_MESSAGE_LOG_INTERVAL_S:
            self.log.warning("%d bad messages so far; latest on %s: %s", self.stats.bad_messages, key, exc)
            self._last_bad_log = now

    # -- publishing ---------------------------------------------------------------------------------

    def _encode_outputs(
        self, run: str, seq: int, stamp_ns: int, outputs: dict[str, Output], extra_meta: dict
    ) -> list[tuple[str, bytes]]:
        payloads = []
        params = self.operator.params.model_dump(mode="json")
        for port, out in outputs.items():
            if port not in self.publishers:
                raise ValueError(f"operator returned output {port!r}; it declares {list(self.cls.outputs)}")
            meta = {**out.meta, **extra_meta, "params": params}
            msg = Message(run, seq, stamp_ns, self.op_id, meta, out.arrays)
            payloads.append((port, encode(msg)))
        return payloads

    def _publish(self, payloads: list[tuple[str, bytes]]) -> None:
        for port, payload in payloads:
            self.publishers[port].put(payload)
        self.stats.frames_out += 1

    def _ack(self, run: str, seq: int) -> None:
        self.ack_pub.put(msgpack.packb({"run": run, "seq": seq, "op": self.op_id}))

    def _markers(self, run: str, seq: int, stamp_ns: int, meta: dict) -> list[tuple[str, bytes]]:
        return [(port, encode(Message(run, seq, stamp_ns, self.op_id, meta))) for port in self.cls.outputs]

    # -- the transform loop -------------------------------------------------------------------------

    def run(self) -> None:
        self._subscribe_service()
        if not isinstance(self.operator, Source):
            self._subscribe_inputs()
        token = self.session.liveliness().declare_token(self.keys.live(self.op_id, self.replica_id))
        try:
            if isinstance(self.operator, Source):
                SourceDriver(self).run()
                return
            self.log.info("ready: %s -> %s", dict(self.spec.inputs), list(self.cls.outputs))
            self._transform_loop()
        finally:
            self.session.put(self.keys.left, msgpack.packb({"op": self.op_id, "replica": self.replica_id}))
            token.undeclare()
            self._publish_stats(force=True)
        if not isinstance(self.operator, Source):
            self.log.info(
                "stopped after %d frames (%d errors, %d bad messages)",
                self.stats.frames_in,
                self.stats.errors,
                self.stats.bad_messages,
            )

    def _transform_loop(self) -> None:
        cache = OutputCache()
        ended: dict[str, list[tuple[str, bytes]]] = {}
        next_seq: dict[str, int] = defaultdict(int)
        in_order: dict[str, dict[int, Frame]] = defaultdict(dict)
        live = self._live_mode()

        def finish(frame: Frame) -> None:
            key = (frame.run, frame.seq)
            self.stats.frames_in += 1
            failed = [
                m
                for m in (*frame.inputs.values(), *(x for d in frame.many.values() for x in d.values()))
                if m.meta.get("error")
            ]
            if failed:
                payloads = self._markers(frame.run, frame.seq, frame.stamp_ns, {"error": failed[0].meta["error"]})
            else:
                start = time.perf_counter()
                try:
                    outputs = self.operator.process(frame)
                    payloads = self._encode_outputs(
                        frame.run, frame.seq, frame.stamp_ns, outputs, {"partial": True} if frame.partial else {}
                    )
                except Exception as exc:  # one bad frame must not stop the operator
                    self.stats.errors += 1
                    self.log.exception("frame %s failed: %s", frame.frame_id, exc)
                    payloads = self._markers(
                        frame.run, frame.seq, frame.stamp_ns, {"error": f"{self.op_id}: {type(exc).__name__}: {exc}"}
                    )
                self.stats.latency.add(time.perf_counter() - start)
            cache.put(key, payloads)
            self._publish(payloads)
            if self.is_sink:
                self._ack(frame.run, frame.seq)

        def end_run(msg: Message) -> None:
            run = msg.run
            if run in ended:
                if (run, msg.seq) not in cache:  # answer a re-sent marker at most once a second
                    cache.put((run, msg.seq), ended[run])
                republish = cache.due_for_republish((run, msg.seq))
                if republish:
                    self._publish(republish)
                    if self.is_sink:
                        self._ack(run, msg.seq)
                return
            meta = {"eos": True, "frames": msg.meta.get("frames", msg.seq)}
            try:
                outputs = self.operator.end_run(run)
                payloads = self._encode_outputs(run, msg.seq, msg.stamp_ns, outputs, meta)
                covered = {p for p, _ in payloads}
                payloads += [(p, b) for p, b in self._markers(run, msg.seq, msg.stamp_ns, meta) if p not in covered]
            except Exception as exc:
                self.stats.errors += 1
                self.log.exception("end of run %s failed: %s", run, exc)
                payloads = self._markers(run, msg.seq, msg.stamp_ns, meta)
            ended[run] = payloads
            cache.put((run, msg.seq), payloads)
            cache.last_republish[(run, msg.seq)] = time.monotonic()
            next_seq.pop(run, None)
            in_order.pop(run, None)
            self._publish(payloads)
            if self.is_sink:
                self._ack(run, msg.seq)

        while not self.shutdown.is_set():
            live_changed = self._handle_service()
            self._publish_stats()
            # read each time round: `umad set OP.deadline_ms=...` applies from the next frame on
            deadline_s = float(getattr(self.operator.params, "deadline_ms", 0) or 0) / 1e3 if live else 0.0
            try:
                port, sample = self.data_q.get(timeout=0.05)
            except queue.Empty:
                port = None
            if port is not None:
                try:
                    msg = decode(sample.payload.to_bytes())
                except MessageError as exc:
                    self.stats.bad_messages += 1
                    self._warn_bad_message(str(sample.key_expr), exc)
                    continue
                key = (msg.run, msg.seq)
                producer = self.keys.parse_data(str(sample.key_expr))[0]
                if msg.meta.get("eos"):
                    end_run(msg)
                    continue
                if key in cache:
                    self.stats.duplicates += 1
                    republish = cache.due_for_republish(key)
                    if republish:
                        self._publish(republish)
                        if self.is_sink:
                            self._ack(*key)
                    continue
                if not self._owns(msg.seq):
                    continue
                self.joiner.add(port, producer, msg)
            elif not live_changed and not (deadline_s and self.joiner.pending):
                continue
            for frame in self.joiner.pop_ready(self._expected(), deadline_s):
                if not self.cls.ordered:
                    finish(frame)
                    continue
                if frame.seq < next_seq[frame.run]:
                    continue
                in_order[frame.run][frame.seq] = frame
                if next_seq[frame.run] == 0 and 0 not in in_order[frame.run]:
                    self._request_rewind(frame.run, frame.seq)
                while next_seq[frame.run] in in_order[frame.run]:
                    finish(in_order[frame.run].pop(next_seq[frame.run]))
                    next_seq[frame.run] += 1


class SourceDriver:
    """Paces a Source: window of un-acked frames, retransmission on timeout, end-of-run markers.

    `lossless` pacing keeps at most `window` frames un-acked and re-sends a frame not acked in time.
    `realtime` pacing publishes at `rate_hz` whatever the acks say and never re-sends (a late frame
    of a live sensor is worthless), yet it still collects acks: a run's end-of-run marker goes out
    only once its frames are acked or have timed out, so no sink closes a run before its last frame.
    """

    def __init__(self, rt: OperatorRuntime):
        self.rt = rt
        self.source: Source = rt.operator  # type: ignore[assignment]
        params = self.source.params
        self.window = int(getattr(params, "window", 8))
        self.realtime = getattr(params, "pacing", "lossless") == "realtime"
        self.rate_hz = float(getattr(params, "rate_hz", 10.0))
        self.ack_timeout_s = float(getattr(params, "ack_timeout_s", 15.0))
        self.sinks = set(rt.graph.sinks())
        self.acks: dict[tuple[str, int], set[str]] = defaultdict(set)
        self.ack_q: queue.Queue = queue.Queue()
        self.inflight: dict[tuple[str, int], tuple[list[tuple[str, bytes]], float, float]] = {}
        self.e2e = LatencyWindow()
        self.markers: set[tuple[str, int]] = set()  # end-of-run keys, which are not frames

    def run(self) -> None:
        rt = self.rt
        rt._subscribers.append(
            rt.session.declare_subscriber(rt.keys.ack, lambda s: self.ack_q.put(s.payload.to_bytes()))
        )
        self._wait_for_graph()
        rt.stats.total_frames = self.source.total_frames()
        if rt.max_frames is not None and rt.stats.total_frames is not None:
            rt.stats.total_frames = min(rt.stats.total_frames, rt.max_frames)
        sent = 0
        current: str | None = None
        count = 0
        last_stamp = 0
        next_due = started = time.monotonic()
        for sf in self.source.frames():
            if rt.shutdown.is_set() or (rt.max_frames is not None and sent >= rt.max_frames):
                break
            if current is not None and sf.run != current:
                self._end_run(current, count, last_stamp)
                count = 0
            current = sf.run
            if self.realtime:
                next_due += 1.0 / self.rate_hz
                while time.monotonic() < next_due and not rt.shutdown.is_set():
                    self._service(min(0.01, max(0.0, next_due - time.monotonic())))
            else:
                while len(self.inflight) >= self.window and not rt.shutdown.is_set():
                    self._service(0.01)
            self._send((sf.run, sf.seq), self._payloads(sf))
            sent += 1
            count += 1
            last_stamp = sf.stamp_ns
        if current is not None and not rt.shutdown.is_set():
            self._end_run(current, count, last_stamp)
        rt.stats.busy_s = time.monotonic() - started
        rt._publish_stats(force=True)
        rt.log.info("source finished: %d frames sent, %d retransmits", sent, rt.stats.retransmits)

    def _wait_for_graph(self) -> None:
        """Frames sent before every operator subscribed would be lost to them: wait for all tokens."""
        wanted = {op.id for op in self.rt.graph.spec.operators}
        deadline = time.monotonic() + LIVE_WAIT_S
        while not self.rt.shutdown.is_set():
            self.rt._handle_service()
            missing = wanted - self.rt.members.ops()
            if not missing:
                time.sleep(0.2)  # let liveliness-triggered subscriptions settle at the hub
                return
            if time.monotonic() > deadline:
                self.rt.log.warning("starting although operators are not live: %s", sorted(missing))
                return
            time.sleep(0.05)

    def _payloads(self, sf: SourceFrame) -> list[tuple[str, bytes]]:
        """A source frame's messages: recorded bytes as they are, or its outputs encoded."""
        if sf.raw:
            return list(sf.raw.items())
        return self.rt._encode_outputs(sf.run, sf.seq, sf.stamp_ns, sf.outputs, {})

    def _send(self, key: tuple[str, int], payloads: list[tuple[str, bytes]]) -> None:
        now = time.monotonic()
        self.rt._publish(payloads)
        if self.sinks:
            self.inflight[key] = (payloads, now, now)

    def _service(self, timeout: float) -> None:
        """Take acks, retransmit what timed out, answer resend requests, publish stats."""
        rt = self.rt
        rt._handle_service()
        rt._publish_stats()
        while rt.resend_requests:
            self._resend(rt.resend_requests.pop(0))
        try:
            raw = self.ack_q.get(timeout=timeout)
        except queue.Empty:
            raw = None
        while raw is not None:
            try:
                ack = msgpack.unpackb(raw)
                key = (str(ack["run"]), int(ack["seq"]))
                op = str(ack["op"])
            except Exception:
                rt.stats.bad_messages += 1
            else:
                if key in self.inflight and op in self.sinks:
                    self.acks[key].add(op)
                    if self.sinks <= self.acks[key]:
                        first_sent = self.inflight.pop(key)[1]
                        self.acks.pop(key)
                        if key not in self.markers:
                            rt.stats.acked += 1
                        self.e2e.add(time.monotonic() - first_sent)
                        rt.stats.latency.add(time.monotonic() - first_sent)
            try:
                raw = self.ack_q.get_nowait()
            except queue.Empty:
                raw = None
        now = time.monotonic()
        timeout_s = max(self.ack_timeout_s, 3 * (self.e2e.percentiles_ms()["p99_ms"] or 0) / 1e3)
        for key, (payloads, first, last) in list(self.inflight.items()):
            if now - last > timeout_s and self.realtime:
                rt.log.warning(
                    "frame %s#%d not acked after %.1fs: given up (realtime pacing)", key[0], key[1], now - last
                )
                self.inflight.pop(key)
                self.acks.pop(key, None)
            elif now - last > timeout_s:
                rt.log.warning("frame %s#%d not acked after %.1fs: re-sending", key[0], key[1], now - last)
                rt.stats.retransmits += 1
                for port, payload in payloads:
                    rt.publishers[port].put(payload)
                self.inflight[key] = (payloads, first, now)

    def _resend(self, request: dict) -> None:
        """Publish frames [from, to) of a run again, byte for byte, for a restarted ordered operator."""
        rt = self.rt
        try:
            run, first, last = str(request["run"]), int(request["from"]), int(request["to"])
            for seq in range(first, last):
                rt._publish(self._payloads(self.source.frame_at(run, seq)))
        except NotImplementedError:
            rt.log.error(
                "%s cannot resend frames (no frame_at); %s must start its run over", rt.op_id, request.get("for")
            )
            return
        except (KeyError, ValueError, TypeError, IndexError) as exc:
            rt.stats.errors += 1
            rt.log.error("bad resend request %r: %s", request, exc)
            return
        rt.log.info("resent %s#%d..%d for %s", run, first, last - 1, request.get("for"))

    def _end_run(self, run: str, frames: int, stamp_ns: int) -> None:
        """Drain the run's frames, then send its end-of-run marker until every sink acked it."""
        rt = self.rt
        while self.inflight and not rt.shutdown.is_set():
            self._service(0.01)
        markers = rt._markers(run, frames, stamp_ns, {"eos": True, "frames": frames})
        self.markers.add((run, frames))
        self._send((run, frames), markers)
        while self.inflight and not rt.shutdown.is_set():
            self._service(0.01)
        rt.log.info("run %s: %d frames", run, frames)


def run_operator(
    graph: Graph,
    op_id: str,
    replica: int = 0,
    connect: str | None = None,
    max_frames: int | None = None,
    replay_log: str | None = None,
    allow_truncated: bool = False,
) -> int:
    """Connect to the hub and run one replica until the stream ends (sources) or a signal arrives."""
    shutdown = ShutdownSignal()
    tls = graph.tls_config()
    session = open_client(connect or graph.spec.hub, tls, cancel=shutdown.event)
    if session is None:
        log.info("stopped while waiting for the hub at %s", connect or graph.spec.hub)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)  # the thread still waiting inside Zenoh would hold up a normal exit
    try:
        try:
            runtime = OperatorRuntime(
                graph, op_id, replica, session, shutdown.event, max_frames, replay_log, allow_truncated
            )
        except Exception as exc:  # bad parameters, missing weights: say so once, do not restart
            log.error("operator %s could not start: %s: %s", op_id, type(exc).__name__, exc)
            return EXIT_CONFIG
        try:
            runtime.run()
        except LogError as exc:
            log.error("%s", exc)
            return EXIT_CONFIG
        finally:
            runtime.operator.close()
    finally:
        closed = close_session(session)
    if not closed:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)  # Zenoh's runtime threads would keep a clean interpreter exit waiting
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run one operator replica of a UMAD graph.")
    parser.add_argument("--graph", required=True)
    parser.add_argument("--op", required=True)
    parser.add_argument("--replica", type=int, default=0)
    parser.add_argument("--connect", default=None, help="hub endpoint, default: the graph's `hub`")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE")
    parser.add_argument("--replay-log", default=None, help="sources publish this MCAP log's recorded frames")
    parser.add_argument("--allow-truncated", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        graph = load_graph(args.graph)
        overrides: dict[str, dict[str, Any]] = defaultdict(dict)
        for text in args.set:
            op, param, value = parse_assignment(text)
            overrides[op][param] = value
        if overrides:
            graph = graph.with_params(overrides)
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return EXIT_CONFIG
    return run_operator(
        graph, args.op, args.replica, args.connect, args.max_frames, args.replay_log, args.allow_truncated
    )


if __name__ == "__main__":
    sys.exit(main())
