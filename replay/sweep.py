"""The paper's ablation from one recorded log: every fusion weight row x every mask setting, no model run.

Frames come from the log through `umad_replay.frames.frames_from_log` (truth, difference maps, masks per
segmenter, the MNAD map, regrouped by `(run, seq)`). Each configuration fuses and refines exactly as the live operators do (`umad_common.refine.fuse`
and `refine`, so a sweep row equals the live pipeline's numbers) and streams its pixels into its own
`PixelMetrics`: memory is one 1 MiB histogram per configuration plus a few frames in flight. With
`components`, a second read of the log adds SegmentMeIfYouCan component metrics for the headline
configurations at their best pixel-F1 thresholds, and per scenario the figures of the best row under
each headline mask setting and of the shipped configuration (the first pass follows only the default
row per scenario). The first
pass also feeds the report's diagnosis
(`umad_common.metrics.diagnosis`): where each map's top 1 % of pixels lies by semantic class, and the
anomaly's frame-relative score against frames since it first became visible.

Rows and settings: the paper's 15 weight rows in its order, then ours (`WeightRow.extra`): two more
groups; every group with SSIM again with the shift-tolerant SSIM (`ssim_shift`) in its place; then
every group again on `robust`-normalised maps (`umad_common.differences.robust` of the logged
min-max maps, equal to robust normalisation of the raw maps); then the lidar difference alone and
every min-max group with it added at `LIDAR_SHARE`; last, the shipped configuration's weights
(`umad_replay.protocol.shipped_configuration`: what the graph as run fused), where no row above has
them with its refinement. Rows of the paper's maps at min-max
are scored per segmenter with the refinements mean, max, single (the paper's), single_keep_raw and
mean_pixel (ours), plus no mask; the others with `mean` and `mean_pixel` refinement and no mask
only. A row whose map the log lacks (a graph without `diff_ssim_shift`) is skipped.
The log's metadata gives the protocol (`umad_replay.protocol`): data, models, the PD network.

With `workers` > 1 the first pass runs in that many processes, each reading the whole log and
scoring its share of the weight rows (`Sweep.owns`); the first also follows the frames (the default
row, MNAD, per scenario, diagnosis, overlays). Each configuration sees the same frames in the same
order with the same arithmetic, so the result is the one process's, bit for bit. The second pass
deals the scored frames out among as many processes and puts their components back in the order of
one read (`second_pass`).
"""

from __future__ import annotations

import heapq
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from fractions import Fraction
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from umad_common.dataflow.process.replica import one_blas_thread
from umad_common.dataflow.record.mcap_log import LogError, describe_loss, read_metadata, recording_outcome
from umad_common.differences.normalization import robust
from umad_common.metrics.components import ComponentMetrics, frame_components
from umad_common.metrics.diagnosis import Diagnosis
from umad_common.metrics.pixel import LabelledPixels, PixelMetrics
from umad_common.refine import (
    MAX_CHUNK_ELEMENTS,
    PIXEL_SHARE,
    fuse,
    only_the_best,
    resize_nearest,
    with_pixel_share,
)
from umad_replay.frames import FrameRecord, LogStats, frames_from_log
from umad_replay.protocol import run_protocol, shipped_configuration

PAPER_METRICS = ("abs", "mse", "ssim", "perceptual", "temporal")
REFINE_MODES = ("mean", "max", "single", "single_keep_raw", "mean_pixel")  # the last two are ours, not the paper's
PAPER_TRIPLES = (  # the paper's 1/3 rows, none with TD, in its order
    ("mse", "ssim", "perceptual"),
    ("abs", "ssim", "perceptual"),
    ("abs", "mse", "perceptual"),
    ("abs", "mse", "ssim"),
)
EXTRA_GROUPS = (  # rows of ours after the paper's: TD in a triple
    ("ssim", "perceptual", "temporal"),
    ("abs", "ssim", "temporal"),
)
STAND_INS = {"ssim": "ssim_shift"}  # a paper map -> the map of ours scored again in its place
LIDAR = "lidar"  # the lidar difference (ours): scored alone and added to every min-max group
LIDAR_SHARE = Fraction(1, 3)  # the lidar map's weight in a group it is added to (the group's own weights
#   scale by 1 - LIDAR_SHARE); chosen on validation seed 2 among 1/6, 1/3 and 1/2 (docs/experiments.md)


@dataclass(frozen=True)
class WeightRow:
    """One fusion weight row of the ablation table."""

    weights: dict[str, Fraction]  # metric -> weight, metrics in PAPER_METRICS order
    extra: bool = False  # True: a row of ours, not in the paper's table
    normalization: str = "minmax"  # of the maps it fuses: minmax (as logged, the paper's) or robust (ours)
    every_mode: bool = False  # True: every refinement scored whatever the maps (the shipped row added last)

    @property
    def modes(self) -> tuple[str, ...]:
        """The refinements scored for this row: all of them on the paper's maps, `mean` and `mean_pixel` on ours."""
        paper_maps = self.normalization == "minmax" and set(self.weights) <= set(PAPER_METRICS)
        return REFINE_MODES if paper_maps or self.every_mode else ("mean", "mean_pixel")

    def scores(self, mode: str) -> bool:
        """Whether this row is scored with refinement `mode` (`none`: no mask)."""
        return mode == "none" or mode in self.modes


def paper_weight_rows() -> list[WeightRow]:
    """The 15 weight rows of the UMAD ablation in the paper's order: each metric alone; the four
    triples at 1/3 (MSE+SSIM+PD, ABS+SSIM+PD, ABS+MSE+PD, ABS+MSE+SSIM); the five quadruples at 1/4
    leaving out ABS, MSE, SSIM, PD, TD in turn; all five at 1/5."""
    quadruples = [tuple(m for m in PAPER_METRICS if m != left_out) for left_out in PAPER_METRICS]
    groups = [(m,) for m in PAPER_METRICS] + list(PAPER_TRIPLES) + quadruples + [PAPER_METRICS]
    return [WeightRow({m: Fraction(1, len(group)) for m in group}) for group in groups]


def weight_rows() -> list[WeightRow]:
    """Every row the sweep computes: the paper's 15, then ours: EXTRA_GROUPS at equal weights, every
    one of those groups that holds a map in STAND_INS again with the stand-in, then all of those
    groups again on robust-normalised maps, then the lidar rows (`lidar_rows`) of the min-max groups."""
    extras = [WeightRow({m: Fraction(1, len(group)) for m in group}, extra=True) for group in EXTRA_GROUPS]
    groups = paper_weight_rows() + extras
    stand_ins = [
        WeightRow({STAND_INS.get(m, m): w for m, w in row.weights.items()}, extra=True)
        for row in groups
        if set(row.weights) & set(STAND_INS)
    ]
    minmax_rows = groups + stand_ins
    robust_rows = [WeightRow(row.weights, extra=True, normalization="robust") for row in minmax_rows]
    return minmax_rows + robust_rows + lidar_rows(minmax_rows)


METRIC_ORDER = (*PAPER_METRICS, *STAND_INS.values(), LIDAR)  # how a row lists its metrics


def shipped_weights(shipped: dict | None) -> dict[str, Fraction] | None:
    """The shipped configuration's fusion weights as fractions of their sum, in METRIC_ORDER (others
    after), or None without a shipped configuration."""
    if not shipped or not shipped["weights"]:
        return None
    total = sum(shipped["weights"].values())
    order = sorted(
        shipped["weights"], key=lambda m: (METRIC_ORDER.index(m) if m in METRIC_ORDER else len(METRIC_ORDER), m)
    )
    return {m: Fraction(shipped["weights"][m] / total).limit_denominator(1000) for m in order}


def shipped_row_index(rows: list[WeightRow], shipped: dict | None) -> int | None:
    """The first min-max row with the shipped weights that is scored with its refinement, or None."""
    weights = shipped_weights(shipped)
    if weights is None:
        return None
    return next(
        (
            i
            for i, row in enumerate(rows)
            if row.normalization == "minmax" and row.weights == weights and row.scores(shipped["mode"])
        ),
        None,
    )


def with_shipped_row(rows: list[WeightRow], shipped: dict | None) -> list[WeightRow]:
    """`rows`, and the shipped weights as one more row (every refinement scored) where none has them."""
    if shipped_weights(shipped) is None or shipped_row_index(rows, shipped) is not None:
        return rows
    return [*rows, WeightRow(shipped_weights(shipped), extra=True, every_mode=True)]


def lidar_rows(groups: list[WeightRow]) -> list[WeightRow]:
    """The lidar map alone, then each of `groups` with the lidar added at LIDAR_SHARE (ours)."""
    rows = [WeightRow({LIDAR: Fraction(1)}, extra=True)]
    for row in groups:
        weights = {m: w * (1 - LIDAR_SHARE) for m, w in row.weights.items()}
        rows.append(WeightRow({**weights, LIDAR: LIDAR_SHARE}, extra=True))
    return rows


def normalised_maps(diffs: dict[str, np.ndarray], normalization: str) -> dict[str, np.ndarray]:
    """A frame's logged (min-max) difference maps as a row of that normalization fuses them."""
    return diffs if normalization == "minmax" else {m: robust(d) for m, d in diffs.items()}


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

    The sweep refines 56 fused maps per frame with the same masks; converting the masks once per
    frame instead of once per call makes it several times faster. The results are bit-identical to
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


@dataclass(frozen=True)
class Config:
    """One table cell's configuration: a weight row and a mask setting."""

    row: int  # index into the weight rows
    segmenter: str | None  # segmenter op id; None = no mask
    mode: str  # mean | max | single | none


@dataclass
class OverlayFrame:
    """Pictures of one frame for the overlay grid (the frames with the largest anomalies)."""

    run: str
    seq: int
    anomaly_pixels: int
    images: dict[str, np.ndarray]  # title -> (h, w, 3) uint8 image or (h, w) float map / labels


@dataclass(frozen=True)
class PaperSetting:
    """One mask setting of the headline, as this run names it: the paper's, or ours after them."""

    label: str  # the setting's label in every table, e.g. "felzenszwalb mean"
    column: str  # the paper's column (gt, unsupervised, sam, max, none or single) or ours (unsupervised_pixel)


@dataclass
class SweepResult:
    rows: list[WeightRow]
    metrics: dict[Config, PixelMetrics]
    frames: dict[Config, int]
    baseline: PixelMetrics | None
    baseline_frames: int
    default_row: int | None
    per_scenario: dict[str, dict[str, PixelMetrics]]  # run -> setting label -> metrics
    overlays: list[OverlayFrame]
    stats: LogStats
    segmenters: dict[str, str]  # op -> method
    skipped_rows: list[int]
    seconds: float = 0.0
    components: dict[str, dict] = field(default_factory=dict)  # name -> ComponentMetrics.compute()
    scenario_tags: dict[str, set[int]] = field(default_factory=dict)  # run -> anomaly tags seen
    frames_evaluated: dict[str, list[int]] = field(default_factory=dict)  # run -> seqs scored, ascending
    score_shapes: set[tuple[int, int]] = field(default_factory=set)  # (h, w) the pixels were scored at
    truth_shapes: set[tuple[int, int]] = field(default_factory=set)  # (H, W) of the labels before resizing
    protocol: dict = field(default_factory=dict)  # what the run used: data, models, PD network (umad_replay.protocol)
    every: int = 1  # the sweep scored frames with seq % every == 0
    diagnosis: dict = field(default_factory=dict)  # Diagnosis.compute(): error location, score since visible
    shipped: Config | None = None  # what the graph as run produced (`shipped_configuration`), None without

    def row_label(self, row: int) -> str:
        label = weights_label(self.rows[row].weights)
        normalization = self.rows[row].normalization
        return label if normalization == "minmax" else f"{label}, {normalization}"

    def _ops_in_order(self) -> list[str]:
        rank = {"gt": 0, "sam": 2}
        return sorted(self.segmenters, key=lambda op: (rank.get(self.segmenters[op], 1), op))

    def _unsupervised_ops(self) -> list[str]:
        return [op for op in self._ops_in_order() if self.segmenters[op] not in ("gt", "sam")]

    def paper_settings(self) -> list[PaperSetting]:
        """The paper's mask settings in its order: each segmenter with mean refinement (GT,
        unsupervised, SAM), then max value, no mask and single mask with the first unsupervised
        segmenter's masks (ground truth's when the run had none)."""
        ops = self._ops_in_order()
        unsupervised = self._unsupervised_ops()
        if not ops:
            return [PaperSetting("no mask", "none")]
        main = masks_name(self.segmenters, (unsupervised or ops)[0])
        kinds = {"gt": "gt", "sam": "sam"}
        means = [
            PaperSetting(f"{masks_name(self.segmenters, op)} mean", kinds.get(self.segmenters[op], "unsupervised"))
            for op in ops
        ]
        return [
            *means,
            PaperSetting(f"{main} max", "max"),
            PaperSetting("no mask", "none"),
            PaperSetting(f"{main} single", "single"),
        ]

    def headline_settings(self) -> list[PaperSetting]:
        """The paper's mask settings, then ours: the first unsupervised segmenter with `mean_pixel`."""
        unsupervised = self._unsupervised_ops()
        ours = [f"{masks_name(self.segmenters, op)} mean_pixel" for op in unsupervised[:1]]
        return self.paper_settings() + [PaperSetting(label, "unsupervised_pixel") for label in ours]

    def setting_labels(self) -> list[str]:
        """Every mask setting's label in table order: the paper's, then ours (every other segmenter x mode)."""
        paper = [setting.label for setting in self.paper_settings()]
        every = [f"{masks_name(self.segmenters, op)} {mode}" for op in self._ops_in_order() for mode in REFINE_MODES]
        return paper + [label for label in every if label not in paper]

    def setting_label(self, config: Config) -> str:
        if config.segmenter is None:
            return "no mask"
        return f"{masks_name(self.segmenters, config.segmenter)} {config.mode}"

    def shipped_name(self) -> str | None:
        """`shipped: <mask setting>: <weight row>`, how tables name the shipped configuration; None without one."""
        if self.shipped is None:
            return None
        return f"shipped: {self.setting_label(self.shipped)}: {self.row_label(self.shipped.row)}"


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
        index, count = self.share
        if row == self.default_row:
            return index == 0
        return row % count == index

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
            weights = {m: float(w) for m, w in self.rows[i].weights.items()}
            fused = fuse({m: maps[self.rows[i].normalization][m] for m in weights}, weights, shape)
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

    def result(self, stats: LogStats) -> SweepResult:
        overlays = [item[2] for item in sorted(self._overlays, key=lambda t: (-t[0], -t[1]))]
        return SweepResult(
            rows=self.rows,
            metrics=self.metrics,
            frames=self.frames,
            baseline=self.baseline,
            baseline_frames=self.baseline_frames,
            default_row=self.default_row,
            per_scenario=self.per_scenario,
            overlays=overlays,
            stats=stats,
            segmenters=dict(stats.segmenters),
            skipped_rows=[i for i in range(len(self.rows)) if i not in self.rows_seen],
            scenario_tags=self.scenario_tags,
            frames_evaluated={run: sorted(seqs) for run, seqs in self.frames_evaluated.items()},
            score_shapes=self.score_shapes,
            truth_shapes=self.truth_shapes,
            every=self.every,
            diagnosis=self.diagnosis.compute(),
            shipped=self.shipped_config(),
        )

    def shipped_config(self) -> Config | None:
        """The shipped configuration's cell of the table, or None where the graph had none."""
        row = shipped_row_index(self.rows, self.shipped)
        if row is None:
            return None
        return Config(row, self.shipped["segmenter"], self.shipped["mode"])


def masks_name(segmenters: dict[str, str], op: str) -> str:
    """How tables name a segmenter op's masks (`segmenters`: op -> method): its method, or
    `method (op)` when several ops of the run share that method (two configurations of one
    segmenter compared side by side)."""
    method = segmenters.get(op, op)
    shared = sum(m == method for m in segmenters.values()) > 1
    return f"{method} ({op})" if shared else method


def model_size_inputs(frame: FrameRecord) -> tuple[tuple[int, int], np.ndarray, dict[str, np.ndarray]]:
    """The difference maps' (h, w) (the largest, should they differ) with labels and masks resized to it."""
    shape = max((m.shape for m in frame.diffs.values()), key=lambda s: (s[0] * s[1], s))
    labels = resize_nearest(frame.truth, shape)
    masks = {op: resize_nearest(packed.unpack(), shape) for op, packed in sorted(frame.masks.items())}
    return shape, labels, masks


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
    float_weights = {m: float(w) for m, w in row.weights.items()}
    maps = normalised_maps({m: frame.diffs[m] for m in float_weights}, row.normalization)
    fused = fuse(maps, float_weights, shape)
    if config.segmenter is None:
        return fused
    return mask_sets[config.segmenter].refine_all(fused, (config.mode,))[config.mode]


def component_configs(result: SweepResult) -> dict[str, Config]:
    """Configurations worth component metrics: the shipped one, the best-AP one and the default row per
    mask setting."""
    chosen: dict[str, Config] = {}
    if result.shipped in result.metrics:
        chosen[result.shipped_name()] = result.shipped
    scored = [c for c, m in result.metrics.items() if m.n_anomaly and m.n_normal]
    if scored:
        best = max(scored, key=lambda c: (result.metrics[c].compute()["AP"], -c.row))
        chosen[f"best AP: {result.row_label(best.row)}, {result.setting_label(best)}"] = best
    for config in sorted(result.metrics, key=lambda c: (c.segmenter or "", c.mode)):
        if config.row == result.default_row and config.mode in ("none", "mean") and config not in chosen.values():
            chosen[f"{result.row_label(config.row)}, {result.setting_label(config)}"] = config
    return chosen


def weights_label(weights: dict[str, Fraction]) -> str:
    """Short name of a weight row: `ssim`, `abs+ssim+perceptual (1/3)`, `all - temporal (1/4)`, `all (1/5)`."""
    names = list(weights)
    if len(names) == 1:
        return names[0]
    if LIDAR in weights:
        rest = {m: w / (1 - weights[LIDAR]) for m, w in weights.items() if m != LIDAR}
        return f"{weights_label(rest)} + lidar {weights[LIDAR]}"
    share = (
        f"({Fraction(1, len(names))})"
        if len(set(weights.values())) == 1
        else "(" + ", ".join(map(str, weights.values())) + ")"
    )
    if set(names) == set(PAPER_METRICS):
        return f"all {share}"
    missing = [m for m in PAPER_METRICS if m not in names]
    if len(missing) == 1 and set(names) <= set(PAPER_METRICS):
        return f"all - {missing[0]} {share}"
    return "+".join(names) + f" {share}"


def scenario_configs(result: SweepResult) -> dict[str, Config]:
    """The configurations the second pass scores per scenario: the shipped one (`shipped_name`), then
    the best-AP configuration under each of the headline's refined and no-mask settings (GT,
    unsupervised and SAM masks with `mean`, unsupervised with `mean_pixel`, no mask), as
    `best <setting>: <weight row>`."""
    chosen: dict[str, Config] = {}
    if result.shipped in result.metrics:
        chosen[result.shipped_name()] = result.shipped
    for setting in result.headline_settings():
        if setting.column not in ("gt", "unsupervised", "sam", "none", "unsupervised_pixel"):
            continue
        scored = [
            c
            for c, m in result.metrics.items()
            if result.setting_label(c) == setting.label and m.n_anomaly and m.n_normal
        ]
        if scored:
            best = max(scored, key=lambda c: (result.metrics[c].compute()["AP"], -c.row))
            chosen[f"best {setting.label}: {result.row_label(best.row)}"] = best
    return chosen


def second_pass(
    path: str | Path, result: SweepResult, lag: int = 32, every: int = 1, progress: bool = True, workers: int = 1
) -> dict[str, dict]:
    """A second read of the log, once the first has ranked every configuration: SegmentMeIfYouCan
    component metrics for `component_configs` and MNAD, each at its best pixel-F1 threshold from the
    first pass (returned), and per scenario the figures of `scenario_configs` (added to
    `result.per_scenario`: the first pass follows only the default row there).

    With `workers` > 1 the scored frames are dealt out in turn among that many processes, each
    reading the whole log; their components are put back in the order of one read, so the figures
    are one process's."""
    configs, best = component_configs(result), scenario_configs(result)
    thresholds = {name: result.metrics[c].best_f1_threshold() for name, c in configs.items()}
    if result.baseline is not None and result.baseline.n_anomaly:
        thresholds["MNAD"] = result.baseline.best_f1_threshold()
    task = partial(_second_pass_share, Path(path), result.rows, configs, best, thresholds, lag, every)
    with ExitStack() as stack:
        others = []
        if workers > 1:
            pool = share_pool(stack, workers)
            others = [pool.submit(task, (index, workers), False) for index in range(1, workers)]
        shares = [task((0, workers), progress), *(other.result() for other in others)]
    for share in shares:
        for run, per_run in share.per_scenario.items():
            merged = result.per_scenario.setdefault(run, {})
            for name in best:
                if name in per_run:
                    merged.setdefault(name, PixelMetrics()).merge(per_run[name])
    components = {}
    for name, threshold in thresholds.items():
        in_order = sorted(
            (frame for share in shares for frame in share.components[name]), key=lambda frame: frame.position
        )
        metrics = components[name] = ComponentMetrics(threshold)
        for frame in in_order:
            metrics.add_frame(frame.siou, frame.ppv)
    return {name: m.compute() for name, m in components.items()}


@dataclass
class FrameComponents:
    """One frame's components under one configuration: its place among the scored frames of one read."""

    position: int
    siou: np.ndarray
    ppv: np.ndarray


@dataclass
class SecondPassShare:
    components: dict[str, list[FrameComponents]]  # name -> its frames of this share
    per_scenario: dict[str, dict[str, PixelMetrics]]  # run -> best configuration's name -> metrics


def _second_pass_share(
    path: Path,
    rows: list[WeightRow],
    configs: dict[str, Config],
    best: dict[str, Config],
    thresholds: dict[str, float],
    lag: int,
    every: int,
    share: tuple[int, int],
    progress: bool,
) -> SecondPassShare:
    """The second pass over the scored frames k, k + n, ... of one read (`share` = (k, n))."""
    index, count = share
    out = SecondPassShare({name: [] for name in thresholds}, {})
    position = -1
    frames = tqdm(frames_from_log(path, LogStats(), lag), desc="second pass", unit="frame", disable=not progress)
    for frame in frames:
        if frame.truth is None or frame.seq % every:
            continue
        position += 1
        if position % count != index:
            continue
        if frame.mnad is not None and "MNAD" in thresholds:
            mnad_labels = resize_nearest(frame.truth, frame.mnad.shape)
            siou, ppv = frame_components(frame.mnad, mnad_labels, thresholds["MNAD"])
            out.components["MNAD"].append(FrameComponents(position, siou, ppv))
        if not frame.diffs:
            continue
        shape, labels, masks = model_size_inputs(frame)
        mask_sets = {op: MaskSet(op_masks) for op, op_masks in masks.items()}
        score_maps = {
            config: configuration_map(frame, rows[config.row], config, shape, mask_sets)
            for config in {*configs.values(), *best.values()}
        }
        for name, config in configs.items():
            if score_maps[config] is not None:
                siou, ppv = frame_components(score_maps[config], labels, thresholds[name])
                out.components[name].append(FrameComponents(position, siou, ppv))
        for name, config in best.items():
            if score_maps[config] is not None:
                per_run = out.per_scenario.setdefault(frame.run, {})
                per_run.setdefault(name, PixelMetrics()).update(score_maps[config], labels)
    return out


def _sweep_share(
    path: Path, lag: int, every: int, shipped: dict | None, share: tuple[int, int]
) -> tuple[dict[Config, PixelMetrics], dict[Config, int]]:
    """One share's first pass in a worker process: the metrics of its weight rows."""
    sweep = Sweep(overlay_frames=0, every=every, share=share, shipped=shipped)
    stats = LogStats()
    for frame in frames_from_log(path, stats, lag):
        sweep.add(frame, stats.segmenters)
    return sweep.metrics, sweep.frames


def sweep_log(
    path: str | Path,
    lag: int = 32,
    every: int = 1,
    overlay_frames: int = 6,
    components: bool = True,
    progress: bool = True,
    allow_incomplete: bool = False,
    workers: int = 1,
) -> SweepResult:
    """Compute every configuration's AP/FPR95/AUROC from one log (see the module docstring); with
    `components`, a second read adds component metrics for the headline configurations and the
    per-scenario figures of the best row under each headline mask setting (`second_pass`).

    A log whose recorder says it lacks messages is refused (LogError naming the channels and
    counts): its table would score other frames than the run's. `allow_incomplete` reports on it
    all the same, the protocol line saying what each channel lacks. `workers`: processes of each pass,
    sharing the weight rows (first) and the frames (second); the same result, see the module docstring."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: log file not found; expected an MCAP file written by the recorder")
    if lag < 0 or every < 1 or workers < 1:
        raise ValueError(
            f"sweep: lag must be >= 0, every and workers >= 1, got lag={lag}, every={every}, workers={workers}"
        )
    incomplete = describe_loss(recording_outcome(path))
    if incomplete and not allow_incomplete:
        raise LogError(
            f"{path}: the recording is incomplete: {incomplete}. A table from it would score other frames "
            "than the run did; pass --allow-incomplete to report on it anyway"
        )
    start = time.perf_counter()
    stats = LogStats()
    metadata = read_metadata(path)
    shipped = shipped_configuration(metadata)
    sweep = Sweep(overlay_frames=overlay_frames, every=every, share=(0, workers), shipped=shipped)
    others = []
    with one_blas_thread(), ExitStack() as stack:  # share 0 here, beside the other shares' processes
        if workers > 1:  # the other shares of the weight rows, each in its own process
            pool = share_pool(stack, workers)
            others = [
                pool.submit(_sweep_share, path, lag, every, shipped, (index, workers)) for index in range(1, workers)
            ]
        for frame in tqdm(frames_from_log(path, stats, lag), desc="sweep", unit="frame", disable=not progress):
            sweep.add(frame, stats.segmenters)
        for other in others:
            sweep.merge_rows(*other.result())
        result = sweep.result(stats)
        result.protocol = run_protocol(metadata, stats.map_notes)
        if incomplete:
            result.protocol["incomplete"] = incomplete
        if components:
            result.components = second_pass(path, result, lag, every, progress, workers)
    result.seconds = time.perf_counter() - start
    return result


def share_pool(stack: ExitStack, workers: int) -> ProcessPoolExecutor:
    """The processes of shares 1 .. workers - 1 (share 0 is the caller's), each with one BLAS thread:
    BLAS threads spinning beside the other shares' cost twice the CPU."""
    spawn = multiprocessing.get_context("spawn")
    return stack.enter_context(ProcessPoolExecutor(workers - 1, mp_context=spawn, initializer=one_blas_thread))
