"""A launched graph's recording: every bus message into an MCAP log, complete, or said not to be.

The evaluation's table is computed from the log, so a log that silently lacks messages is a table
of other frames than the user asked for. Three rules keep it whole:

  - the recorder is a consumer of every frame, like a sink: it acks a frame (op `_recorder` on the
    ack key) once it has written that frame's message on every output of every live operator, and
    a lossless source keeps the frame in flight until then (`SourceDriver` waits for the acks of
    the sinks and of a live recorder). A slow recorder slows the graph; it never falls so far
    behind that a publisher's payload ring overwrites a payload it has not copied;
  - the Zenoh callback only copies a payload out of its publisher's payload plane (or queues a
    fetch from a publisher on another host); decoding, compressing and writing happen on the writer
    thread;
  - what is lost all the same (a publisher killed before its payload was fetched) is counted per
    channel, and so are the frames a channel lacks when the frame was closed without it. `close`
    writes both into the log's `umad_recording` metadata, which `umad sweep` and `umad eval` read
    before they report a table.

A frame whose every sink acked, yet whose outputs did not all arrive while nothing was left to
read (an operator that returns fewer outputs than it declares), is acked after `CLOSE_GRACE_S`,
so such a graph does not stall; its missing messages count as lacking.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections import Counter, OrderedDict, defaultdict
from pathlib import Path

import zenoh

from umad_common.dataflow.api.graph import Graph
from umad_common.dataflow.api.plugins import import_class
from umad_common.dataflow.delivery.service_messages import ServiceMessageError, encode_ack, read_ack
from umad_common.dataflow.record.mcap_log import RECORDING_METADATA, LogViews, McapRecorder
from umad_common.dataflow.transport.bus import RECORDER, Keys
from umad_common.dataflow.transport.planes import open_plane

log = logging.getLogger("umad.record")


CLOSE_GRACE_S = 2.0  # sinks acked, nothing left to read: the frame's missing outputs are not coming
REACK_INTERVAL_S = 1.0  # a re-sent frame that was already recorded is acked again at most this often
ACKED_REMEMBERED = 4096  # recorded frames remembered for re-acks
WARN_FIRST = 5  # lost payloads logged one by one, then one line per WARN_INTERVAL_S
WARN_INTERVAL_S = 5.0
SERVICE_KEYS = ("_stats", "_live", "_left")  # bus traffic that is not recorded
RECORDER_REPLICA = "0"  # the recorder's replica name in its liveliness token and its acks' key


class Recording:
    """Records the graph `keys.root/**` to `path` from `session` until `close`.

    Args:
        session: the launcher's session on the hub.
        graph: the launched graph: its operators' outputs are what a frame must have.
        path: the MCAP file (created).
        metadata: the log's `umad` metadata (graph text, base dir, sets).
    """

    def __init__(self, session: zenoh.Session, graph: Graph, path: Path, metadata: dict[str, str]):
        self.keys = Keys(graph.name)
        self.path = path
        self.file = McapRecorder(
            path, metadata.pop("graph", ""), metadata, views=log_views(graph), mask_sources=mask_sources(graph)
        )
        self.sinks = set(graph.sinks())
        self._outputs = {op: [self.keys.data(op, out) for out in cls.outputs] for op, cls in graph.classes.items()}
        self._live: dict[str, set[str]] = {}  # op -> its live replicas, once seen
        self._session = session
        self._payloads = open_plane()  # publishes nothing, takes what every plane puts
        self._writes: queue.Queue = queue.Queue()  # ("data" | "ack", key, bytes) | None to stop
        self._fetches: queue.Queue = queue.Queue()  # (key, reference) of payloads on another host's ring
        self._pending: dict[tuple[str, int], set[str]] = defaultdict(set)  # frame -> channels written
        self._sink_acks: dict[tuple[str, int], set[str]] = defaultdict(set)
        self._sinks_done: dict[tuple[str, int], float] = {}  # frame -> when its last sink acked
        self._acked: OrderedDict[tuple[str, int], float] = OrderedDict()  # frame -> when we last acked it
        self._closed_without: Counter[str] = Counter()  # channel -> frames closed without its message
        self.lost: Counter[str] = Counter()  # channel -> payloads that could not be read
        self._last_warning = 0.0
        self._closing = threading.Event()
        self._ack_pub = session.declare_publisher(
            self.keys.ack(RECORDER, RECORDER_REPLICA), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._declared = [
            session.liveliness().declare_subscriber(self.keys.live_all, self._on_live, history=True),
            session.declare_subscriber(f"{self.keys.root}/**", self._on_sample),
        ]
        self._token = session.liveliness().declare_token(self.keys.live(RECORDER, RECORDER_REPLICA))
        self._writer = threading.Thread(target=self._write_loop, name="recording-writer", daemon=True)
        self._fetcher = threading.Thread(target=self._fetch_loop, name="recording-fetcher", daemon=True)
        self._writer.start()
        self._fetcher.start()

    @property
    def count(self) -> int:
        return self.file.count

    def write_command(self, key: str, payload: bytes) -> None:
        """A command to the graph (`umad set`, `umad op ...`): recorded so the log says what changed when."""
        self._writes.put(("data", key, payload))

    # -- Zenoh's callbacks: copy and queue, nothing more ------------------------------------------------

    def _on_live(self, sample: zenoh.Sample) -> None:
        op, replica = self.keys.parse_live(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.PUT:
            self._live.setdefault(op, set()).add(replica)
        else:
            self._live.setdefault(op, set()).discard(replica)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        service = key[len(self.keys.root) + 1 :].partition("/")[0]
        if service in SERVICE_KEYS or self._closing.is_set():
            return
        raw = sample.payload.to_bytes()
        if service == "_ack":
            self._writes.put(("ack", key, raw))
            return
        payload = self._payloads.take(raw)
        if payload is None:  # a publisher on another host, or a payload already overwritten
            self._fetches.put((key, raw))
        else:
            self._writes.put(("data", key, payload))

    # -- the fetcher and the writer ------------------------------------------------------------------

    def _fetch_loop(self) -> None:
        while True:
            item = self._fetches.get()
            if item is None:
                return
            key, reference = item
            producer = self.keys.payload(self.keys.parse_data(key)[0])
            payload = None if self._closing.is_set() else self._payloads.fetch(self._session, producer, reference)
            if payload is None:
                self._lose(key)
            else:
                self._writes.put(("data", key, payload))
            self._fetches.task_done()

    def _lose(self, key: str) -> None:
        self.lost[key] += 1
        total = sum(self.lost.values())
        now = time.monotonic()
        if total <= WARN_FIRST or now - self._last_warning >= WARN_INTERVAL_S:
            self._last_warning = now
            log.warning("a payload on %s could not be read for the recording (%d lost so far)", key, total)

    def _write_loop(self) -> None:
        while not self._closing.is_set():
            try:
                item = self._writes.get(timeout=0.2)
            except queue.Empty:
                item = ()
            if item is None:
                self._writes.task_done()
                return
            try:
                if item and item[0] == "data":
                    self._record(item[1], item[2])
                elif item:
                    self._take_sink_ack(item[1], item[2])
            except Exception:  # e.g. the disk is full: say so, count it, keep the file closable
                log.exception("could not record a message on %s", item[1])
                if item[0] == "data":
                    self.lost[item[1]] += 1
            finally:
                if item:
                    self._writes.task_done()
            if self._writes.empty() and self._fetches.unfinished_tasks == 0:
                self._close_overdue_frames()

    def _record(self, key: str, payload: bytes) -> None:
        msg = self.file.write(key, payload)
        if msg is None or key.startswith(f"{self.keys.root}/_"):
            return
        frame = (msg.run, msg.seq)
        if frame in self._acked:
            if time.monotonic() - self._acked[frame] >= REACK_INTERVAL_S:  # the source re-sent it
                self._ack(frame)
            return
        self._pending[frame].add(key)
        if self._pending[frame] >= self._expected():
            self._ack(frame)

    def _expected(self) -> set[str]:
        """The channels every frame has: each output of each operator of the graph, but for those
        whose every replica has left (stopped with `umad op stop`, or crashed and not back yet)."""
        return {key for op, keys in self._outputs.items() if self._live.get(op, True) for key in keys}

    def _take_sink_ack(self, key: str, raw: bytes) -> None:
        """A sink's ack, taken only where its key names the sink it claims to come from (the sources log the others)."""
        try:
            ack = read_ack(self.keys, key, raw)
        except ServiceMessageError:
            return
        frame, op = (ack.run, ack.seq), ack.op
        if op not in self.sinks or frame in self._acked:
            return
        self._sink_acks[frame].add(op)
        if self.sinks <= self._sink_acks[frame]:
            self._sinks_done.setdefault(frame, time.monotonic())

    def _close_overdue_frames(self) -> None:
        """Ack frames whose sinks acked CLOSE_GRACE_S ago while nothing was left to read; what they
        lack then is not coming."""
        now = time.monotonic()
        for frame, since in list(self._sinks_done.items()):
            if now - since >= CLOSE_GRACE_S:
                for key in self._expected() - self._pending.get(frame, set()):
                    self._closed_without[key] += 1
                self._ack(frame)

    def _ack(self, frame: tuple[str, int]) -> None:
        self._pending.pop(frame, None)
        self._sink_acks.pop(frame, None)
        self._sinks_done.pop(frame, None)
        self._acked[frame] = time.monotonic()
        self._acked.move_to_end(frame)
        while len(self._acked) > ACKED_REMEMBERED:
            self._acked.popitem(last=False)
        try:
            self._ack_pub.put(encode_ack(frame[0], frame[1], RECORDER))
        except zenoh.ZError:  # the session is closing
            pass

    # -- the end -------------------------------------------------------------------------------------

    def drain(self, timeout_s: float) -> bool:
        """Wait until everything received so far is written (True), or `timeout_s` passed."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._writes.unfinished_tasks == 0 and self._fetches.unfinished_tasks == 0:
                return True
            time.sleep(0.05)
        return False

    def close(self, timeout_s: float, stopped: bool = False) -> dict[str, dict[str, int]]:
        """Stop recording, write what was received within `timeout_s`, close the log readable.

        Returns `{"lost": {channel: payloads}, "lacking": {channel: frames}}`, both written into the
        log's metadata too. Payloads still being fetched or written when time runs out count as lost.
        """
        deadline = time.monotonic() + timeout_s
        for declared in self._declared:
            declared.undeclare()
        self._token.undeclare()
        self._writes.put(None)
        self._writer.join(timeout=max(0.0, deadline - time.monotonic()))
        self._closing.set()  # the writer stops after the message it is writing
        self._fetches.put(None)
        self._writer.join(timeout=0.5)
        self._fetcher.join(timeout=max(0.0, deadline - time.monotonic()))
        for item in _take_all(self._writes):  # out of time: what was not written is lost
            if item and item[0] == "data":
                self.lost[item[1]] += 1
        for item in _take_all(self._fetches):
            if item is not None:
                self.lost[item[0]] += 1
        outcome = {"lost": dict(self.lost), "lacking": dict(self._closed_without)}
        self.file.close(
            drop_views=stopped,
            metadata_name=RECORDING_METADATA,
            metadata={
                "complete": json.dumps(not self.lost and not self._closed_without),
                "stopped": json.dumps(stopped),
                "messages": str(self.file.count),
                "lost": json.dumps(outcome["lost"], sort_keys=True),
                "lacking": json.dumps(outcome["lacking"], sort_keys=True),
            },
        )
        self._payloads.close()
        return outcome

    def sweep_gone_rings(self) -> None:
        """Forget the mappings of rings their publishers have left (the launcher swept them)."""
        self._payloads.forget_gone()


class UnknownViewsError(LookupError):
    """A graph's `record_views` that is not a loadable `LogViews` class."""


def log_views(graph: Graph) -> type[LogViews] | None:
    """The class of the views the graph's log holds (`record_views`, imported here: the engine names
    the Foxglove views, `umad_common.viz.foxglove`, and never imports them itself), or None for none."""
    path = graph.spec.record_views
    return import_class(path, LogViews, "record_views", UnknownViewsError) if path else None


def mask_sources(graph: Graph) -> dict[str, str]:
    """Each output (`op/output`) of an operator with a `masks` input -> the masks channel wired to
    it: the Foxglove views outline a refined map's masks on the camera with their scores."""
    found = {}
    for spec in graph.spec.operators:
        if "masks" not in spec.inputs or spec.id not in graph.classes:
            continue
        producers = [producer for source in spec.sources_of("masks") for producer in graph.producers(source)]
        if len(producers) == 1:
            found.update({f"{spec.id}/{out}": "/".join(producers[0]) for out in graph.classes[spec.id].outputs})
    return found


def _take_all(waiting: queue.Queue) -> list:
    items = []
    while True:
        try:
            items.append(waiting.get_nowait())
        except queue.Empty:
            return items
