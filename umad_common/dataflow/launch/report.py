"""What the launcher prints about a running graph: the progress line while it runs, and the
per-replica table when it ends (`umad launch`'s summary)."""

from __future__ import annotations

import time

PROGRESS_INTERVAL_S = 15.0


class ProgressLine:
    """Every PROGRESS_INTERVAL_S: frames acked by every sink, out of the total when the sources know
    it, with the rate and the time left. Nothing until the first frame is through."""

    def __init__(self) -> None:
        self.last = time.monotonic()
        self.first: tuple[float, int] | None = None

    def update(self, source_stats: list[dict | None]) -> str | None:
        now = time.monotonic()
        known = [s for s in source_stats if s]
        done = sum(s.get("acked", 0) for s in known)
        if done == 0 or now - self.last < PROGRESS_INTERVAL_S:
            return None
        self.last = now
        if self.first is None:
            self.first = (now, done)
            return f"{done} frames through the graph"
        rate = (done - self.first[1]) / max(now - self.first[0], 1e-9)
        totals = [s.get("total_frames") for s in known]
        if len(known) < len(source_stats) or None in totals:
            return f"{done} frames through the graph, {rate:.2f} frames/s"
        total = sum(totals)
        left = f", ~{(total - done) / rate:.0f} s left" if rate > 0 else ""
        return f"{done}/{total} frames ({100 * done / max(total, 1):.0f} %), {rate:.2f} frames/s{left}"


SUMMARY_TIMES = {  # stats field -> column: where a frame's time went in each replica, ms per frame
    "p50_ms": "p50",
    "p99_ms": "p99",
    "cpu_ms": "cpu",
    "runtime_cpu_ms": "rt cpu",
    "wait_ms": "wait",
    "queue_ms": "queue",
    "transport_ms": "bus",
}


def summary_table(stats: dict[str, dict]) -> str:
    """The final per-replica table: counts (`passed`: frames passed over in live mode for a newer
    one), then ms per frame: processing latency (p50, p99), the operator's own CPU (`cpu`), the
    runtime's and the bus's CPU in the process (`rt cpu`), waiting for a slower input (`wait`),
    waiting for this replica to be free (`queue`: replicate it), and the hop from the producer
    (`bus`)."""
    head = f"{'replica':<24}{'in':>7}{'out':>7}{'errors':>7}{'bad':>5}{'dups':>5}{'passed':>7}"
    lines = [head + "".join(f"{col:>8}" for col in SUMMARY_TIMES.values()) + "   (times: ms per frame)"]
    for name in sorted(stats):
        s = stats[name]
        row = (
            f"{name:<24}{s['frames_in']:>7}{s['frames_out']:>7}{s['errors']:>7}{s['bad_messages']:>5}"
            f"{s['duplicates']:>5}{s.get('superseded', 0):>7}"
        )
        times = [s.get(field) for field in SUMMARY_TIMES]
        lines.append(row + "".join(f"{t:>8.1f}" if t is not None else f"{'-':>8}" for t in times))
    return "\n".join(lines)
