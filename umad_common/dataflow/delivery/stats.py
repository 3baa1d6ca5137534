"""What every replica publishes about itself: its counters, where each frame's time went, and the
latency percentiles. Plain data, no Zenoh."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np


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
    """What a replica publishes about itself. Besides the counters, where each frame's time went,
    as sums the snapshot turns into means per frame (per message for the bus's part):

    - `cpu_ms`: CPU time of the operator's own work (`process`, a source's reading of a frame);
    - `runtime_cpu_ms`: the rest of the process's CPU since its first frame (decoding, encoding,
      joining, acks, Zenoh's threads), per frame in: what the runtime and the bus cost;
    - `transport_ms`: a message's time from the producer's put to this replica's subscriber;
    - `queue_ms`: a message's time waiting for this replica to take it (the replica was busy);
    - `wait_ms`: a frame's time from its first input to its last (waiting for a slower producer).
    """

    frames_in: int = 0
    frames_out: int = 0
    errors: int = 0
    bad_messages: int = 0
    duplicates: int = 0
    dropped: int = 0
    retransmits: int = 0
    lost_payloads: int = 0  # ring references whose payload was gone (recovered by retransmission)
    superseded: int = 0  # live mode: frames passed over for a newer frame of their run (stale or lost)
    param_changes: int = 0
    busy_s: float = 0.0  # sources: first send to last ack
    acked: int = 0  # sources: frames every sink has acked
    primed: int = 0  # realtime sources: frames sent one at a time at start-up, before the clock started
    total_frames: int | None = None  # sources: frames the stream will have, when known
    computed: int = 0  # frames the operator's work ran on (not markers)
    cpu_s: float = 0.0
    process_cpu_s: float = 0.0  # the process's CPU since its first frame, set at each snapshot
    messages_in: int = 0
    transport_s: float = 0.0
    queue_s: float = 0.0
    joined: int = 0
    wait_s: float = 0.0
    latency: LatencyWindow = field(default_factory=LatencyWindow)

    def snapshot(self, queue_depth: int) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "latency"}
        return {**d, **self.latency.percentiles_ms(), **self.time_per_frame_ms(), "queue_depth": queue_depth}

    def time_per_frame_ms(self) -> dict[str, float | None]:
        """The sums above as means in ms (None before there is anything to divide by)."""

        def mean_ms(total_s: float, count: int) -> float | None:
            return 1e3 * total_s / count if count else None

        frames = max(self.frames_in, self.frames_out)  # a source takes no frames in
        return {
            "cpu_ms": mean_ms(self.cpu_s, self.computed),
            "runtime_cpu_ms": mean_ms(max(0.0, self.process_cpu_s - self.cpu_s), frames),
            "transport_ms": mean_ms(self.transport_s, self.messages_in),
            "queue_ms": mean_ms(self.queue_s, self.messages_in),
            "wait_ms": mean_ms(self.wait_s, self.joined),
        }
