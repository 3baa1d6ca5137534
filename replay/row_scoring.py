"""Scoring a weight row on one frame: its maps fused at model size, then refined with each
segmenter's masks exactly as `umad_common.refine.refine` would, and counted into pixel metrics.

`MaskSet` converts a frame's masks once and refines every row's fused map with them; `PaintedMap`
and `MaskLabels` let a refined map's pixels be counted one mask at a time instead of drawn.
`configuration_map` is one configuration's whole score map of a frame, for passes that need the map
itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from umad_common.differences.normalization import robust
from umad_common.metrics.pixel import LabelledPixels, PixelMetrics
from umad_common.refine import (
    MAX_CHUNK_ELEMENTS,
    PIXEL_SHARE,
    fuse,
    only_the_best,
    resize_nearest,
    scale_by_camera_agreement,
    weigh_down_above_lidar,
    with_pixel_share,
)
from umad_replay.configurations import LIDAR, REFINE_MODES, Config, WeightRow
from umad_replay.frames import FrameRecord


def normalised_maps(diffs: dict[str, np.ndarray], normalization: str) -> dict[str, np.ndarray]:
    """A frame's logged (min-max) difference maps as a row of that normalization fuses them."""
    return diffs if normalization == "minmax" else {m: robust(d) for m, d in diffs.items()}


def row_fused_map(
    maps: dict[str, np.ndarray], row: WeightRow, frame: FrameRecord, shape: tuple[int, int]
) -> np.ndarray:
    """One row's fused map of a frame from its normalised `maps`, as the fusion operator makes it
    (the camera maps weighed down above the lidar's returns, then the lidar map scaled by the camera
    maps' agreement, where the row does that)."""
    weights = {m: float(w) for m, w in row.weights.items()}
    row_maps = weigh_down_above_lidar({m: maps[m] for m in weights}, frame.above_lidar, LIDAR, row.above_lidar_weight)
    if frame.above_lidar is not None:
        row_maps = scale_by_camera_agreement(row_maps, LIDAR, weights, row.lidar_camera_exponent)
    return fuse(row_maps, weights, shape)


def model_size_inputs(frame: FrameRecord) -> tuple[tuple[int, int], np.ndarray, dict[str, np.ndarray]]:
    """The difference maps' (h, w) (the largest, should they differ) with labels and masks resized to it."""
    shape = max((m.shape for m in frame.diffs.values()), key=lambda s: (s[0] * s[1], s))
    labels = resize_nearest(frame.truth, shape)
    masks = {op: resize_nearest(packed.unpack(), shape) for op, packed in sorted(frame.masks.items())}
    return shape, labels, masks


@dataclass(frozen=True)
class MaskLabels:
    """A frame's labels as masks that do not overlap see them: per nonempty mask (in `MaskSet.nonempty`
    order) its normal, anomaly and ignored pixel counts, and the labels of the pixels no mask covers."""

    normal: np.ndarray
    anomaly: np.ndarray
    ignored: np.ndarray
    uncovered: np.ndarray  # flat indices of the pixels no mask covers
    uncovered_pixels: LabelledPixels


@dataclass(frozen=True)
class PaintedMap:
    """A mask-refined map left undrawn: each nonempty mask's score (float64, -inf: not painted) over
    `background` (a map, or one value everywhere). `count_into` adds to a `PixelMetrics` exactly the
    pixels of the map `MaskSet.paint` would draw, reading one count per mask instead of every pixel."""

    scores: np.ndarray
    background: np.ndarray | np.float32
    labels: MaskLabels

    def count_into(self, metrics: PixelMetrics) -> None:
        labels, painted = self.labels, np.isfinite(self.scores)
        values = self.scores[painted].astype(np.float32)  # as the drawn float32 map holds them
        metrics.update_counts(values, labels.normal[painted], labels.anomaly[painted], labels.ignored[painted].sum())
        if np.ndim(self.background) == 0:  # every pixel no painted mask covers holds the one value
            rest, uncovered = ~painted, labels.uncovered_pixels
            metrics.update_counts(
                np.array([self.background], np.float32),
                [labels.normal[rest].sum() + uncovered.normal.size],
                [labels.anomaly[rest].sum() + uncovered.anomaly.size],
                labels.ignored[rest].sum() + uncovered.n_ignored,
            )
        else:  # every mask painted (see `MaskSet.refine_all`): the background shows where no mask is
            background = np.asarray(self.background).reshape(-1)[labels.uncovered]
            metrics.update_labelled(background, labels.uncovered_pixels)


class MaskSet:
    """`refine(fused, masks, mode, uncovered="keep")` for many fused maps over the same masks.

    The sweep refines every weight row's fused map of a frame with the same masks, so the masks are
    converted once per frame, not once per call (docs/experiments.md). The results are bit-identical to
    `umad_common.refine.refine` (tests/test_sweep.py checks it): `mean` scores use the same float64
    product in the same chunks unless every mask's sum is exact in float64 (then any order gives
    refine's sums); `max` is exact whatever the order; painting gives each pixel the score that
    refine's `paint_masks` paints last.

    Given the frame's `labels`, masks that do not overlap (every segmenter's here) also count their
    pixels per class once, and `refine_all(..., undrawn=True)` returns the `mean`, `max` and `single`
    maps as `PaintedMap`s, whose metrics need one count per mask instead of every pixel.
    """

    def __init__(self, masks: np.ndarray, labels: np.ndarray | None = None):
        self.masks = masks  # (K, h, w) bool
        flat = masks.reshape(masks.shape[0], masks.shape[1] * masks.shape[2])
        self.areas = flat.sum(axis=1)
        self.dense = flat.astype(np.float64)  # (K, N), the operand refine's `mean` builds on every call
        self.chunk = max(1, MAX_CHUNK_ELEMENTS // max(1, flat.shape[1]))
        self.owners, self.pixels = np.nonzero(flat)  # (mask, pixel) pairs: pixels of mask 0, then mask 1, ...
        self.covered = flat.any(axis=0).reshape(masks.shape[1:])
        self.nonempty = np.flatnonzero(self.areas > 0)
        self.starts = np.searchsorted(self.owners, self.nonempty)
        self.overlapping = self.pixels.size > int(self.covered.sum())
        self.labels = None if labels is None or self.overlapping else self._mask_labels(labels)

    def _mask_labels(self, labels: np.ndarray) -> MaskLabels:
        flat_labels = labels.reshape(-1)
        owner = np.full(flat_labels.size, -1, np.int64)  # per pixel: the one mask covering it, -1 none
        owner[self.pixels] = self.owners

        def count(label: int) -> np.ndarray:
            return np.bincount(owner[flat_labels == label] + 1, minlength=self.masks.shape[0] + 1)[1:][self.nonempty]

        normal, anomaly = count(0), count(1)
        uncovered = np.flatnonzero(~self.covered.reshape(-1))
        return MaskLabels(
            normal=normal,
            anomaly=anomaly,
            ignored=self.areas[self.nonempty] - normal - anomaly,
            uncovered=uncovered,
            uncovered_pixels=LabelledPixels(flat_labels[uncovered]),
        )

    def exact_sums(self, values: np.ndarray) -> np.ndarray | None:
        """Each nonempty mask's sum of `values` (float64 copies of float32 scores, mask by mask as in
        `pixels`), or None unless every sum is exact in any order: a mask's values are all multiples of
        its smallest nonzero magnitude's float32 spacing q, so every partial sum, in any order, is a
        multiple of q no larger than the sum of the magnitudes, exact while that stays under 2**53 q
        (checked with a factor 2 to spare for the rounded bound)."""
        magnitudes = np.abs(values)
        bound = np.add.reduceat(magnitudes, self.starts)
        smallest = np.minimum.reduceat(np.where(magnitudes > 0, magnitudes, np.inf), self.starts)
        all_zero = np.isinf(smallest)
        spacing = np.spacing(np.where(all_zero, 1.0, smallest).astype(np.float32)).astype(np.float64)
        if not np.all(all_zero | (bound < 2.0**52 * spacing)):
            return None
        return np.add.reduceat(values, self.starts)

    def mean_scores(self, fused: np.ndarray) -> np.ndarray:
        flat_scores = np.asarray(fused, dtype=np.float64).reshape(-1)
        scores = np.full(self.masks.shape[0], -np.inf)
        sums = self.exact_sums(flat_scores[self.pixels]) if self.nonempty.size else None
        if sums is not None:
            scores[self.nonempty] = sums / self.areas[self.nonempty]
            return scores
        for start in range(0, self.masks.shape[0], self.chunk):
            areas = self.areas[start : start + self.chunk]
            sums = self.dense[start : start + self.chunk] @ flat_scores
            scores[start : start + self.chunk] = np.where(areas > 0, sums / np.maximum(areas, 1), -np.inf)
        return scores

    def max_scores(self, fused: np.ndarray) -> np.ndarray:
        scores = np.full(self.masks.shape[0], -np.inf)
        if self.nonempty.size:
            values = np.asarray(fused, dtype=np.float64).reshape(-1)[self.pixels]
            scores[self.nonempty] = np.maximum.reduceat(values, self.starts)
        return scores

    def paint(self, scores: np.ndarray, background: np.ndarray) -> np.ndarray:
        """`paint_masks(scores, self.masks, background)` in one pass over the mask pixels: paint_masks
        paints the finite-scored masks in stable ascending score order, so each covered pixel ends
        with the score of its mask latest in that order (of masks that do not overlap: its one mask)."""
        out = np.array(background, dtype=np.float32, copy=True).reshape(-1)
        if not self.overlapping:
            if np.isfinite(scores[self.nonempty]).all():
                out[self.pixels] = scores[self.owners]
            else:
                painted = np.isfinite(scores)[self.owners]
                out[self.pixels[painted]] = scores[self.owners[painted]]
            return out.reshape(background.shape)
        paint_order = np.argsort(scores, kind="stable")
        position = np.empty(scores.size, dtype=np.int64)
        position[paint_order] = np.arange(scores.size)
        position[~np.isfinite(scores)] = -1  # never painted
        last = np.full(background.size, -1, dtype=np.int64)  # per pixel: the latest painted mask's position
        np.maximum.at(last, self.pixels, position[self.owners])
        covered = last >= 0
        out[covered] = scores[paint_order][last[covered]]
        return out.reshape(background.shape)

    def refine_all(
        self, fused: np.ndarray, modes: tuple[str, ...] = REFINE_MODES, undrawn: bool = False
    ) -> dict[str, np.ndarray | PaintedMap]:
        """The `modes` (of REFINE_MODES) maps of one fused map (uncovered pixels keep their score;
        `single` gives every pixel outside the winning mask the frame's lowest score). With `undrawn`
        and the frame's labels counted (`labels`), `mean`, `max` and `single` come as `PaintedMap`s
        where every mask they paint is scored (always so for `single`, whose background is one value)."""
        fused = np.asarray(fused, dtype=np.float32)
        lowest = np.full_like(fused, fused.min())
        if self.masks.shape[0] == 0:
            empty = {"mean": fused, "max": fused, "single": lowest, "single_keep_raw": fused, "mean_pixel": fused}
            return {mode: empty[mode].copy() for mode in modes}
        mean = self.mean_scores(fused)
        single = only_the_best(mean) if {"single", "single_keep_raw"} & set(modes) else mean
        mean_map = self.paint(mean, fused) if {"mean", "mean_pixel"} & set(modes) else None

        def painted(scores: np.ndarray, background: np.ndarray, one_value: bool = False) -> np.ndarray | PaintedMap:
            kept = scores[self.nonempty]
            if undrawn and self.labels is not None and (one_value or np.isfinite(kept).all()):
                return PaintedMap(kept, background.flat[0] if one_value else background, self.labels)
            return self.paint(scores, background)

        refinements = {
            "mean": lambda: painted(mean, fused) if undrawn else mean_map,
            "max": lambda: painted(self.max_scores(fused), fused),
            "single": lambda: painted(single, lowest, one_value=True),
            "single_keep_raw": lambda: self.paint(single, fused),
            "mean_pixel": lambda: with_pixel_share(mean_map, fused, self.covered, PIXEL_SHARE),
        }
        return {mode: refinements[mode]() for mode in modes}


def configuration_map(
    frame: FrameRecord,
    row: WeightRow,
    config: Config,
    shape: tuple[int, int],
    mask_sets: dict[str, MaskSet],
) -> np.ndarray | None:
    """One configuration's score map of a frame (refined as `refine(..., uncovered="keep")` would), or
    None when the frame lacks a map or mask it needs."""
    if not set(row.weights) <= set(frame.diffs) or (config.segmenter is not None and config.segmenter not in mask_sets):
        return None
    fused = row_fused_map(
        normalised_maps({m: frame.diffs[m] for m in row.weights}, row.normalization), row, frame, shape
    )
    if config.segmenter is None:
        return fused
    return mask_sets[config.segmenter].refine_all(fused, (config.mode,))[config.mode]
