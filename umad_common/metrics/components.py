"""Component-level metrics of SegmentMeIfYouCan (Chan et al. 2021): sIoU, PPV and mean F1.

A frame's score map is thresholded (score > threshold) into a predicted anomaly mask; predicted
components and ground-truth components are the 8-connected components of the predicted mask and of
the anomaly label. Pixels labelled 255 are outside the region of interest: predictions there are
dropped before labelling, and only region-of-interest pixels are counted.

- sIoU of a ground-truth component k: |k ∩ K̂(k)| / |(k ∪ K̂(k)) \\ A(k)|, with K̂(k) the union of
  predicted components touching k and A(k) the pixels of the other ground-truth components (a
  prediction that covers two objects is not punished twice).
- PPV of a predicted component k̂: the share of its pixels that lie on any ground-truth component.
- At each sIoU threshold t in 0.25, 0.30, ..., 0.75: TP = #{sIoU >= t}, FN = #{sIoU < t},
  FP = #{PPV < t}, pooled over frames; F1(t) = 2TP / (2TP + FN + FP); mean F1 averages the 11.

The threshold on the score map is given, or chosen as the best pixel-F1 threshold of the pooled
scores (`PixelMetrics.best_f1_threshold`), as the benchmark does. Optional size filters follow the
benchmark: predicted components below `min_predicted_size` pixels are removed, ground-truth
components below `min_truth_size` pixels become ignored (the benchmark uses 500 / 100 at 2048x1024;
here both default to 0 because maps are far smaller).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy import ndimage

from umad_common.metrics.pixel import ANOMALY, IGNORE, PixelMetrics

SIOU_THRESHOLDS = tuple(round(0.25 + 0.05 * i, 2) for i in range(11))
_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


def frame_components(
    scores: np.ndarray, labels: np.ndarray, threshold: float, min_predicted_size: int = 0, min_truth_size: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """sIoU per ground-truth component and PPV per predicted component of one frame.

    Args:
        scores: (H, W) anomaly scores.
        labels: (H, W) 0 normal / 1 anomaly / 255 ignored.
        threshold: a pixel is predicted anomalous when its float16-quantised score > threshold.

    Returns:
        (siou, ppv): float arrays, one entry per ground-truth / predicted component in the region
        of interest, in label order.
    """
    scores, labels = np.asarray(scores), np.asarray(labels)
    if scores.ndim != 2 or scores.shape != labels.shape:
        raise ValueError(f"expected 2-D scores and labels of equal shape, got {scores.shape} and {labels.shape}")
    labels = labels.astype(np.uint8, copy=True)
    truth, n_truth = ndimage.label(labels == ANOMALY, structure=_EIGHT_CONNECTED)
    above = scores.astype(np.float16) > threshold  # float16, like the pixel metrics' thresholds
    predicted, n_predicted = ndimage.label(above & (labels != IGNORE), structure=_EIGHT_CONNECTED)
    if min_predicted_size > 0 and n_predicted:
        small = np.bincount(predicted.ravel(), minlength=n_predicted + 1) < min_predicted_size
        small[0] = False
        predicted[small[predicted]] = 0
    if min_truth_size > 0 and n_truth:
        small = np.bincount(truth.ravel(), minlength=n_truth + 1) < min_truth_size
        small[0] = False
        labels[small[truth]] = IGNORE
    roi = labels != IGNORE
    truth_roi, predicted_roi = truth[roi].astype(np.int64), predicted[roi].astype(np.int64)
    # overlap[i, j] = pixels of truth component i and predicted component j (0 = background)
    overlap = np.bincount(truth_roi * (n_predicted + 1) + predicted_roi, minlength=(n_truth + 1) * (n_predicted + 1))
    overlap = overlap.reshape(n_truth + 1, n_predicted + 1)

    truth_sizes = overlap.sum(axis=1)
    touching = overlap[1:, 1:] > 0  # [truth i, predicted j]
    intersection = (overlap[1:, 1:] * touching).sum(axis=1)
    predicted_on_background = touching @ overlap[0, 1:]  # pixels of K̂(k) outside every truth component
    union = truth_sizes[1:] + predicted_on_background
    present_truth = truth_sizes[1:] > 0
    siou = intersection[present_truth] / union[present_truth]

    predicted_sizes = overlap.sum(axis=0)[1:]
    present_predicted = predicted_sizes > 0
    on_truth = overlap[1:, 1:].sum(axis=0)
    ppv = on_truth[present_predicted] / predicted_sizes[present_predicted]
    return siou.astype(np.float64), ppv.astype(np.float64)


class ComponentMetrics:
    """Pooled SegmentMeIfYouCan component metrics at a fixed score threshold."""

    def __init__(self, threshold: float, min_predicted_size: int = 0, min_truth_size: int = 0) -> None:
        if not np.isfinite(threshold):
            raise ValueError(f"component threshold must be a finite number, got {threshold}")
        self.threshold = float(threshold)
        self.min_predicted_size = int(min_predicted_size)
        self.min_truth_size = int(min_truth_size)
        self.siou: list[np.ndarray] = []
        self.ppv: list[np.ndarray] = []

    def update(self, scores: np.ndarray, labels: np.ndarray) -> None:
        """Add one (H, W) frame."""
        self.add_frame(*frame_components(scores, labels, self.threshold, self.min_predicted_size, self.min_truth_size))

    def add_frame(self, siou: np.ndarray, ppv: np.ndarray) -> None:
        """Add one frame's components as `frame_components` gave them (e.g. in another process)."""
        self.siou.append(siou)
        self.ppv.append(ppv)

    def compute(self) -> dict[str, float | int | dict[str, float]]:
        """Mean sIoU, mean PPV, F1 per sIoU threshold and mean F1 (NaN where nothing to count)."""
        siou = np.concatenate(self.siou) if self.siou else np.zeros(0)
        ppv = np.concatenate(self.ppv) if self.ppv else np.zeros(0)
        f1 = {}
        for t in SIOU_THRESHOLDS:
            tp = int(np.count_nonzero(siou >= t))
            fn = int(np.count_nonzero(siou < t))
            fp = int(np.count_nonzero(ppv < t))
            f1[f"{t:.2f}"] = 2 * tp / (2 * tp + fn + fp) if (2 * tp + fn + fp) else float("nan")
        return {
            "threshold": self.threshold,
            "sIoU": float(siou.mean()) if siou.size else float("nan"),
            "PPV": float(ppv.mean()) if ppv.size else float("nan"),
            "mean_F1": float(np.mean(list(f1.values()))),
            "F1": f1,
            "n_truth_components": int(siou.size),
            "n_predicted_components": int(ppv.size),
        }


def component_metrics(
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    threshold: float | None = None,
    min_predicted_size: int = 0,
    min_truth_size: int = 0,
) -> dict:
    """Component metrics over (scores, labels) frames; without a threshold, the best pixel-F1 one.

    `frames` is iterated twice when no threshold is given (pixel pass, then component pass), so pass
    a list or another re-iterable collection.
    """
    if threshold is None:
        pixels = PixelMetrics()
        for scores, labels in frames:
            pixels.update(scores, labels)
        threshold = pixels.best_f1_threshold()
    metrics = ComponentMetrics(threshold, min_predicted_size, min_truth_size)
    for scores, labels in frames:
        metrics.update(scores, labels)
    return metrics.compute()
