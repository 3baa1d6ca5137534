"""Streaming pixel metrics (`PixelMetrics`) against scikit-learn on the same pixels: time, peak memory, agreement.

`bench_metrics(n_pixels)` is what `umad bench metrics` runs. Both sides get the same float16
scores (what the SegmentMeIfYouCan protocol stores) and labels (1 % anomaly, 5 % ignored):
scikit-learn's `average_precision_score` + `roc_auc_score` on the whole pooled array, as an
offline evaluation would call them; `PixelMetrics` one frame-sized slice at a time, as the
accumulator sees the stream. Peak memory is what each side allocates on top of the input arrays
(tracemalloc, which numpy reports to), so the inputs themselves count for neither.
"""

from __future__ import annotations

import gc
import time
import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np

FRAME_PIXELS = 512 * 768  # one AnoVox camera frame per update


def make_pixels(n_pixels: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """float16 scores and uint8 labels (0 normal, 1 anomaly, 255 ignored), anomalies scoring higher."""
    rng = np.random.default_rng(seed)
    labels = np.zeros(n_pixels, np.uint8)
    u = rng.random(n_pixels, dtype=np.float32)
    labels[u < 0.01] = 1
    labels[u > 0.95] = 255
    scores = rng.random(n_pixels, dtype=np.float32)
    scores += 0.5 * (labels == 1)
    return scores.astype(np.float16), labels


def _measure(fn: Callable[[], dict[str, float]]) -> tuple[dict[str, float], float, int]:
    """(result, seconds, peak bytes allocated during the call)."""
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    start = time.perf_counter()
    result = fn()
    seconds = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return result, seconds, peak


def _streaming(scores: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    from umad_common.metrics.pixel import PixelMetrics

    metrics = PixelMetrics()
    for start in range(0, scores.size, FRAME_PIXELS):
        metrics.update(scores[start : start + FRAME_PIXELS], labels[start : start + FRAME_PIXELS])
    return metrics.compute()


def _sklearn(scores: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    from sklearn.metrics import average_precision_score, roc_auc_score

    keep = labels != 255
    y, s = labels[keep], scores[keep]
    return {"AP": float(average_precision_score(y, s)), "AUROC": float(roc_auc_score(y, s))}


def bench_metrics(n_pixels: int = 10**7, seed: int = 0) -> dict[str, Any]:
    """Time and peak memory of PixelMetrics vs scikit-learn on `n_pixels` pixels, and their agreement.

    Returns:
        {"n_pixels", "umad": {"seconds", "peak_mib", "AP", "AUROC"}, "sklearn": {...},
         "speedup": sklearn time / umad time, "memory_ratio": sklearn peak / umad peak,
         "max_abs_difference": of AP and AUROC}
    """
    if n_pixels < 100:
        raise ValueError(f"bench_metrics: n_pixels must be >= 100, got {n_pixels}")
    import sklearn.metrics  # noqa: F401  imported before measuring: import time and memory count for neither side

    import umad_common.metrics.pixel  # noqa: F401

    scores, labels = make_pixels(n_pixels, seed)
    ours, our_seconds, our_peak = _measure(lambda: _streaming(scores, labels))
    theirs, their_seconds, their_peak = _measure(lambda: _sklearn(scores, labels))
    mib = 1024 * 1024
    return {
        "n_pixels": n_pixels,
        "umad": {
            "seconds": round(our_seconds, 3),
            "peak_mib": round(our_peak / mib, 1),
            "AP": ours["AP"],
            "AUROC": ours["AUROC"],
        },
        "sklearn": {
            "seconds": round(their_seconds, 3),
            "peak_mib": round(their_peak / mib, 1),
            "AP": theirs["AP"],
            "AUROC": theirs["AUROC"],
        },
        "speedup": round(their_seconds / our_seconds, 1),
        "memory_ratio": round(their_peak / max(1, our_peak), 1),
        "max_abs_difference": max(abs(ours["AP"] - theirs["AP"]), abs(ours["AUROC"] - theirs["AUROC"])),
    }
