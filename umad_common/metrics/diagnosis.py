"""Where a model's error lives and whether an anomaly's score holds while it stays in view.

Two streaming accumulators, pure numpy, each with `update` and `compute` like the other metrics:

- `ErrorLocation`: of every frame's score map, the top 1 % of its (not ignored) pixels, counted by
  semantic class. Its shares say whether a map's highest scores sit on the object or on a normal
  region the model finds hard (facades, sky, lane marks).
- `ScoreSinceVisible`: per scenario, for every frame from the anomaly's first visible frame on
  (the first frame given whose anomaly mask is not empty), the anomaly pixels' score relative to
  the same frame's normal pixels, averaged per bin of frames since that first frame. A falling
  line is an object the model learns to draw while the ego watches it.

`Diagnosis` keeps both for several named maps, per scenario and overall. Memory is a 256-bin
histogram per (map, scenario) and a few sums per (map, scenario, bin): nothing grows with pixels.
"""

from __future__ import annotations

import math

import numpy as np

from umad_common.refine import resize_nearest

NORMAL, ANOMALY, IGNORE = 0, 1, 255
TOP_FRACTION = 0.01
BIN_FRAMES = 20
N_TAGS = 256  # semantic tags are uint8


def top_pixels(scores: np.ndarray, fraction: float) -> np.ndarray:
    """Flat indices of the ceil(fraction * n) highest of the 1-D `scores`, ascending; of pixels tied at
    the cut, the first by position. O(n): one partition, no sort."""
    k = min(scores.size, max(1, math.ceil(fraction * scores.size)))
    cut = np.partition(scores, scores.size - k)[scores.size - k]  # the k-th highest score
    above = np.flatnonzero(scores > cut)
    tied = np.flatnonzero(scores == cut)[: k - above.size]
    return np.sort(np.concatenate([above, tied]))


class ErrorLocation:
    """Shares of the top `fraction` of each frame's score pixels by semantic tag, pooled over frames.

    Example:
        >>> loc = ErrorLocation(fraction=0.5)
        >>> loc.update(np.array([[0.9, 0.8], [0.1, 0.2]]), np.array([[11, 3], [1, 1]]))
        >>> loc.compute()
        {3: 0.5, 11: 0.5}
    """

    def __init__(self, fraction: float = TOP_FRACTION):
        if not 0 < fraction <= 1:
            raise ValueError(f"ErrorLocation: fraction must be in (0, 1], got {fraction}")
        self.fraction = fraction
        self.counts = np.zeros(N_TAGS, dtype=np.int64)
        self.frames = 0

    def update(self, scores: np.ndarray, semantic: np.ndarray, valid: np.ndarray | None = None) -> None:
        """Count one frame's top pixels by class.

        Args:
            scores: (h, w) score map.
            semantic: (h, w) integer semantic tags, 0..255.
            valid: optional (h, w) bool, pixels to rank (the others, e.g. ignore-labelled, are left out).

        Raises:
            ValueError: shapes differ, or tags outside 0..255.
        """
        scores, semantic = np.asarray(scores), np.asarray(semantic)
        if scores.shape != semantic.shape or (valid is not None and np.shape(valid) != scores.shape):
            raise ValueError(
                f"ErrorLocation: scores {scores.shape}, semantic {semantic.shape}"
                + ("" if valid is None else f", valid {np.shape(valid)}")
                + "; expected one (h, w) shape"
            )
        if semantic.size and (semantic.min() < 0 or semantic.max() >= N_TAGS):
            raise ValueError(f"ErrorLocation: semantic tags span {semantic.min()}..{semantic.max()}; expected 0..255")
        keep = np.ones(scores.shape, bool) if valid is None else np.asarray(valid, bool)
        flat_scores = scores[keep].astype(np.float64)
        if flat_scores.size == 0:
            return
        tags = semantic[keep].astype(np.int64)[top_pixels(flat_scores, self.fraction)]
        self.counts += np.bincount(tags, minlength=N_TAGS)
        self.frames += 1

    def merge(self, other: ErrorLocation) -> None:
        self.counts += other.counts
        self.frames += other.frames

    def compute(self) -> dict[int, float]:
        """Tag -> share of the counted top pixels (summing to 1), largest share first; {} before any frame."""
        total = int(self.counts.sum())
        if total == 0:
            return {}
        tags = sorted(np.flatnonzero(self.counts), key=lambda t: (-self.counts[t], t))
        return {int(t): float(self.counts[t] / total) for t in tags}


def frame_relative_scores(scores: np.ndarray, labels: np.ndarray) -> dict[str, float] | None:
    """How one frame's anomaly pixels score against its normal pixels, or None when either class is empty.

    Returns:
        `rank`: the anomaly pixels' mean percentile rank among the normal pixels (ties count half;
        the frame's AUROC: 0.5 = no different, 1 = above every normal pixel); `ratio`: mean anomaly
        score / mean normal score; `ratio_p99`: mean anomaly score / the normal pixels' 99th
        percentile (below 1: the object scores under the frame's hardest normal region). A ratio
        whose denominator is not positive is NaN.
    """
    scores, labels = np.asarray(scores, dtype=np.float64), np.asarray(labels)
    if scores.shape != labels.shape:
        raise ValueError(f"scores {scores.shape} and labels {labels.shape}; expected one (h, w) shape")
    anomaly, normal = scores[labels == ANOMALY], np.sort(scores[labels == NORMAL])
    if anomaly.size == 0 or normal.size == 0:
        return None
    below = np.searchsorted(normal, anomaly, side="left")
    not_above = np.searchsorted(normal, anomaly, side="right")
    rank = float(np.mean(below + 0.5 * (not_above - below)) / normal.size)
    mean_normal, p99 = float(normal.mean()), float(np.percentile(normal, 99))
    mean_anomaly = float(anomaly.mean())
    return {
        "rank": rank,
        "ratio": mean_anomaly / mean_normal if mean_normal > 0 else math.nan,
        "ratio_p99": mean_anomaly / p99 if p99 > 0 else math.nan,
    }


class ScoreSinceVisible:
    """Per scenario: the anomaly's frame-relative score against frames since it first became visible.

    Frames of one scenario must come in ascending seq (as `umad_replay.frames` yields them); scenarios may
    interleave. Frames before the first visible one, and later frames without anomaly pixels, are
    not counted. Each counted frame weighs the same in its bin's means.
    """

    FIELDS = ("rank", "ratio", "ratio_p99")

    def __init__(self, bin_frames: int = BIN_FRAMES):
        if bin_frames < 1:
            raise ValueError(f"ScoreSinceVisible: bin_frames must be >= 1, got {bin_frames}")
        self.bin_frames = bin_frames
        self.first_visible: dict[str, int] = {}
        self._last_seq: dict[str, int] = {}
        self._sums: dict[str, dict[int, dict[str, list[float]]]] = {}  # run -> bin -> field -> [sum, n]

    def update(self, run: str, seq: int, scores: np.ndarray, labels: np.ndarray) -> None:
        """Add one frame (labels 0 normal, 1 anomaly, 255 ignored)."""
        if run in self._last_seq and seq <= self._last_seq[run]:
            raise ValueError(
                f"ScoreSinceVisible: run {run!r} frame {seq} after frame {self._last_seq[run]}; "
                "expected each run's frames in ascending seq, each once"
            )
        self._last_seq[run] = seq
        relative = frame_relative_scores(scores, labels)
        if run not in self.first_visible:
            if not np.any(np.asarray(labels) == ANOMALY):
                return
            self.first_visible[run] = seq
        if relative is None:
            return
        per_bin = self._sums.setdefault(run, {}).setdefault(
            (seq - self.first_visible[run]) // self.bin_frames, {f: [0.0, 0] for f in self.FIELDS}
        )
        for name, value in relative.items():
            if not math.isnan(value):
                per_bin[name][0] += value
                per_bin[name][1] += 1

    def _bins(self, sums: dict[int, dict[str, list[float]]]) -> list[dict]:
        return [
            {
                "from": b * self.bin_frames,
                "to": (b + 1) * self.bin_frames - 1,
                "frames": sums[b]["rank"][1],
                **{f: (sums[b][f][0] / sums[b][f][1] if sums[b][f][1] else None) for f in self.FIELDS},
            }
            for b in sorted(sums)
        ]

    def compute(self) -> dict[str, list[dict]]:
        """Run -> bins in order, each `{from, to, frames, rank, ratio, ratio_p99}` (frames since first
        visible, inclusive; means over the bin's frames, None where no frame had a value), and
        "all": the same over every scenario's frames."""
        out = {run: self._bins(sums) for run, sums in sorted(self._sums.items())}
        pooled: dict[int, dict[str, list[float]]] = {}
        for sums in self._sums.values():
            for b, fields in sums.items():
                target = pooled.setdefault(b, {f: [0.0, 0] for f in self.FIELDS})
                for f in self.FIELDS:
                    target[f][0] += fields[f][0]
                    target[f][1] += fields[f][1]
        if pooled:
            out["all"] = self._bins(pooled)
        return out


class Diagnosis:
    """`ErrorLocation` per named map (overall and per scenario) and `ScoreSinceVisible` per named map."""

    def __init__(self, fraction: float = TOP_FRACTION, bin_frames: int = BIN_FRAMES):
        self.fraction, self.bin_frames = fraction, bin_frames
        ErrorLocation(fraction), ScoreSinceVisible(bin_frames)  # check the arguments now
        self.location: dict[str, dict[str, ErrorLocation]] = {}  # run -> map name -> accumulator
        self.since_visible: dict[str, ScoreSinceVisible] = {}  # map name -> accumulator

    def update(
        self,
        run: str,
        seq: int,
        labels: np.ndarray,
        semantic: np.ndarray | None,
        location_maps: dict[str, np.ndarray],
        time_maps: dict[str, np.ndarray],
    ) -> None:
        """One frame.

        Args:
            labels: (h, w) 0/1/255 at the maps' size (each map is matched by nearest resize when
                its size differs).
            semantic: (H, W) semantic tags, or None where the data has no labels (location skipped).
            location_maps: name -> score map whose top pixels are counted by class.
            time_maps: name -> score map whose anomaly score is followed over time.
        """
        labelled = semantic is not None and np.any(semantic)
        resized: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}

        def at(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
            if shape not in resized:
                resized[shape] = (
                    resize_nearest(labels, shape),
                    resize_nearest(semantic, shape) if labelled else None,
                )
            return resized[shape]

        if labelled:
            per_run = self.location.setdefault(run, {})
            for name, score_map in location_maps.items():
                frame_labels, frame_semantic = at(np.shape(score_map))
                loc = per_run.setdefault(name, ErrorLocation(self.fraction))
                loc.update(score_map, frame_semantic, frame_labels != IGNORE)
        for name, score_map in time_maps.items():
            tracker = self.since_visible.setdefault(name, ScoreSinceVisible(self.bin_frames))
            tracker.update(run, seq, score_map, at(np.shape(score_map))[0])

    def compute(self) -> dict:
        """{"fraction", "bin_frames", "location": {"overall" | run: {map: {tag: share}}},
        "since_visible": {map: {run | "all": bins}}, "first_visible": {run: seq}}."""
        overall: dict[str, ErrorLocation] = {}
        for per_run in self.location.values():
            for name, loc in per_run.items():
                overall.setdefault(name, ErrorLocation(self.fraction)).merge(loc)
        location = {"overall": {n: loc.compute() for n, loc in overall.items()}} if overall else {}
        location |= {run: {n: loc.compute() for n, loc in per.items()} for run, per in sorted(self.location.items())}
        first = next(iter(self.since_visible.values()), None)
        return {
            "fraction": self.fraction,
            "bin_frames": self.bin_frames,
            "location": location,
            "since_visible": {name: tracker.compute() for name, tracker in self.since_visible.items()},
            "first_visible": dict(sorted(first.first_visible.items())) if first else {},
        }
