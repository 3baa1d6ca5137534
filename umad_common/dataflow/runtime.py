"""The operator runtime: one process runs one replica of one operator from the graph.

It owns everything an operator module should not have to write: the Zenoh session, joining inputs by
`(run, seq)`, in-order delivery, the replica split, the output cache that answers retransmissions,
end-to-end acks, end-of-run markers, stats, runtime parameter changes, and a clean shutdown.
Its data structures (joiner, membership, output cache, stats) are in `delivery.py`; how a source
paces, re-sends and closes runs is in `source_driver.py`.

Delivery protocol (lossless by design):
  - a source keeps at most `window` frames in flight and forgets a frame once every sink of the
    graph has acked it; an un-acked frame is re-sent after a timeout (at-least-once);
  - every operator caches its recent outputs, so a re-sent input re-publishes the cached output
    instead of recomputing (exactly-once effect, state untouched);
  - a frame whose processing raised travels on as an error marker (meta `error`), so sinks still
    ack it and the stream never stalls on it;
  - a frame the source marks as not scored (meta `skip`: `umad eval --every k` scores every k-th
    frame) is processed by in-order operators (the world model's state needs every frame) and
    passed on by every other operator as a skip marker, without computing;
  - after the last frame of a run is acked the source sends an end-of-run marker (meta `eos`),
    which each operator passes on after calling its `end_run`.

Live mode (a source paces in real time and never re-sends) replaces waiting with keeping up: an
operator computes the newest frames it has ready, as many as it can in one camera period, and
passes the older ones over (meta `superseded`, counted in `superseded`); a frame still waiting for
an input after its deadline is passed over too. So a lost payload never holds an operator, a slow
operator never works through a backlog, and a cheap one catches up after a stall (`_finish_live`).

Commands arrive as queries on the control key and are answered once applied or refused; what does
not change while the graph runs (is this replica a sink, which producers feed a wildcard port) is
worked out once, or again when the live membership changes, never per frame.
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
from collections import defaultdict
from collections.abc import Callable
from typing import Any, NamedTuple, NoReturn

import msgpack
import zenoh
from pydantic import ValidationError
from threadpoolctl import threadpool_limits

from umad_common.dataflow.allocator import keep_freed_memory
from umad_common.dataflow.assignments import GraphError, merge_params, parse_sets
from umad_common.dataflow.bus import (
    HubJoinError,
    Keys,
    ShutdownSignal,
    answer,
    close_session,
    open_client,
)
from umad_common.dataflow.certificates import add_certificate_arguments, operator_identity
from umad_common.dataflow.delivery import FrameJoiner, Membership, OutputCache, Stats
from umad_common.dataflow.exit_codes import EXIT_CONFIG
from umad_common.dataflow.graph import Graph, load_graph
from umad_common.dataflow.mcap_log import LogError
from umad_common.dataflow.messages import Message, MessageError, decode, encode
from umad_common.dataflow.operator import Context, Frame, Operator, Output, Source
from umad_common.dataflow.pacing import JoinParams
from umad_common.dataflow.payload_ring import (
    SWEPT_BY_LAUNCHER,
    PayloadReader,
    PayloadRing,
    fetch,
    on_this_host,
)
from umad_common.dataflow.shm_payloads import DEFAULT_POOL_MIB, ZenohShmPayloads, payload_plane
from umad_common.dataflow.source_driver import SourceDriver

log = logging.getLogger("umad.runtime")

STATS_INTERVAL_S = 1.0
LIVE_JOIN_POLL_S = 0.05  # how often a live join with frames waiting checks their deadline
COMPUTE_EMA = 0.2  # weight of the newest frame in the running mean of an operator's compute time
CATCH_UP_PERIODS = 2  # live mode: an operator computes the newest ready frames it can in this many camera periods
IDLE_WAIT_S = 0.25  # an idle operator's sleep: the longest a stop signal waits to be seen
BAD_MESSAGE_LOG_FIRST = 10  # malformed messages logged one by one; later ones are summarised
BAD_MESSAGE_LOG_INTERVAL_S = 5.0
REWIND_RETRY_S = 10.0


class Received(NamedTuple):
    """One input message as the subscriber took it: decoded at once, its arrays views on the bytes
    copied out of the publisher's payload ring or out of what Zenoh delivered, so a busy operator's
    queue never holds shared memory a publisher is about to reuse. A payload the ring could not
    give (its publisher runs on another host) stays a reference until the transform loop fetches it."""

    port: str
    key: str
    message: Message | MessageError | bytes  # decoded, refused, or a reference still to fetch
    sent: float | None  # the producer's put, from the sample's timestamp (wall clock, seconds)
    arrived: float  # wall clock

    @classmethod
    def take(cls, port: str, sample: zenoh.Sample, reader: PayloadReader) -> Received:
        stamp = sample.timestamp
        sent = None if stamp is None else stamp.get_time_as_ntp64().as_secs_f64()
        raw = sample.payload.to_bytes()
        payload = reader.take(raw)
        message = raw if payload is None else decode_or_refuse(payload)
        return cls(port, str(sample.key_expr), message, sent, time.time())


def decode_or_refuse(payload: bytes | memoryview) -> Message | MessageError:
    try:
        return decode(payload)
    except MessageError as exc:
        return exc


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
        shared_payloads: bool = True,
    ):
        """`shared_payloads=False`: publish every payload through Zenoh even where the graph asks
        for shared memory (a replica whose hub is on another host)."""
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
            from umad_common.dataflow.log_source import LoggedSource

            params = self.cls.validate_params(self.spec.params)
            self.operator: Operator = LoggedSource(replay_log, self.cls, params, context, allow_truncated)
        else:
            self.operator = self.cls(self.spec.params, context)
        self.data_q: queue.Queue = queue.Queue(maxsize=64)
        self.ctl_q: queue.Queue = queue.Queue()
        self.members = Membership()
        self.resend_requests: list[dict] = []  # sources: frames a restarted ordered operator needs again
        self._rewinds: dict[str, float] = {}  # ordered operators: run -> when frames were last re-requested
        plane = payload_plane(graph.spec.shared_payloads if shared_payloads else False)
        self.ring = PayloadRing(self.keys.payload(op_id)) if plane == "ring" else None
        self.shm = ZenohShmPayloads(graph.spec.shm_pool_mib or DEFAULT_POOL_MIB) if plane == "zenoh_shm" else None
        self.reader = PayloadReader()
        self.publishers = {
            out: session.declare_publisher(self.keys.data(op_id, out), congestion_control=zenoh.CongestionControl.BLOCK)
            for out in self.cls.outputs
        }
        self.ack_pub = session.declare_publisher(self.keys.ack, congestion_control=zenoh.CongestionControl.BLOCK)
        self.stats_pub = session.declare_publisher(
            self.keys.stats(op_id, self.replica_id), congestion_control=zenoh.CongestionControl.DROP
        )
        self.joiner = FrameJoiner(
            [p.name for p in self.cls.inputs if not p.many and p.name in self.spec.inputs],
            [p.name for p in self.cls.inputs if p.many and p.name in self.spec.inputs],
        )
        self._subscribers: list[Any] = []
        self._last_stats = 0.0
        self._cpu_from: float | None = None  # process CPU at the first frame (start-up is no frame's cost)
        self._last_bad_log = 0.0
        self.is_sink = op_id in graph.sinks()  # sinks ack frames end to end
        self.live = self._live_mode()
        self._frame_period_s = self._camera_period_s()
        self._compute_s = 0.0  # running mean of the wall time `process` takes (live mode's catch-up)
        self._params_meta = self.operator.params.model_dump(mode="json")  # recorded in every output
        self._route_cache: tuple[dict[str, set[str]], list[str]] | None = None  # expected producers, replicas
        # the transform loop's state
        self._cache = OutputCache()  # recent outputs, re-published for a duplicate input
        self._ended: dict[str, list[tuple[str, bytes]]] = {}  # run -> its end-of-run payloads
        self._next_seq: dict[str, int] = defaultdict(int)  # ordered or live: run -> the lowest seq still to process
        self._in_order: dict[str, dict[int, Frame]] = defaultdict(dict)  # run -> joined frames waiting their turn

    # -- wiring -----------------------------------------------------------------------------------

    def subscribe(self, key: str, callback: Callable[[zenoh.Sample], None]) -> None:
        """A subscriber that lives as long as this replica (the source driver takes acks with it)."""
        self._subscribers.append(self.session.declare_subscriber(key, callback))

    def _subscribe_inputs(self) -> None:
        for port in self.spec.inputs:
            for source in self.spec.sources_of(port):
                self.subscribe(
                    self.keys.pattern(source),
                    lambda s, port=port: self.data_q.put(Received.take(port, s, self.reader)),
                )

    def _subscribe_service(self) -> None:
        control = self.keys.control(self.op_id)
        self.subscribe(control, lambda s: self._service_event("ctl", (s.payload.to_bytes(), None)))  # e.g. resend
        self._subscribers.append(
            self.session.declare_queryable(
                control, lambda q: self._service_event("ctl", (q.payload.to_bytes() if q.payload else b"", q))
            )
        )
        self.subscribe(self.keys.left, lambda s: self._service_event("left", s))
        if self.ring is not None:  # subscribers that cannot map the ring fetch payloads here
            self._subscribers.append(self.session.declare_queryable(self.ring.fetch_key, self.ring.serve))
        self._subscribers.append(
            self.session.liveliness().declare_subscriber(
                self.keys.live_all, lambda s: self._service_event("live", s), history=True
            )
        )

    def _service_event(self, kind: str, event: Any) -> None:
        """Queue a command or membership change and wake the transform loop to apply it now: the
        loop sleeps on its data queue and has nothing else to wake up for."""
        self.ctl_q.put((kind, event))
        try:
            self.data_q.put_nowait(None)
        except queue.Full:  # messages are waiting: the loop is awake
            pass

    def _routes(self) -> tuple[dict[str, set[str]], list[str]]:
        """The producers each wildcard port waits for and this operator's sorted live replicas:
        computed again only after the live membership changed."""
        if self._route_cache is None:
            self._route_cache = (self._expected(), sorted(self.members.replicas(self.op_id) | {self.replica_id}))
        return self._route_cache

    def _owns(self, seq: int) -> bool:
        """Replicas split frames by seq over the sorted live replica set."""
        replicas = self._routes()[1]
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
                    if not op.startswith("_")  # the recorder's token: a consumer, never a producer
                    and any(self._produces(op, src) for src in self.spec.sources_of(port.name))
                }
        return expected

    # -- service messages ---------------------------------------------------------------------------

    def handle_service(self) -> bool:
        """Apply queued commands and liveliness events; True when the set of live operators changed."""
        changed = self.members.expire()
        while True:
            try:
                kind, sample = self.ctl_q.get_nowait()
            except queue.Empty:
                if changed:
                    self._route_cache = None
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
                payload, query = sample
                outcome = self._apply_control(payload)
                if query is not None:
                    answer(
                        query, self.keys.control(self.op_id), {"op": self.op_id, "replica": self.replica_id, **outcome}
                    )

    def _apply_control(self, payload: bytes) -> dict[str, str]:
        """Stop, resend or a parameter change; returns the outcome the asking command prints. A
        change that fails validation, needs an input the graph does not wire to this operator, or
        that the operator refuses (a weight file that does not load), is logged and counted; the old
        parameters stay."""
        try:
            command = json.loads(payload)
            if not isinstance(command, dict):
                raise TypeError(f"expected a JSON object with `set`, `stop` or `resend`, got {type(command).__name__}")
            if command.get("stop"):
                self.log.info("stop requested on the control key")
                self.shutdown.set()
                return {"status": "stopping"}
            if "resend" in command:
                self.resend_requests.append(command["resend"])
                return {"status": "resending"}
            updates = command["set"]
            if not isinstance(updates, dict):
                raise TypeError(f"`set` must map parameter names to values, got {type(updates).__name__}")
            old = self.operator.params
            params = old.model_dump()
            merge_params(params, updates)
            new = self.cls.validate_params(params)
            unwired = self.cls.wiring_problems(new, set(self.spec.inputs))
            if unwired:  # e.g. a segmenter method that reads an input this operator is not wired to
                raise ValueError("; ".join(unwired))
        except (ValueError, KeyError, TypeError, ValidationError, GraphError) as exc:
            self.stats.errors += 1
            self.log.error("rejected parameter change %r: %s", payload[:200], exc)
            return {"status": "refused", "reason": _one_line(exc)}
        try:
            self.operator.update_params(new)
        except Exception as exc:  # the operator could not take the change: keep running as before
            self.stats.errors += 1
            self.log.error(
                "parameter change %s refused by %s: %s; keeping the old parameters", updates, self.op_id, exc
            )
            self.operator.params = old
            return {"status": "refused", "reason": f"{type(exc).__name__}: {exc}"}
        self._params_meta = self.operator.params.model_dump(mode="json")
        self.stats.param_changes += 1
        self.log.info("parameters changed: %s", updates)
        return {"status": "applied"}

    def _realtime_rates(self) -> list[float]:
        """The `rate_hz` of every source that paces in real time (none: the graph is lossless)."""
        sources = (self.graph.classes[s].validate_params(self.graph.op(s).params) for s in self.graph.sources())
        return [params.rate_hz for params in sources if params.pacing == "realtime"]

    def _live_mode(self) -> bool:
        """Live (a source paces in real time): joins may give up at their deadline. Lossless (the
        default): every expected input is waited for."""
        return bool(self._realtime_rates())

    def _camera_period_s(self) -> float:
        """Live mode: the time between two frames of the fastest realtime source (0 when lossless)."""
        rates = self._realtime_rates()
        return 1.0 / max(rates) if rates else 0.0

    def _deadline_s(self) -> float:
        """How long a partly joined frame may wait in live mode: a joining operator's `deadline_ms`
        (`umad set OP.deadline_ms=...` applies from the next frame on), else JoinParams' default."""
        if not self.live:
            return 0.0
        params = self.operator.params if isinstance(self.operator.params, JoinParams) else JoinParams()
        return params.deadline_ms / 1e3

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

    def publish_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_stats >= STATS_INTERVAL_S:
            self._last_stats = now
            self.stats.dropped = self.joiner.dropped
            self.stats.joined, self.stats.wait_s = self.joiner.joined, self.joiner.wait_s
            if self._cpu_from is not None:
                self.stats.process_cpu_s = time.process_time() - self._cpu_from
            snap = self.stats.snapshot(self.data_q.qsize())
            self.reader.forget_gone()
            self.stats_pub.put(json.dumps({"op": self.op_id, "replica": self.replica_id, **snap}).encode())

    def _message_of(self, received: Received) -> Message | MessageError | None:
        """The message; a reference to a ring this host cannot map is fetched from its publisher. A
        payload nobody has any more is counted in `lost_payloads` and left to the source's
        retransmission, which brings the frame again; in live mode, where nothing is re-sent, its
        frame is passed over at its deadline (`_finish_live`)."""
        if not isinstance(received.message, bytes):
            return received.message
        payload = fetch(self.session, self.keys.payload(self.keys.parse_data(received.key)[0]), received.message)
        if payload is None:
            self.stats.lost_payloads += 1
            self.log.warning(
                "payload on %s could not be fetched from its publisher; %s",
                received.key,
                "its frame will be passed over" if self.live else "waiting for a resend",
            )
            return None
        return decode_or_refuse(payload)

    def _warn_bad_message(self, key: str, exc: MessageError) -> None:
        """Log the first few malformed messages in full, then one summary line per interval: a flood
        of garbage must not turn into a flood of log lines (stats count every one)."""
        now = time.monotonic()
        if self.stats.bad_messages <= BAD_MESSAGE_LOG_FIRST:
            self.log.warning("bad message on %s: %s", key, exc)
        elif now - self._last_bad_log >= BAD_MESSAGE_LOG_INTERVAL_S:
            self.log.warning("%d bad messages so far; latest on %s: %s", self.stats.bad_messages, key, exc)
            self._last_bad_log = now

    def count_cpu_from_now(self) -> None:
        """Start counting the process's CPU (`runtime_cpu_ms`) at the first frame, not before."""
        if self._cpu_from is None:
            self._cpu_from = time.process_time()

    def _count_arrival(self, received: Received) -> None:
        """A message's transport (producer's put to our subscriber) and queueing (subscriber to us)."""
        self.count_cpu_from_now()
        self.stats.messages_in += 1
        self.stats.queue_s += time.time() - received.arrived
        if received.sent is not None:
            self.stats.transport_s += max(0.0, received.arrived - received.sent)

    # -- publishing ---------------------------------------------------------------------------------

    def encode_outputs(
        self, run: str, seq: int, stamp_ns: int, outputs: dict[str, Output], extra_meta: dict
    ) -> list[tuple[str, bytes]]:
        """One frame's outputs as (port, payload) pairs; each records the parameters that made it."""
        payloads = []
        for port, out in outputs.items():
            if port not in self.publishers:
                raise ValueError(f"operator returned output {port!r}; it declares {list(self.cls.outputs)}")
            meta = {**out.meta, **extra_meta, "params": self._params_meta}
            msg = Message(run, seq, stamp_ns, self.op_id, meta, out.arrays)
            payloads.append((port, encode(msg)))
        return payloads

    def publish(self, payloads: list[tuple[str, bytes]], count: bool = True) -> None:
        """Put one frame's payloads; `count=False` for a retransmission, which is no new frame. Each
        carries the put's time (a Zenoh timestamp, not part of the payload) for `transport_ms`."""
        for port, payload in payloads:
            if self.ring is not None:
                payload = self.ring.pack(payload)
            elif self.shm is not None:
                payload = self.shm.pack(payload)
            self.publishers[port].put(payload, timestamp=self.session.new_timestamp())
        if count:
            self.stats.frames_out += 1

    def _ack(self, run: str, seq: int) -> None:
        self.ack_pub.put(msgpack.packb({"run": run, "seq": seq, "op": self.op_id}))

    def markers(self, run: str, seq: int, stamp_ns: int, meta: dict) -> list[tuple[str, bytes]]:
        """Array-less messages on every output: an end-of-run marker or a frame's error marker."""
        return [(port, encode(Message(run, seq, stamp_ns, self.op_id, meta))) for port in self.cls.outputs]

    # -- the transform loop -------------------------------------------------------------------------

    def run(self) -> None:
        self._subscribe_service()
        if not isinstance(self.operator, Source):
            self._subscribe_inputs()
        token = self.session.liveliness().declare_token(self.keys.live(self.op_id, self.replica_id))
        try:
            if isinstance(self.operator, Source):
                SourceDriver(self, self.operator, self.graph, self.max_frames).run()
                return
            self.log.info("ready: %s -> %s", dict(self.spec.inputs), list(self.cls.outputs))
            self._transform_loop()
        finally:
            self.session.put(self.keys.left, msgpack.packb({"op": self.op_id, "replica": self.replica_id}))
            token.undeclare()
            self.publish_stats(force=True)
            self.reader.close()
            if self.ring is not None:
                self.ring.close(unlink=SWEPT_BY_LAUNCHER not in os.environ)
        if not isinstance(self.operator, Source):
            self.log.info(
                "stopped after %d frames (%d errors, %d bad messages)",
                self.stats.frames_in,
                self.stats.errors,
                self.stats.bad_messages,
            )

    def _transform_loop(self) -> None:
        """Until a stop: apply commands, take one message (or time out for a live join's deadline),
        then process every frame the joiner has ready."""
        while not self.shutdown.is_set():
            live_changed = self.handle_service()
            self.publish_stats()
            deadline_s = self._deadline_s()
            try:  # messages and commands wake the loop; the timeout is for deadlines, stats and signals
                received = self.data_q.get(
                    timeout=LIVE_JOIN_POLL_S if deadline_s and self.joiner.pending else IDLE_WAIT_S
                )
            except queue.Empty:
                received = None
            if received is not None:
                taken = self._take(received)
                if self.live:  # choose among every frame already waiting, not the first one
                    taken = self._take_waiting() or taken
                if not taken:
                    continue
            elif not live_changed and not (deadline_s and self.joiner.pending):
                continue
            ready = self.joiner.pop_ready(self._routes()[0], deadline_s)
            if self.live:
                self._finish_live(ready)
                for (run, seq), stamp_ns in self.joiner.pop_expired(deadline_s, self._next_seq).items():
                    self._pass_over(run, seq, stamp_ns)
                continue
            for frame in ready:
                if self.cls.ordered:
                    self._finish_in_order(frame)
                else:
                    self._finish(frame)

    def _take_waiting(self) -> bool:
        """Live mode: take every message already queued; True when any of them needs a join."""
        taken = False
        for _ in range(self.data_q.qsize()):
            try:
                received = self.data_q.get_nowait()
            except queue.Empty:
                break
            if received is not None:  # None only wakes the loop for a command
                taken = self._take(received) or taken
        return taken

    def _take(self, received: Received) -> bool:
        """Hand one input message to the joiner; False when it needs no join (unreadable, malformed,
        an end-of-run marker, a duplicate answered from the cache, or another replica's frame)."""
        self._count_arrival(received)
        msg = self._message_of(received)
        if msg is None:
            return False
        if isinstance(msg, MessageError):
            self.stats.bad_messages += 1
            self._warn_bad_message(received.key, msg)
            return False
        key = (msg.run, msg.seq)
        producer = self.keys.parse_data(received.key)[0]
        if msg.meta.get("eos"):
            self._end_run(msg)
            return False
        if key in self._cache:
            self.stats.duplicates += 1
            republish = self._cache.due_for_republish(key)
            if republish:
                self._publish_and_ack(msg.run, msg.seq, republish)
            return False
        if not self._owns(msg.seq):
            return False
        if self.live and msg.seq < self._next_seq[msg.run] and key not in self.joiner.pending:
            return False  # a late input of a frame finished or passed over (`_finish_live`)
        self.joiner.add(received.port, producer, msg)
        return True

    def _finish_in_order(self, frame: Frame) -> None:
        """An ordered operator's frame: held until every earlier frame of its run is finished; a run
        that starts past seq 0 (this replica restarted) asks the sources for the frames before it."""
        run = frame.run
        if frame.seq < self._next_seq[run]:
            return
        waiting = self._in_order[run]
        waiting[frame.seq] = frame
        if self._next_seq[run] == 0 and 0 not in waiting:
            self._request_rewind(run, frame.seq)
        while self._next_seq[run] in waiting:
            self._finish(waiting.pop(self._next_seq[run]))
            self._next_seq[run] += 1

    def _finish_live(self, ready: list[Frame]) -> None:
        """Live mode: a camera's consumer wants every frame it can have, soon, and never a backlog;
        a frame lost on the way never comes again (live sources do not re-send).

        The rule, per run: of the ready frames to compute, the newest ones this operator can compute
        in `CATCH_UP_PERIODS` camera periods (by its running mean compute time; at least the newest)
        are processed, oldest first, and the older ones are passed over. One period is a frame's
        own; the second absorbs one stall of a busy machine, while a longer stall is passed over
        rather than queued. A passed-over frame is counted in `superseded` and sent on as a
        marker with meta `superseded`, so the sinks ack it and the operators after this one pass it
        on without computing. Frames that need no computing (an input is an error, skip or
        superseded marker) are passed on at once and do not compete.

        A frame still waiting for an input while a newer one was processed stays until its deadline
        (`_deadline_s`; then it is passed over, `FrameJoiner.pop_expired`), and is processed if it
        completes before: a join whose inputs came by paths of different speed loses nothing. The
        newest frame is never given up (a slow input is no lost one); at the run's end the frames
        still waiting are passed over (`_end_run`). An ordered operator, which
        cannot go back, passes over its older waiting frames when it processes a newer one; it thus
        sees its run's frames in increasing seq order with gaps (the world model bridges a gap),
        and a replica restarted mid-run starts from the newest frame (no rewind: a live source's old
        frames are worthless).
        """
        to_compute: list[Frame] = []
        for frame in sorted(ready, key=lambda f: f.seq):
            if self._marker_meta(frame) is None:
                to_compute.append(frame)
            else:
                self._finish(frame)
        budget_s = CATCH_UP_PERIODS * self._frame_period_s
        fits = max(1, int(budget_s / self._compute_s)) if self._compute_s > 0 else len(to_compute)
        for run in dict.fromkeys(frame.run for frame in to_compute):
            frames = [frame for frame in to_compute if frame.run == run]
            for frame in frames[:-fits]:
                self._pass_over(run, frame.seq, frame.stamp_ns)
            for frame in frames[-fits:]:
                if self.cls.ordered:
                    for seq, stamp_ns in sorted(self.joiner.discard_older(run, frame.seq).items()):
                        self._pass_over(run, seq, stamp_ns)
                self._next_seq[run] = max(self._next_seq[run], frame.seq + 1)
                self._finish(frame)

    def _pass_over(self, run: str, seq: int, stamp_ns: int) -> None:
        """Send a superseded marker for a frame this live operator will not process."""
        self.stats.superseded += 1
        payloads = self.markers(run, seq, stamp_ns, {"superseded": True})
        self._cache.put((run, seq), payloads)
        self.publish(payloads, count=False)
        if self.is_sink:
            self._ack(run, seq)

    def _finish(self, frame: Frame) -> None:
        """Process one joined frame (or pass on its marker: `_marker_meta`), cache and publish the result."""
        self.stats.frames_in += 1
        payloads = self._payloads_for(frame)
        self._cache.put((frame.run, frame.seq), payloads)
        self._publish_and_ack(frame.run, frame.seq, payloads)

    def _marker_meta(self, frame: Frame) -> dict | None:
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
        if not self.cls.ordered and any(m.meta.get("skip") for m in received):
            return {"skip": True}
        return None

    def _payloads_for(self, frame: Frame) -> list[tuple[str, bytes]]:
        """A frame's outputs: a marker passed on (`_marker_meta`), or what `process` returned (a skip
        marker for a skipped frame an in-order operator processed for its state), or the error it
        raised."""
        marker = self._marker_meta(frame)
        if marker is not None:
            return self.markers(frame.run, frame.seq, frame.stamp_ns, marker)
        skipped = any(m.meta.get("skip") for m in frame_messages(frame))
        start, cpu_start = time.perf_counter(), time.process_time()
        try:
            outputs = self.operator.process(frame)
            self.stats.cpu_s += time.process_time() - cpu_start
            if self.stats.computed:  # an operator's first frame is start-up (first calls, memory): not counted
                took = time.perf_counter() - start
                self._compute_s = (1 - COMPUTE_EMA) * self._compute_s + COMPUTE_EMA * took if self._compute_s else took
            self.stats.computed += 1
            if skipped:  # an in-order operator saw the frame for its state; nobody scores it
                payloads = self.markers(frame.run, frame.seq, frame.stamp_ns, {"skip": True})
            else:
                payloads = self.encode_outputs(
                    frame.run, frame.seq, frame.stamp_ns, outputs, {"partial": True} if frame.partial else {}
                )
        except Exception as exc:  # one bad frame must not stop the operator
            self.stats.errors += 1
            self.log.exception("frame %s failed: %s", frame.frame_id, exc)
            payloads = self.markers(
                frame.run, frame.seq, frame.stamp_ns, {"error": f"{self.op_id}: {type(exc).__name__}: {exc}"}
            )
        self.stats.latency.add(time.perf_counter() - start)
        return payloads

    def _end_run(self, msg: Message) -> None:
        """A run's end-of-run marker: call the operator's `end_run` once and pass the marker on; a
        re-sent marker is answered from what the first one published."""
        run = msg.run
        if run in self._ended:
            if (run, msg.seq) not in self._cache:  # answer a re-sent marker at most once a second
                self._cache.put((run, msg.seq), self._ended[run])
            republish = self._cache.due_for_republish((run, msg.seq))
            if republish:
                self._publish_and_ack(run, msg.seq, republish)
            return
        meta = {"eos": True, "frames": msg.meta.get("frames", msg.seq)}
        try:
            outputs = self.operator.end_run(run)
            payloads = self.encode_outputs(run, msg.seq, msg.stamp_ns, outputs, meta)
            covered = {p for p, _ in payloads}
            payloads += [(p, b) for p, b in self.markers(run, msg.seq, msg.stamp_ns, meta) if p not in covered]
        except Exception as exc:
            self.stats.errors += 1
            self.log.exception("end of run %s failed: %s", run, exc)
            payloads = self.markers(run, msg.seq, msg.stamp_ns, meta)
        self._ended[run] = payloads
        self._cache.put((run, msg.seq), payloads)
        self._cache.last_republish[(run, msg.seq)] = time.monotonic()
        if self.live:  # frames still waiting for an input the source gave up on
            for seq, stamp_ns in sorted(self.joiner.discard_older(run, msg.seq).items()):
                self._pass_over(run, seq, stamp_ns)
        self._next_seq.pop(run, None)
        self._in_order.pop(run, None)
        self._publish_and_ack(run, msg.seq, payloads)

    def _publish_and_ack(self, run: str, seq: int, payloads: list[tuple[str, bytes]]) -> None:
        """Publish a frame's (or an end-of-run marker's) payloads; a sink then acks it end to end."""
        self.publish(payloads)
        if self.is_sink:
            self._ack(run, seq)


def frame_messages(frame: Frame) -> list[Message]:
    """Every input message of a joined frame, single and `many` ports alike."""
    return [*frame.inputs.values(), *(m for port in frame.many.values() for m in port.values())]


def _one_line(exc: Exception) -> str:
    """An error as one line for a command's answer (a schema error lists each field on its own line)."""
    if isinstance(exc, ValidationError):
        return "; ".join(f"{'.'.join(str(x) for x in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors())
    return f"{type(exc).__name__}: {exc}".replace("\n", " ")


def run_operator(
    graph: Graph,
    op_id: str,
    replica: int = 0,
    connect: str | None = None,
    max_frames: int | None = None,
    replay_log: str | None = None,
    allow_truncated: bool = False,
    cert: str | None = None,
    key: str | None = None,
) -> NoReturn:
    """Connect to the hub, run one replica until the stream ends (sources) or a signal arrives, and
    end the process. With TLS it presents `cert`/`key`, else its operator's certificate `op-<id>` of
    the graph's `tls.certs`; a hub that refuses it ends the process with one line saying so.

    The process ends with `os._exit` once its operator and session are closed and its output is
    flushed. The interpreter's own finalization is skipped: it garbage-collects every object torch,
    scikit-learn and the models left behind, CPU that a graph stopping all its replicas at once on
    a busy machine does not have (measured on 2 cores: every replica was through its shutdown
    within 0.15 s of SIGTERM, then sat in that collection past the launcher's grace period and was
    killed). With the hub gone, Zenoh's threads would hold up a normal exit as well.
    """
    one_blas_thread()
    keep_freed_memory()
    shutdown = ShutdownSignal()
    tls = graph.tls_config(operator_identity(op_id), cert, key)
    hub = connect or graph.spec.hub
    local = on_this_host(hub)
    try:
        session = open_client(
            hub,
            tls,
            cancel=shutdown.event,
            shm_pool_mib=graph.spec.shm_pool_mib,
            direct_links=local and graph.spec.direct_links and tls is None,
        )
    except HubJoinError as exc:
        log.error("operator %s could not join: %s", op_id, exc)
        _exit(EXIT_CONFIG)
    if session is None:
        log.info("stopped while waiting for the hub at %s", hub)
        _exit(0)
    code = 0
    try:
        runtime = OperatorRuntime(
            graph, op_id, replica, session, shutdown.event, max_frames, replay_log, allow_truncated, local
        )
    except Exception as exc:  # bad parameters, missing weights: say so once, do not restart
        log.error("operator %s could not start: %s: %s", op_id, type(exc).__name__, exc)
        code = EXIT_CONFIG
    else:
        try:
            runtime.run()
        except LogError as exc:
            log.error("%s", exc)
            code = EXIT_CONFIG
        finally:
            runtime.operator.close()
    finally:
        close_session(session)
    _exit(code)


def one_blas_thread() -> threadpool_limits:
    """Limit numpy's BLAS to one thread in this process (until the returned limiter, used as a context
    manager, exits).

    By default BLAS starts a thread per core that spins after every call: in a mask refiner that was
    38 ms of CPU per frame next to 2 ms of its own work. A replica's parallelism is the graph's
    processes; an operator that wants threads for its own work (torch's `threads`) sets them."""
    return threadpool_limits(limits=1, user_api="blas")


def _exit(code: int) -> NoReturn:
    """End the process at once, after flushing what it has to say."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


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
    add_certificate_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        graph = load_graph(args.graph)
        overrides = parse_sets(args.set)
        if overrides:
            graph = graph.with_params(overrides)
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return EXIT_CONFIG
    run_operator(
        graph,
        args.op,
        args.replica,
        args.connect,
        args.max_frames,
        args.replay_log,
        args.allow_truncated,
        args.cert,
        args.key,
    )


if __name__ == "__main__":
    sys.exit(main())
