"""The source driver: how a graph's source paces its frames (window of un-acked frames, or a fixed
rate), re-sends what was not acked, answers a restarted ordered operator's rewind, and closes runs."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from functools import partial
from typing import Any, Protocol

from umad_common.dataflow.api.graph import Graph
from umad_common.dataflow.api.operator import Output, Source, SourceFrame
from umad_common.dataflow.api.pacing import SourceParams
from umad_common.dataflow.delivery.joiner import Membership
from umad_common.dataflow.delivery.service_messages import IgnoredMessages, ServiceMessageError, read_ack
from umad_common.dataflow.delivery.stats import LatencyWindow, Stats
from umad_common.dataflow.transport.bus import RECORDER, Keys

LIVE_WAIT_S = 60.0
PRIME_S = 3.0  # realtime pacing: the longest start-up before the camera's clock starts (`_prime`)
PRIME_QUICK = 3  # ... which starts once this many frames in a row came back within one camera period
ACK_WAIT_S = 0.05  # a full window's wait for acks (an ack ends it at once): re-sends and commands wait this long


class SourceHost(Protocol):
    """What the source driver uses of the runtime that runs it (`OperatorRuntime`): its counters,
    logger and stop signal, the live membership, the service loop and publishing."""

    op_id: str
    log: logging.Logger
    stats: Stats
    shutdown: threading.Event
    members: Membership  # the live operators and their replicas
    resend_requests: list[dict]  # frames a restarted ordered operator asked for; the driver takes them
    ignored: IgnoredMessages  # acks that are malformed or claim another sender than their key

    def subscribe(self, key: str, callback: Callable[[Any], None]) -> None: ...

    def handle_service(self) -> bool: ...

    def publish_stats(self, force: bool = False) -> None: ...

    def count_cpu_from_now(self) -> None: ...

    def encode_outputs(
        self, run: str, seq: int, stamp_ns: int, outputs: dict[str, Output], extra_meta: dict
    ) -> list[tuple[str, bytes]]: ...

    def markers(self, run: str, seq: int, stamp_ns: int, meta: dict) -> list[tuple[str, bytes]]: ...

    def publish(self, payloads: list[tuple[str, bytes]], count: bool = True) -> None: ...


class SourceDriver:
    """Paces a Source: window of un-acked frames, retransmission on timeout, end-of-run markers.

    `lossless` pacing keeps at most `window` frames un-acked and re-sends a frame not acked in time.
    A frame is acked when every sink acked it, and the launcher's recorder too while one is live: a
    recorded run goes no faster than its log is written, so the log lacks nothing.
    `realtime` pacing publishes at `rate_hz` whatever the acks say and never re-sends (a late frame
    of a live sensor is worthless), yet it still collects acks: a run's end-of-run marker goes out
    only once its frames are acked or have timed out, so no sink closes a run before its last frame.
    Its clock starts once the graph keeps up (`_prime`): the graph's start-up costs are paid on
    frames sent one at a time, not by the frames a camera would send meanwhile.
    """

    def __init__(self, host: SourceHost, source: Source, graph: Graph, *, max_frames: int | None = None):
        self.host = host
        self.source = source
        if not isinstance(source.params, SourceParams):
            raise TypeError(f"{host.op_id}: a source's Params must extend SourceParams, got {type(source.params)}")
        self.graph = graph
        self.max_frames = max_frames
        self.sinks = set(graph.sinks())
        self.acks: dict[tuple[str, int], set[str]] = defaultdict(set)
        self.keys = Keys(graph.name)
        self.ack_q: queue.Queue = queue.Queue()  # (key, payload) of each ack
        self.inflight: dict[tuple[str, int], tuple[list[tuple[str, bytes]], float, float]] = {}
        self.e2e = LatencyWindow()
        self.markers: set[tuple[str, int]] = set()  # end-of-run keys, which are not frames
        self._quick = 0  # start-up: frames in a row acked within one camera period (`_prime`)

    @property
    def pacing(self) -> SourceParams:
        """Read each time: `umad set replayer.window=...` applies to the next frame."""
        return self.source.params  # type: ignore[return-value]

    def run(self) -> None:
        host = self.host
        host.subscribe(self.keys.ack_all, lambda s: self.ack_q.put((str(s.key_expr), s.payload.to_bytes())))
        self._wait_for_graph()
        host.stats.total_frames = self.source.total_frames()
        if self.max_frames is not None and host.stats.total_frames is not None:
            host.stats.total_frames = min(host.stats.total_frames, self.max_frames)
        started = time.monotonic()
        runs = self.source.runs() if self.pacing.runs_in_flight > 1 else None
        if self.pacing.runs_in_flight > 1 and runs is None:
            host.log.warning(
                "runs_in_flight %d: %s cannot read its frames in any order (Source.runs); sending one run at a time",
                self.pacing.runs_in_flight,
                type(self.source).__name__,
            )
        sent = self._send_side_by_side(runs) if runs is not None else self._send_in_order(started)
        host.stats.busy_s = time.monotonic() - started
        host.publish_stats(force=True)
        host.log.info("source finished: %d frames sent, %d retransmits", sent, host.stats.retransmits)

    def _send_in_order(self, started: float) -> int:
        """Send the source's frames as `frames` yields them, one run after the other; returns how
        many were sent."""
        host = self.host
        sent = 0
        current: str | None = None
        count = 0
        last_stamp = 0
        next_due = started
        priming, prime_until = self.pacing.pacing == "realtime", started + PRIME_S
        frames = self.source.frames()
        while not host.shutdown.is_set() and (self.max_frames is None or sent < self.max_frames):
            sf = self._next_frame(frames)
            if sf is None:
                break
            if current is not None and sf.run != current:
                self._end_run(current, count, last_stamp)
                count = 0
            current = sf.run
            if self.pacing.pacing == "realtime":
                next_due += 1.0 / self.pacing.rate_hz
                while time.monotonic() < next_due and not host.shutdown.is_set():
                    self._service(min(0.01, max(0.0, next_due - time.monotonic())))
            else:
                while len(self.inflight) >= self.pacing.window and not host.shutdown.is_set():
                    self._service(ACK_WAIT_S)
            self._send((sf.run, sf.seq), self._payloads(sf))
            if priming:
                priming = self._prime(prime_until)
                next_due = time.monotonic()
            sent += 1
            count += 1
            last_stamp = sf.stamp_ns
        if current is not None and not host.shutdown.is_set():
            self._end_run(current, count, last_stamp)
        return sent

    def _send_side_by_side(self, runs: dict[str, int]) -> int:
        """Send `runs_in_flight` runs at once, taking their frames in turn, each run with at most
        `window` frames in flight; a run's end-of-run marker goes out once its own frames are
        acked, and the next run starts in its place. Returns how many frames were sent."""
        host = self.host
        waiting = [(run, length) for run, length in runs.items() if length > 0]
        waiting.reverse()  # popped from the end: `runs`' order
        sending: dict[str, list[int]] = {}  # run -> [next seq, frames, stamp of the last frame sent]
        closing: dict[str, tuple[int, int]] = {}  # run -> (frames, last stamp): every frame sent, its marker due
        sent = 0
        while not host.shutdown.is_set():
            self._close_acked_runs(closing)
            while waiting and len(sending) + len(closing) < self.pacing.runs_in_flight:
                run, length = waiting.pop()
                sending[run] = [0, length, 0]
            if not sending and not closing:
                break
            run = self._next_run_with_room(sending)
            if run is None:
                self._service(ACK_WAIT_S)
                continue
            seq, length, _ = sending[run]
            sf = self._read(partial(self.source.frame_or_error, run, seq))
            assert sf is not None, "frame_or_error returns a frame or an error frame"
            self._send((run, seq), self._payloads(sf))
            sent += 1
            del sending[run]
            if seq + 1 < length:
                sending[run] = [seq + 1, length, sf.stamp_ns]  # at the back of the turn
            else:
                closing[run] = (length, sf.stamp_ns)
            if self.max_frames is not None and sent >= self.max_frames:  # every run sent so far ends here
                closing.update({r: (next_seq, stamp) for r, (next_seq, _, stamp) in sending.items() if next_seq})
                sending.clear()
                waiting.clear()
        while self.inflight and not host.shutdown.is_set():
            self._service(ACK_WAIT_S)
        return sent

    def _next_run_with_room(self, sending: dict[str, list[int]]) -> str | None:
        """The first run in turn with fewer than `window` frames in flight (None: every run waits for acks)."""
        in_flight: dict[str, int] = defaultdict(int)
        for run, _ in self.inflight:
            in_flight[run] += 1
        return next((run for run in sending if in_flight[run] < self.pacing.window), None)

    def _close_acked_runs(self, closing: dict[str, tuple[int, int]]) -> None:
        """Send the end-of-run marker of every closing run whose frames are all acked."""
        busy = {run for run, _ in self.inflight}
        for run, (frames, stamp_ns) in list(closing.items()):
            if run in busy:
                continue
            self.markers.add((run, frames))
            self._send((run, frames), self.host.markers(run, frames, stamp_ns, {"eos": True, "frames": frames}))
            self.host.log.info("run %s: %d frames", run, frames)
            del closing[run]

    def _prime(self, until: float) -> bool:
        """Realtime pacing at start-up: wait for the frame just sent to be acked; True while the
        graph is still warming up, that is until `PRIME_QUICK` frames in a row came back within one
        camera period, for at most `PRIME_S` in all (a frame lost then is left to its ack timeout).
        Each process's first frames cost what no later one does (first messages, memory, kernels:
        several times what a later frame takes; docs/experiments.md), and a camera that went on
        meanwhile would have its next frames passed over."""
        host = self.host
        host.stats.primed += 1
        sent_at = time.monotonic()
        while self.inflight and not host.shutdown.is_set() and time.monotonic() < until:
            self._service(ACK_WAIT_S)
        took = time.monotonic() - sent_at
        self._quick = self._quick + 1 if not self.inflight and took <= 1.0 / self.pacing.rate_hz else 0
        if not self.inflight and self._quick < PRIME_QUICK and time.monotonic() < until:
            return True
        host.log.info(
            "the camera's clock starts after %d frame(s) sent one at a time (the last %s)",
            host.stats.primed,
            "not yet acked" if self.inflight else f"acked in {1e3 * took:.0f} ms",
        )
        return False

    def _next_frame(self, frames: Iterator[SourceFrame]) -> SourceFrame | None:
        """The source's next frame, its reading counted as the source's own work (`cpu_ms`)."""
        return self._read(lambda: next(frames, None))

    def _read(self, read: Callable[[], SourceFrame | None]) -> SourceFrame | None:
        """A frame `read` returns, its reading counted as the source's own work (`cpu_ms`)."""
        self.host.count_cpu_from_now()
        cpu_start = time.process_time()
        sf = read()
        if sf is not None:
            self.host.stats.cpu_s += time.process_time() - cpu_start
            self.host.stats.computed += 1
        return sf

    def _wait_for_graph(self) -> None:
        """Frames sent before every operator subscribed would be lost to them: wait for all tokens,
        every replica's. A replica splits frames with the siblings it sees (seq modulo their
        number), so a frame sent after one replica saw a sibling's token but before that sibling
        subscribed would be nobody's until its re-send, `ack_timeout_s` later (`umad bench scaling`
        with two VGG16 replicas stalled so while only one replica per operator was awaited)."""
        wanted = {op.id: op.replicas for op in self.graph.spec.operators}
        deadline = time.monotonic() + LIVE_WAIT_S
        while not self.host.shutdown.is_set():
            self.host.handle_service()
            live = self.host.members.live
            missing = [
                f"{op} ({len(live.get(op, ()))} of {n})" for op, n in wanted.items() if len(live.get(op, ())) < n
            ]
            if not missing:
                time.sleep(0.2)  # let liveliness-triggered subscriptions settle at the hub
                return
            if time.monotonic() > deadline:
                self.host.log.warning("starting although operators are not live: %s", sorted(missing))
                return
            time.sleep(0.05)

    def _payloads(self, sf: SourceFrame) -> list[tuple[str, bytes]]:
        """A source frame's messages: recorded bytes as they are, its outputs encoded, or error
        markers for a frame that could not be read (logged with its id and counted in `errors`)."""
        if sf.error is not None:
            self.host.stats.errors += 1
            self.host.log.error("frame %s#%d cannot be read, sent on as an error: %s", sf.run, sf.seq, sf.error)
            return self.host.markers(sf.run, sf.seq, sf.stamp_ns, {"error": f"{self.host.op_id}: {sf.error}"})
        if sf.raw:
            return list(sf.raw.items())
        return self.host.encode_outputs(sf.run, sf.seq, sf.stamp_ns, sf.outputs, {})

    def _send(self, key: tuple[str, int], payloads: list[tuple[str, bytes]]) -> None:
        now = time.monotonic()
        self.host.publish(payloads)
        if self.sinks:
            self.inflight[key] = (payloads, now, now)

    def _service(self, timeout: float) -> None:
        """Take acks (each from the sender its key names), retransmit what timed out, answer resend
        requests, publish stats."""
        host = self.host
        host.handle_service()
        host.publish_stats()
        while host.resend_requests:
            self._resend(host.resend_requests.pop(0))
        try:
            received = self.ack_q.get(timeout=timeout)
        except queue.Empty:
            received = None
        while received is not None:
            try:
                ack = read_ack(self.keys, *received)
            except ServiceMessageError as exc:
                host.ignored.ignore(received[0], exc)
            else:
                key, op = (ack.run, ack.seq), ack.op
                ackers = self._ackers()
                if key in self.inflight and op in ackers:
                    self.acks[key].add(op)
                    if ackers <= self.acks[key]:
                        first_sent = self.inflight.pop(key)[1]
                        self.acks.pop(key)
                        if key not in self.markers:
                            host.stats.acked += 1
                        self.e2e.add(time.monotonic() - first_sent)
                        host.stats.latency.add(time.monotonic() - first_sent)
            try:
                received = self.ack_q.get_nowait()
            except queue.Empty:
                received = None
        now = time.monotonic()
        if not self.inflight or now - min(last for _, _, last in self.inflight.values()) <= self.pacing.ack_timeout_s:
            return  # nothing can be due: the percentiles below cost more than this whole call
        timeout_s = max(self.pacing.ack_timeout_s, 3 * (self.e2e.percentiles_ms()["p99_ms"] or 0) / 1e3)
        for key, (payloads, first, last) in list(self.inflight.items()):
            if now - last > timeout_s and self.pacing.pacing == "realtime":
                host.log.warning(
                    "frame %s#%d not acked after %.1fs: given up (realtime pacing)", key[0], key[1], now - last
                )
                self.inflight.pop(key)
                self.acks.pop(key, None)
            elif now - last > timeout_s:
                host.log.warning("frame %s#%d not acked after %.1fs: re-sending", key[0], key[1], now - last)
                host.stats.retransmits += 1
                host.publish(payloads, count=False)
                self.inflight[key] = (payloads, first, now)

    def _ackers(self) -> set[str]:
        """Who must ack a frame: every sink, and the recorder while it is live."""
        return self.sinks | {RECORDER} if self.host.members.replicas(RECORDER) else self.sinks

    def _resend(self, request: dict) -> None:
        """Publish frames [from, to) of a run again, byte for byte, for a restarted ordered operator."""
        host = self.host
        try:
            run, first, last = str(request["run"]), int(request["from"]), int(request["to"])
            for seq in range(first, last):
                host.publish(self._payloads(self.source.frame_or_error(run, seq)))
        except NotImplementedError:
            host.log.error(
                "%s cannot resend frames (no frame_at); %s must start its run over", host.op_id, request["for"]
            )
            return
        except (KeyError, ValueError, TypeError, IndexError) as exc:  # a run or frame this source does not have
            host.stats.errors += 1
            host.log.error("bad resend request %r: %s", request, exc)
            return
        host.log.info("resent %s#%d..%d for %s", run, first, last - 1, request["for"])

    def _end_run(self, run: str, frames: int, stamp_ns: int) -> None:
        """Drain the run's frames, then send its end-of-run marker until every sink acked it."""
        host = self.host
        while self.inflight and not host.shutdown.is_set():
            self._service(ACK_WAIT_S)
        markers = host.markers(run, frames, stamp_ns, {"eos": True, "frames": frames})
        self.markers.add((run, frames))
        self._send((run, frames), markers)
        while self.inflight and not host.shutdown.is_set():
            self._service(ACK_WAIT_S)
        host.log.info("run %s: %d frames", run, frames)
