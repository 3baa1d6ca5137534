"""The first pass: one read of the log that scores every configuration of the table.

`Sweep` takes the frames one by one; per frame it fuses each weight row's maps and refines them with
each segmenter's masks (`umad_replay.row_scoring`), streaming every configuration's pixels into its
own `PixelMetrics`. The share that follows the frames (share 0) also keeps MNAD's metrics, the
default row's per scenario, the diagnosis and the overlay frames. With several processes each runs
`first_pass_share` on its share of the weight rows and share 0 merges their configurations
(`Sweep.merge_rows`) in the order one process meets them.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from umad_common.metrics.diagnosis import Diagnosis
from umad_common.metrics.pixel import LabelledPixels, PixelMetrics
from umad_common.refine import resize_nearest
from umad_replay.configurations import (
    LIDAR,
    PAPER_METRICS,
    Config,
    masks_name,
    shipped_row_index,
    weight_rows,
    with_shipped_row,
)
from umad_replay.frames import FrameRecord, LogStats, frames_from_log
from umad_replay.row_scoring import MaskSet, PaintedMap, model_size_inputs, normalised_maps, row_fused_map
from umad_replay.shares import dealt


@dataclass
class OverlayFrame:
    """Pictures of one frame for the overlay grid (the frames with the largest anomalies)."""

    run: str
    seq: int
    anomaly_pixels: int
    images: dict[str, np.ndarray]  # title -> (h, w, 3) uint8 image or (h, w) float map / labels


class Sweep:
    """Feed frames with `add`; every configuration's metrics stream as they come.

    `share` (index, count): this sweep is one of `count` processes sweeping the same log, and scores
    only the weight rows it owns (`owns`); share 0 owns the default row and also follows the frames.
    `merge_rows` pools the others' configurations into share 0's."""

    def __init__(
        self, overlay_frames: int = 6, every: int = 1, share: tuple[int, int] = (0, 1), shipped: dict | None = None
    ):
        index, count = share
        if not 0 <= index < count:
            raise ValueError(f"share {share}: expected (index, count) with 0 <= index < count")
        self.rows = with_shipped_row(weight_rows(), shipped)
        self.shipped = shipped
        self.every = every
        self.share = share
        self.metrics: dict[Config, PixelMetrics] = {}
        self.frames: dict[Config, int] = {}
        self.baseline: PixelMetrics | None = None
        self.baseline_frames = 0
        self.default_row: int | None = None
        self.per_scenario: dict[str, dict[str, PixelMetrics]] = {}
        self.overlay_frames = overlay_frames
        self._overlays: list[tuple[int, int, OverlayFrame]] = []  # min-heap on anomaly pixels
        self._tie = 0
        self.rows_seen: set[int] = set()
        self.scenario_tags: dict[str, set[int]] = {}
        self.frames_evaluated: dict[str, list[int]] = {}
        self.score_shapes: set[tuple[int, int]] = set()
        self.truth_shapes: set[tuple[int, int]] = set()
        self.diagnosis = Diagnosis()

    def _count(self, config: Config, scores: np.ndarray | PaintedMap, pixels: LabelledPixels) -> None:
        metrics = self.metrics.get(config)
        if metrics is None:
            metrics = self.metrics[config] = PixelMetrics()
        if isinstance(scores, PaintedMap):
            scores.count_into(metrics)
        else:
            metrics.update_labelled(scores, pixels)
        self.frames[config] = self.frames.get(config, 0) + 1

    def owns(self, row: int) -> bool:
        """Whether this share scores weight row `row`: share 0 the default row, the other rows by
        turns (row index modulo the share count), skipping the default row."""
        if row == self.default_row:
            return self.share[0] == 0
        return dealt(row, self.share)

    @property
    def follows_frames(self) -> bool:
        """Whether this share keeps what is not a weight row's metrics: MNAD, per scenario, diagnosis, overlays."""
        return self.share[0] == 0

    def add(self, frame: FrameRecord, segmenters: dict[str, str]) -> None:
        if frame.truth is None or frame.seq % self.every or (frame.mnad is None and not frame.diffs):
            return
        if self.follows_frames:
            self._follow(frame)
        if not frame.diffs:
            return
        shape, labels, masks = model_size_inputs(frame)
        pixels = LabelledPixels(labels)  # split once, read by every configuration's metrics
        self.score_shapes.add(shape)
        mask_sets = {op: MaskSet(op_masks, labels) for op, op_masks in masks.items()}
        names = {op: masks_name(segmenters, op) for op in mask_sets}
        usable = [i for i, row in enumerate(self.rows) if set(row.weights) <= set(frame.diffs)]
        camera_rows = [i for i in usable if LIDAR not in self.rows[i].weights]
        if self.default_row is None and camera_rows:
            self.default_row = max(camera_rows, key=lambda i: (len(self.rows[i].weights), not self.rows[i].extra, i))
        maps = {n: normalised_maps(frame.diffs, n) for n in {self.rows[i].normalization for i in usable}}
        pictures: dict[str, np.ndarray] = {}
        followed: dict[str, np.ndarray] = {}  # the default row's maps whose anomaly score the diagnosis follows
        for i in usable:
            self.rows_seen.add(i)
            if not self.owns(i):
                continue
            fused = row_fused_map(maps[self.rows[i].normalization], self.rows[i], frame, shape)
            self._count(Config(i, None, "none"), fused, pixels)
            if i == self.default_row:
                self._scenario(frame.run, "no mask").update_labelled(fused, pixels)
                pictures["fused"] = followed["fused"] = fused
            undrawn = i != self.default_row  # the default row's maps are pictured and followed
            for op, mask_set in mask_sets.items():
                for mode, refined in mask_set.refine_all(fused, self.rows[i].modes, undrawn).items():
                    self._count(Config(i, op, mode), refined, pixels)
                    if i == self.default_row:
                        name = names[op]
                        self._scenario(frame.run, f"{name} {mode}").update_labelled(refined, pixels)
                        if mode == "mean":
                            pictures[f"refined ({name} mean)"] = refined
                            followed[f"{name} mean"] = refined
        if self.follows_frames:  # the default row, whose maps these follow, is share 0's
            location = dict(frame.diffs) | ({"fused": followed["fused"]} if "fused" in followed else {})
            self.diagnosis.update(frame.run, frame.seq, frame.truth, frame.semantic, location, followed)
            self._keep_overlay(frame, labels, pictures)

    def _follow(self, frame: FrameRecord) -> None:
        """What share 0 keeps of each frame besides the weight rows: its scenario, shapes and MNAD."""
        self.scenario_tags.setdefault(frame.run, set()).update(frame.anomaly_tags)
        self.frames_evaluated.setdefault(frame.run, []).append(frame.seq)
        self.truth_shapes.add(tuple(frame.truth.shape))
        if frame.mnad is not None:
            self.baseline = self.baseline or PixelMetrics()
            mnad_labels = resize_nearest(frame.truth, frame.mnad.shape)
            self.baseline.update(frame.mnad, mnad_labels)
            self.baseline_frames += 1
            self._scenario(frame.run, "MNAD").update(frame.mnad, mnad_labels)

    def merge_rows(self, metrics: dict[Config, PixelMetrics], frames: dict[Config, int]) -> None:
        """Pool another share's configurations into this one, in the order one process would have
        met them: by row, then no mask before each segmenter (by op id), then the row's refinements."""
        self.metrics.update(metrics)
        self.frames.update(frames)

        def met_at(config: Config) -> tuple:
            modes = ("none", *self.rows[config.row].modes)
            return (config.row, config.segmenter is not None, config.segmenter or "", modes.index(config.mode))

        self.metrics = {config: self.metrics[config] for config in sorted(self.metrics, key=met_at)}
        self.frames = {config: self.frames[config] for config in self.metrics}

    def _scenario(self, run: str, label: str) -> PixelMetrics:
        per_run = self.per_scenario.setdefault(run, {})
        if label not in per_run:
            per_run[label] = PixelMetrics()
        return per_run[label]

    def _keep_overlay(self, frame: FrameRecord, labels: np.ndarray, pictures: dict[str, np.ndarray]) -> None:
        anomaly_pixels = int((labels == 1).sum())
        if self.overlay_frames <= 0 or anomaly_pixels == 0:
            return
        if len(self._overlays) >= self.overlay_frames and anomaly_pixels <= self._overlays[0][0]:
            return
        images: dict[str, np.ndarray] = {}
        if frame.target is not None:
            images["input"] = frame.target
        images["ground truth"] = labels
        if frame.recon is not None:
            images["reconstruction"] = frame.recon
        for metric in sorted(frame.diffs, key=lambda m: (PAPER_METRICS + (m,)).index(m)):
            images[metric] = frame.diffs[metric]
        images.update(pictures)
        if frame.mnad is not None:
            images["MNAD"] = frame.mnad
        self._tie += 1
        item = (anomaly_pixels, -self._tie, OverlayFrame(frame.run, frame.seq, anomaly_pixels, images))
        if len(self._overlays) < self.overlay_frames:
            heapq.heappush(self._overlays, item)
        else:
            heapq.heapreplace(self._overlays, item)

    def overlays(self) -> list[OverlayFrame]:
        """The overlay frames kept, the most anomaly pixels first (of equals, the one met first)."""
        return [item[2] for item in sorted(self._overlays, key=lambda t: (-t[0], -t[1]))]

    def shipped_config(self) -> Config | None:
        """The shipped configuration's cell of the table, or None where the graph had none."""
        row = shipped_row_index(self.rows, self.shipped)
        if row is None:
            return None
        return Config(row, self.shipped["segmenter"], self.shipped["mode"])


def first_pass_share(
    path: Path, lag: int, every: int, shipped: dict | None, share: tuple[int, int]
) -> tuple[dict[Config, PixelMetrics], dict[Config, int]]:
    """One share's first pass in a worker process: the metrics of its weight rows."""
    sweep = Sweep(overlay_frames=0, every=every, share=share, shipped=shipped)
    stats = LogStats()
    for frame in frames_from_log(path, stats, lag):
        sweep.add(frame, stats.segmenters)
    return sweep.metrics, sweep.frames
