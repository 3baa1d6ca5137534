"""Streaming pixel-level AP, FPR95 and AUROC over float16-quantised anomaly scores.

Scores are quantised to float16, as the SegmentMeIfYouCan benchmark stores them, so every score is
one of 65,536 bit patterns. `PixelMetrics` keeps one histogram per class (normal, anomaly) over
those patterns: memory is O(1) in the number of pixels (2 x 65,536 int64 counts = 1 MiB) and the
results equal scikit-learn's on the float16 scores, because sorting the pooled scores only ever
needs the count of each class at each distinct value.

Conventions (scikit-learn's, on the quantised scores):

- thresholds run over the distinct scores present, high to low; a pixel is "anomaly" when its
  score >= threshold;
- AP is the step rule sum_k (R_k - R_{k-1}) P_k (`average_precision_score`);
- FPR95 is the FPR at the first threshold whose TPR >= 0.95;
- AUROC is the trapezoid under (FPR, TPR) starting at (0, 0) (`roc_auc_score`).

AP, FPR95 and AUROC are NaN when no anomaly pixel was seen (scikit-learn warns or raises there);
FPR95 and AUROC are NaN too when no normal pixel was seen. Float16 overflows beyond +-65504 to
+-inf, which is still ordered correctly but merges all such scores into one value. -0 and +0 are
one value. NaN scores are refused with a ValueError.
"""

from __future__ import annotations

import numpy as np

NORMAL, ANOMALY, IGNORE = 0, 1, 255
N_PATTERNS = 1 << 16
_UPDATE_CHUNK = 1 << 22  # pixels per internal step: bounds the temporaries of one update()


def _value_order() -> tuple[np.ndarray, np.ndarray]:
    """For every float16 bit pattern: its rank among the distinct non-NaN values (ascending).

    Returns (rank_of_pattern, distinct_values); -0 and +0 share a rank, NaN patterns have rank 0
    (they are never counted).
    """
    values = np.arange(N_PATTERNS, dtype=np.uint32).astype(np.uint16).view(np.float16).astype(np.float64)
    is_nan = np.isnan(values)
    distinct, rank = np.unique(values[~is_nan], return_inverse=True)
    rank_of_pattern = np.zeros(N_PATTERNS, dtype=np.int64)
    rank_of_pattern[~is_nan] = rank
    return rank_of_pattern, distinct


_RANK_OF_PATTERN, _DISTINCT_VALUES = _value_order()


_REBIAS = np.uint32((((15 - 127) << 23) + 0xFFF) & 0xFFFFFFFF)  # float32 -> float16 exponent, minus half an ulp
_SUBNORMAL_MAGIC = np.array([(127 - 15 + 23 - 10 + 1) << 23], np.uint32)  # 0.5 as float32, adding aligns to 2**-24


def _float16_patterns(scores: np.ndarray) -> np.ndarray:
    """The flat scores' float16 bit patterns; NaN refused (ValueError). Float32 scores (every map the
    sweep scores) are converted by `_float32_to_float16_bits`, the others by numpy's cast."""
    if scores.dtype.kind in "fc" and np.isnan(scores).any():
        raise ValueError("scores contain NaN; expected finite or infinite numbers (NaN has no rank)")
    if scores.dtype == np.float32:
        return _float32_to_float16_bits(scores.reshape(-1))
    return scores.reshape(-1).astype(np.float16, copy=False).view(np.uint16)


def _float32_to_float16_bits(values: np.ndarray) -> np.ndarray:
    """numpy's `values.astype(np.float16).view(np.uint16)` for finite or infinite float32 values, bit
    for bit (checked over every non-NaN float32 when this was written; tests/test_metrics.py checks
    the edges), faster than numpy's cast (docs/experiments.md): in place on the integer bits, rounding to nearest
    even by adding half an ulp less one plus the kept mantissa's lowest bit; the few values below
    float16's normal range rounded by the FPU's own float32 addition of 0.5 (whose ulp is float16's
    subnormal spacing), those at or past 65520 made infinite."""
    bits = np.ascontiguousarray(values, np.float32).view(np.uint32)
    magnitude = bits & np.uint32(0x7FFFFFFF)
    half = magnitude >> 13
    half &= np.uint32(1)
    half += magnitude
    half += _REBIAS
    half >>= 13
    if magnitude.min(initial=np.uint32(0xFFFFFFFF)) < np.uint32(113 << 23):
        subnormal = (magnitude.view(np.float32) + _SUBNORMAL_MAGIC.view(np.float32)).view(np.uint32)
        subnormal -= _SUBNORMAL_MAGIC
        np.copyto(half, subnormal, where=magnitude < np.uint32(113 << 23))
    if magnitude.max(initial=np.uint32(0)) >= np.uint32((127 + 16) << 23):
        half[magnitude >= np.uint32((127 + 16) << 23)] = 0x7C00
    half |= (bits >> 16) & np.uint32(0x8000)
    return half.astype(np.uint16)


class LabelledPixels:
    """One frame's labels checked and split by class once: the flat indices of its normal and its
    anomaly pixels and the count of ignored ones. The sweep scores ~200 maps per frame over the same
    labels; `PixelMetrics.update_labelled` then only reads the scores.

    Raises:
        ValueError: a label is not 0/1/255, or the labels are not integers.
    """

    def __init__(self, labels: np.ndarray):
        labels = np.asarray(labels)
        if labels.dtype.kind not in "biu":
            raise ValueError(f"labels must be integers 0/1/255, got dtype {labels.dtype}")
        if labels.dtype not in (np.uint8, np.bool_) and labels.size and (labels.min() < 0 or labels.max() > 255):
            raise ValueError(f"labels must be 0, 1 or 255, got values in [{labels.min()}, {labels.max()}]")
        flat = labels.reshape(-1).astype(np.uint8, copy=False)
        label_counts = np.bincount(flat, minlength=256)
        bad = np.flatnonzero(label_counts)
        bad = bad[(bad != NORMAL) & (bad != ANOMALY) & (bad != IGNORE)]
        if bad.size:
            raise ValueError(f"labels must be 0 (normal), 1 (anomaly) or 255 (ignore), got {bad[:5].tolist()}")
        self.size = flat.size
        self.normal = np.flatnonzero(flat == NORMAL)
        self.anomaly = np.flatnonzero(flat == ANOMALY)
        self.n_ignored = int(label_counts[IGNORE])


class PixelMetrics:
    """Pooled pixel metrics over any number of frames, exact on float16-quantised scores.

    Example:
        >>> m = PixelMetrics()
        >>> m.update(np.array([0.9, 0.1, 0.4]), np.array([1, 0, 255]))
        >>> m.compute()["AP"]
        1.0
    """

    def __init__(self) -> None:
        self.hist = np.zeros((2, N_PATTERNS), dtype=np.int64)  # [class, float16 bit pattern]
        self.n_ignored = 0

    def update(self, scores: np.ndarray, labels: np.ndarray) -> None:
        """Add one frame (any shape; scores and labels of equal shape).

        Args:
            scores: anomaly scores, higher = more anomalous; any float or integer dtype.
            labels: 0 normal, 1 anomaly, 255 ignored (uint8, bool or any integer dtype).

        Raises:
            ValueError: shapes differ, a label is not 0/1/255, or a score is NaN.
        """
        scores, labels = np.asarray(scores), np.asarray(labels)
        if scores.shape != labels.shape:
            raise ValueError(
                f"scores of shape {scores.shape} and labels of shape {labels.shape} must have the same shape"
            )
        flat_scores, flat_labels = scores.reshape(-1), labels.reshape(-1)
        for start in range(0, flat_scores.size, _UPDATE_CHUNK):
            chunk = slice(start, start + _UPDATE_CHUNK)
            self.update_labelled(flat_scores[chunk], LabelledPixels(flat_labels[chunk]))

    def update_labelled(self, scores: np.ndarray, pixels: LabelledPixels) -> None:
        """Add one frame whose labels were split by class once (`LabelledPixels`), for many score maps
        over the same labels: only the scores are read here.

        Args:
            scores: anomaly scores of `pixels.size` pixels (any shape, read in C order).
            pixels: the frame's labels, as `LabelledPixels`.

        Raises:
            ValueError: a score is NaN, or the scores are not `pixels.size` many.
        """
        scores = np.asarray(scores)
        if scores.size != pixels.size:
            raise ValueError(f"{scores.size} scores for {pixels.size} labelled pixels; expected one score per pixel")
        patterns = _float16_patterns(scores)
        for label, index in ((NORMAL, pixels.normal), (ANOMALY, pixels.anomaly)):
            counts = np.bincount(patterns[index])  # as long as the highest pattern present, not 65,536
            self.hist[label, : counts.size] += counts
        self.n_ignored += pixels.n_ignored

    def update_counts(self, scores: np.ndarray, normal: np.ndarray, anomaly: np.ndarray, ignored: int = 0) -> None:
        """Add pixels given as counts per score: `normal[i]` normal and `anomaly[i]` anomaly pixels
        scored `scores[i]`, and `ignored` ignored ones; the same as `update` with a map holding those
        pixels. For maps made of few distinct values (a mask-refined map: one score per mask).

        Raises:
            ValueError: a score is NaN, or the three arrays differ in length.
        """
        scores = np.asarray(scores).reshape(-1)
        if not scores.size == len(normal) == len(anomaly):
            raise ValueError(
                f"{scores.size} scores, {len(normal)} normal and {len(anomaly)} anomaly counts; expected one of each per score"
            )
        patterns = _float16_patterns(scores)
        np.add.at(self.hist[NORMAL], patterns, normal)
        np.add.at(self.hist[ANOMALY], patterns, anomaly)
        self.n_ignored += int(ignored)

    def merge(self, other: PixelMetrics) -> PixelMetrics:
        """Pool another accumulator's pixels into this one (e.g. per-run -> overall); returns self."""
        self.hist += other.hist
        self.n_ignored += other.n_ignored
        return self

    def reset(self) -> None:
        self.hist[:] = 0
        self.n_ignored = 0

    @property
    def n_anomaly(self) -> int:
        return int(self.hist[ANOMALY].sum())

    @property
    def n_normal(self) -> int:
        return int(self.hist[NORMAL].sum())

    def _cumulative(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Thresholds (distinct scores present, descending) with the cumulative TP and FP counts."""
        n_values = _DISTINCT_VALUES.size
        neg = np.bincount(_RANK_OF_PATTERN, weights=self.hist[NORMAL], minlength=n_values)
        pos = np.bincount(_RANK_OF_PATTERN, weights=self.hist[ANOMALY], minlength=n_values)
        present = np.flatnonzero((neg + pos) > 0)[::-1]  # descending score
        return _DISTINCT_VALUES[present], np.cumsum(pos[present]), np.cumsum(neg[present])

    def roc_curve(self) -> dict[str, np.ndarray]:
        """FPR and TPR per threshold, starting at (0, 0) with threshold +inf (as scikit-learn does)."""
        thresholds, tp, fp = self._cumulative()
        n_pos, n_neg = (tp[-1], fp[-1]) if tp.size else (0.0, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            tpr = np.concatenate([[0.0], tp / n_pos])
            fpr = np.concatenate([[0.0], fp / n_neg])
        return {"fpr": fpr, "tpr": tpr, "thresholds": np.concatenate([[np.inf], thresholds])}

    def pr_curve(self) -> dict[str, np.ndarray]:
        """Precision and recall per threshold (descending thresholds), ending at recall 0 / precision 1."""
        thresholds, tp, fp = self._cumulative()
        n_pos = tp[-1] if tp.size else 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            precision = tp / (tp + fp)
            recall = tp / n_pos
        return {
            "precision": np.concatenate([[1.0], precision]),
            "recall": np.concatenate([[0.0], recall]),
            "thresholds": np.concatenate([[np.inf], thresholds]),
        }

    def best_f1_threshold(self) -> float:
        """The score threshold of best pixel F1 (SegmentMeIfYouCan's choice for component metrics)."""
        curve = self.pr_curve()
        p, r = curve["precision"][1:], curve["recall"][1:]
        if p.size == 0 or self.n_anomaly == 0:
            raise ValueError("best F1 threshold needs at least one anomaly pixel")
        with np.errstate(invalid="ignore", divide="ignore"):
            f1 = 2 * p * r / (p + r)
        return float(curve["thresholds"][1:][np.nanargmax(f1)])

    def compute(self) -> dict[str, float | int]:
        """AP, FPR95, AUROC (floats, NaN where undefined) and the pixel counts."""
        thresholds, tp, fp = self._cumulative()
        n_pos, n_neg = self.n_anomaly, self.n_normal
        result: dict[str, float | int] = {
            "AP": float("nan"),
            "FPR95": float("nan"),
            "AUROC": float("nan"),
            "n_anomaly": n_pos,
            "n_normal": n_neg,
            "n_ignored": self.n_ignored,
        }
        if n_pos == 0:
            return result
        recall = tp / n_pos
        precision = tp / (tp + fp)
        result["AP"] = float(np.sum(np.diff(recall, prepend=0.0) * precision))
        if n_neg == 0:
            return result
        fpr = np.concatenate([[0.0], fp / n_neg])
        tpr = np.concatenate([[0.0], recall])
        result["FPR95"] = float(fpr[np.searchsorted(tpr, 0.95, side="left")])
        result["AUROC"] = float(np.trapezoid(tpr, fpr))
        return result
