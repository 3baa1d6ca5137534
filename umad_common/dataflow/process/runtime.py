"""The operator runtime: one replica of one operator from the graph, on a connected Zenoh session.

It owns everything an operator module should not have to write: the Zenoh session, joining inputs by
`(run, seq)`, in-order delivery, the replica split, the output cache that answers retransmissions,
end-to-end acks, end-of-run markers, stats, runtime parameter changes, and a clean shutdown.

This module holds the subscriptions, the live membership, publishing, stats, and the transform loop
that joins each input message (`delivery/joiner.py`) and hands the complete frames to a delivery
strategy: `delivery/replay.py` (lossless, stateless), `ordered.py` (lossless, stateful) or `live.py`
(a realtime source). The strategy finishes frames through the frame processor (`frame_processing.py`);
commands go to `control.py`, a source's pacing to `source_driver.py`. Each of these sees the runtime
only through a small Protocol of its own (`DeliveryHost`, `FrameHost`, `ControlHost`, `SourceHost`),
which `OperatorRuntime` fits as it is, so none imports this module.

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

Commands arrive as queries on the control key and are answered once applied or refused; a source
takes resend requests on a key of its own (`_resend/<source>`), nothing else there. What does
not change while the graph runs (is this replica a sink, which producers feed a wildcard port) is
worked out once, or again when the live membership changes, never per frame.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import zenoh

from umad_common.dataflow.api.graph import Graph
from umad_common.dataflow.api.messages import Message, MessageError, decode, encode
from umad_common.dataflow.api.operator import Context, Operator, Output, Source
from umad_common.dataflow.api.pacing import JoinParams
from umad_common.dataflow.delivery.joiner import FrameJoiner, Membership
from umad_common.dataflow.delivery.live import LiveDelivery
from umad_common.dataflow.delivery.ordered import OrderedDelivery, RunOwners
from umad_common.dataflow.delivery.paths import DeliveryPath
from umad_common.dataflow.delivery.replay import ReplayDelivery
from umad_common.dataflow.delivery.routes import expected_producers
from umad_common.dataflow.delivery.service_messages import (
    IgnoredMessages,
    ServiceMessageError,
    encode_ack,
    encode_goodbye,
    encode_resend,
    read_goodbye,
    read_resend,
)
from umad_common.dataflow.delivery.stats import Stats
from umad_common.dataflow.process.control import apply_command
from umad_common.dataflow.process.frame_processing import FrameProcessor
from umad_common.dataflow.process.source_driver import SourceDriver
from umad_common.dataflow.transport.bus import Keys, answer
from umad_common.dataflow.transport.planes import PayloadPlane, open_plane, payload_plane

log = logging.getLogger("umad.runtime")

STATS_INTERVAL_S = 1.0
LIVE_JOIN_POLL_S = 0.05  # how often a live join with frames waiting checks their deadline
IDLE_WAIT_S = 0.25  # an idle operator's sleep: the longest a stop signal waits to be seen
BAD_MESSAGE_LOG_FIRST = 10  # malformed messages logged one by one; later ones are summarised
BAD_MESSAGE_LOG_INTERVAL_S = 5.0


class Received(NamedTuple):
    """One input message as the subscriber took it: decoded at once, its arrays views on the bytes
    copied out of the publisher's payload plane or out of what Zenoh delivered, so a busy operator's
    queue never holds shared memory a publisher is about to reuse. A payload the plane could not
    give (its publisher runs on another host) stays as received until the transform loop fetches it."""

    port: str
    key: str
    message: Message | MessageError | bytes  # decoded, refused, or a payload still to fetch
    sent: float | None  # the producer's put, from the sample's timestamp (wall clock, seconds)
    arrived: float  # wall clock

    @classmethod
    def take(cls, port: str, sample: zenoh.Sample, plane: PayloadPlane) -> Received:
        stamp = sample.timestamp
        sent = None if stamp is None else stamp.get_time_as_ntp64().as_secs_f64()
        raw = sample.payload.to_bytes()
        payload = plane.take(raw)
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
        *,
        graph: Graph,
        op_id: str,
        replica: int,
        session: zenoh.Session,
        shutdown: threading.Event,
        max_frames: int | None = None,
        replay_log: str | None = None,
        allow_truncated: bool = False,
        hub_on_this_host: bool = True,
    ):
        """`hub_on_this_host=False` (a replica whose hub is on another host): publish every payload
        through Zenoh even where the graph asks for shared memory."""
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
        self.ignored = IgnoredMessages(self.log, self.stats)  # forged or misplaced service messages
        context = Context(op_id, replica, graph.name, graph.base_dir, self.log)
        if replay_log and issubclass(self.cls, Source):
            from umad_common.dataflow.record.log_source import LoggedSource

            params = self.cls.validate_params(self.spec.params)
            self.operator: Operator = LoggedSource(
                replay_log, self.cls, params=params, context=context, allow_truncated=allow_truncated
            )
        else:
            self.operator = self.cls(self.spec.params, context)
        self.data_q: queue.Queue = queue.Queue(maxsize=64)
        self.ctl_q: queue.Queue = queue.Queue()
        self.members = Membership()
        self.resend_requests: list[dict] = []  # sources: frames a restarted ordered operator needs again
        self.payloads = open_plane(  # puts with this replica's plane, takes what any plane put
            payload_plane(graph.spec.shared_payloads if hub_on_this_host else False),
            self.keys.payload(op_id),
            graph.spec.shm_pool_mib,
        )
        self.publishers = {
            out: session.declare_publisher(self.keys.data(op_id, out), congestion_control=zenoh.CongestionControl.BLOCK)
            for out in self.cls.outputs
        }
        self.ack_pub = session.declare_publisher(
            self.keys.ack(op_id, self.replica_id), congestion_control=zenoh.CongestionControl.BLOCK
        )
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
        rates = self._realtime_rates()
        self.live = bool(rates)  # a source paces in real time: joins may give up at their deadline
        self.frame_period_s = 1.0 / max(rates) if rates else 0.0  # live: the camera period
        self.params_meta = self.operator.params.model_dump(mode="json")  # recorded in every output
        self._route_cache: tuple[dict[str, set[str]], list[str]] | None = None  # expected producers, replicas
        self.run_owners = RunOwners(self.replica_id)  # ordered operators: which replica owns each run
        self.processor = FrameProcessor(self, self.operator, ordered=self.cls.ordered)
        self.delivery = self._choose_delivery()

    def _choose_delivery(self) -> DeliveryPath:
        """How this replica delivers the frames it joined: live (a realtime source), ordered (a
        stateful operator) or replay (lossless, any order)."""
        if self.live:
            return LiveDelivery(
                self,
                finisher=self.processor,
                joiner=self.joiner,
                ordered=self.cls.ordered,
                frame_period_s=self.frame_period_s,
            )
        if self.cls.ordered:
            return OrderedDelivery(self, self.processor)
        return ReplayDelivery(self, self.processor)

    # -- wiring -----------------------------------------------------------------------------------

    def subscribe(self, key: str, callback: Callable[[zenoh.Sample], None]) -> None:
        """A subscriber that lives as long as this replica (the source driver takes acks with it)."""
        self._subscribers.append(self.session.declare_subscriber(key, callback))

    def _subscribe_inputs(self) -> None:
        for port in self.spec.inputs:
            for source in self.spec.sources_of(port):
                self.subscribe(
                    self.keys.pattern(source),
                    lambda s, port=port: self.data_q.put(Received.take(port, s, self.payloads)),
                )

    def _subscribe_service(self) -> None:
        self._subscribers.append(
            self.session.declare_queryable(
                self.keys.control(self.op_id),
                lambda q: self._service_event("ctl", (q.payload.to_bytes() if q.payload else b"", q)),
            )
        )
        if isinstance(self.operator, Source):  # a restarted ordered operator's rewind
            self.subscribe(self.keys.resend(self.op_id), lambda s: self._service_event("resend", s))
        self.subscribe(self.keys.left_all, lambda s: self._service_event("left", s))
        self._subscribers.extend(self.payloads.declare(self.session))  # answers subscribers that cannot reach the plane
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
            expected = expected_producers(self.graph, self.spec, self.cls.inputs, self.members.ops())
            self._route_cache = (expected, sorted(self.members.replicas(self.op_id) | {self.replica_id}))
        return self._route_cache

    def owns_seq(self, seq: int) -> bool:
        """Replicas split frames by seq over the sorted live replica set."""
        replicas = self._routes()[1]
        if len(replicas) == 1:
            return True
        return replicas[seq % len(replicas)] == self.replica_id

    def owns_run(self, run: str, seq: int) -> bool:
        """Ordered operators: whether `run` belongs to this replica (`RunOwners`), over the replicas
        whose liveliness token is there now (a lost one is not waited for: its runs move on)."""
        return self.run_owners.owner(run, seq, set(self.members.live.get(self.op_id, ()))) == self.replica_id

    def _replica_gone(self, replica: str) -> None:
        """A sibling replica's token went: the runs it owned that now fall to this one are taken over."""
        taken = self.run_owners.replica_gone(replica, set(self.members.live.get(self.op_id, ())))
        if taken and isinstance(self.delivery, OrderedDelivery):
            self.delivery.take_over(taken)

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
                    if op == self.op_id and rep != self.replica_id and self.cls.ordered:
                        self._replica_gone(rep)
                changed = True
            elif kind == "left":
                key = str(sample.key_expr)
                try:
                    self.members.leave(*read_goodbye(self.keys, key, sample.payload.to_bytes()))
                    changed = True
                except ServiceMessageError as exc:
                    self.ignored.ignore(key, exc)
            elif kind == "resend":
                try:
                    self.resend_requests.append(read_resend(sample.payload.to_bytes()))
                except ServiceMessageError as exc:
                    self.ignored.ignore(str(sample.key_expr), exc)
            else:
                payload, query = sample
                outcome = apply_command(self, payload)
                answer(query, self.keys.control(self.op_id), {"op": self.op_id, "replica": self.replica_id, **outcome})

    def _realtime_rates(self) -> list[float]:
        """The `rate_hz` of every source that paces in real time (none: the graph is lossless)."""
        sources = (self.graph.classes[s].validate_params(self.graph.op(s).params) for s in self.graph.sources())
        return [params.rate_hz for params in sources if params.pacing == "realtime"]

    def deadline_s(self) -> float:
        """How long a partly joined frame may wait in live mode: a joining operator's `deadline_ms`
        (`umad set OP.deadline_ms=...` applies from the next frame on), else JoinParams' default."""
        if not self.live:
            return 0.0
        params = self.operator.params if isinstance(self.operator.params, JoinParams) else JoinParams()
        return params.deadline_ms / 1e3

    def publish_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_stats >= STATS_INTERVAL_S:
            self._last_stats = now
            self.stats.dropped = self.joiner.dropped
            self.stats.joined, self.stats.wait_s = self.joiner.joined, self.joiner.wait_s
            if self._cpu_from is not None:
                self.stats.process_cpu_s = time.process_time() - self._cpu_from
            snap = self.stats.snapshot(self.data_q.qsize())
            self.payloads.forget_gone()
            self.stats_pub.put(json.dumps({"op": self.op_id, "replica": self.replica_id, **snap}).encode())

    def _message_of(self, received: Received) -> Message | MessageError | None:
        """The message; a payload this host's planes cannot read is fetched from its publisher. A
        payload nobody has any more is counted in `lost_payloads` and left to the source's
        retransmission, which brings the frame again; in live mode, where nothing is re-sent, its
        frame is passed over at its deadline (`delivery/live.py`)."""
        if not isinstance(received.message, bytes):
            return received.message
        producer = self.keys.payload(self.keys.parse_data(received.key)[0])
        payload = self.payloads.fetch(self.session, producer, received.message)
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
            meta = {**out.meta, **extra_meta, "params": self.params_meta}
            msg = Message(run, seq, stamp_ns, self.op_id, meta, out.arrays)
            payloads.append((port, encode(msg)))
        return payloads

    def publish(self, payloads: list[tuple[str, bytes]], count: bool = True) -> None:
        """Put one frame's payloads; `count=False` for a retransmission, which is no new frame. Each
        carries the put's time (a Zenoh timestamp, not part of the payload) for `transport_ms`."""
        for port, payload in payloads:
            self.publishers[port].put(self.payloads.put(payload), timestamp=self.session.new_timestamp())
        if count:
            self.stats.frames_out += 1

    def ack(self, run: str, seq: int) -> None:
        self.ack_pub.put(encode_ack(run, seq, self.op_id))

    def request_resend(self, run: str, first: int, end: int) -> None:
        """Ask every source upstream of this operator to send frames [first, end) of `run` again."""
        for source in self.graph.upstream_sources(self.op_id):
            self.session.put(self.keys.resend(source), encode_resend(run, first, end, self.op_id))

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
                SourceDriver(self, self.operator, self.graph, max_frames=self.max_frames).run()
                return
            self.log.info("ready: %s -> %s", dict(self.spec.inputs), list(self.cls.outputs))
            self._transform_loop()
        finally:
            self.session.put(self.keys.left(self.op_id, self.replica_id), encode_goodbye(self.op_id, self.replica_id))
            token.undeclare()
            self.publish_stats(force=True)
            self.payloads.close()
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
            deadline_s = self.deadline_s()
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
            if self.shutdown.is_set():  # a stopping graph: producers leaving now are no reason to complete a frame
                break
            ready = self.joiner.pop_ready(self._routes()[0], deadline_s)
            self.delivery.deliver(ready)

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
            self.delivery.end_run(msg)
            return False
        if self.processor.answer_duplicate(key) or not self.delivery.accepts(msg):
            return False
        self.joiner.add(received.port, producer, msg)
        return True
