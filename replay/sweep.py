"""The paper's ablation from one recorded log: every fusion weight row x every mask setting, no model run.

A log (replay/log.py) holds each bus message's exact payload on the channel `umad/<graph>/<op>/<output>`.
The sweep regroups the messages it needs by frame `(run, seq)`:

- `<replayer>/truth`    -> the anomaly labels (0/1/255);
- `<world_model>/frame` -> target and reconstruction (kept as uint8, for the overlay pictures);
- `<op>/map` with meta `metric` -> one normalised difference map per metric;
- `<segmenter>/masks`   -> (K, h, w) bool masks per segmenter operator (meta `method`);
- `<op>/map` with meta `model: mnad` (or op id `mnad`) -> the MNAD baseline's L2 map.

Each configuration fuses and refines exactly as the live operators do (`umad_common.refine.fuse`
and `refine`, so a sweep row equals the live pipeline's numbers) and streams its pixels into its own
`PixelMetrics`: memory is one 1 MiB histogram per configuration plus a few frames in flight. A frame
is complete once its run has moved `lag` frames further (lossless delivery keeps frames at most a
window apart); a message arriving later is counted as late and dropped.
"""

from __future__ import annotations

import bisect
import heapq
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np
from tqdm import tqdm

from replay.log import LogError, read_log
from umad_common.messages import MessageError, decode
from umad_common.metrics.components import ComponentMetrics
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import fuse, refine, resize_nearest

PAPER_METRICS = ("abs", "mse", "ssim", "perceptual", "temporal")
METRIC_ALIASES = {"pd": "perceptual", "td": "temporal", "l1": "abs", "l2": "mse"}
WANTED_OUTPUTS = ("truth", "frame", "map", "masks")
REFINE_MODES = ("mean", "max", "single")


def paper_weight_rows() -> list[dict[str, Fraction]]:
    """The 15 weight rows of the UMAD ablation: each metric alone, four triples at 1/3, the five
    leave-one-out quadruples at 1/4 and all five at 1/5."""
    triples = [
        ("abs", "ssim", "perceptual"),
        ("mse", "ssim", "perceptual"),
        ("abs", "ssim", "temporal"),
        ("ssim", "perceptual", "temporal"),
    ]
    quadruples = [tuple(m for m in PAPER_METRICS if m != left_out) for left_out in PAPER_METRICS]
    groups = [(m,) for m in PAPER_METRICS] + triples + quadruples + [PAPER_METRICS]
    return [{m: Fraction(1, len(group)) for m in group} for group in groups]


def canonical_metric(name: str) -> str:
    return METRIC_ALIASES.get(name.lower(), name.lower())


@dataclass
class FrameRecord:
    """What the sweep needs of one frame; arrays are copies (the payloads are freed)."""

    run: str
    seq: int
    truth: np.ndarray | None = None  # (H, W) uint8 0/1/255
    target: np.ndarray | None = None  # (h, w, 3) uint8
    recon: np.ndarray | None = None  # (h, w, 3) uint8
    diffs: dict[str, np.ndarray] = field(default_factory=dict)  # canonical metric -> (h, w) float32
    masks: dict[str, np.ndarray] = field(default_factory=dict)  # segmenter op -> (K, h, w) bool
    mnad: np.ndarray | None = None  # (h', w') float32


@dataclass
class LogStats:
    messages: int = 0  # bus messages read from the log
    decoded: int = 0  # of those, decoded because the sweep needs their output
    bad: int = 0  # payloads that failed to decode (counted, skipped)
    duplicates: int = 0  # retransmissions of a (channel, run, seq) already read
    late: int = 0  # messages of a frame already evaluated
    truncated: str | None = None  # why reading stopped early, if it did
    frames: int = 0  # (run, seq) groups formed
    segmenters: dict[str, str] = field(default_factory=dict)  # segmenter op -> method


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def frames_from_log(path: str | Path, stats: LogStats, lag: int = 32) -> Iterator[FrameRecord]:
    """Stream the log's frames, each once, after `lag` newer frames of its run have appeared (or at the end).

    Counting frames, not seq numbers, keeps this right when a run's seqs are sparse (every k-th frame).

    A truncated or corrupt log ends the stream at the last readable message; `stats.truncated` says why.
    """
    buffer: dict[tuple[str, int], FrameRecord] = {}
    seqs_seen: dict[str, list[int]] = {}  # run -> every seq seen, sorted
    done: set[tuple[str, int]] = set()
    seen: set[tuple[str, str, int]] = set()

    def ready(run: str, upto: int) -> Iterator[FrameRecord]:
        for key in sorted(k for k in buffer if k[0] == run and k[1] <= upto):
            done.add(key)
            stats.frames += 1
            yield buffer.pop(key)

    messages = read_log(path)
    while True:
        try:
            entry = next(messages)
        except StopIteration:
            break
        except LogError as exc:
            stats.truncated = str(exc)
            break
        except Exception as exc:  # a decompressor's own error type on a cut chunk: same meaning
            stats.truncated = (
                f"{path}: log is truncated or corrupt after {stats.messages} messages ({type(exc).__name__}: {exc})"
            )
            break
        stats.messages += 1
        parts = entry.topic.split("/")
        if len(parts) != 4 or parts[0] != "umad" or parts[2].startswith("_") or parts[3] not in WANTED_OUTPUTS:
            continue
        op, output = parts[2], parts[3]
        try:
            msg = decode(entry.data)
        except MessageError:
            stats.bad += 1
            continue
        stats.decoded += 1
        key = (msg.run, msg.seq)
        if (entry.topic, *key) in seen:
            stats.duplicates += 1
            continue
        seen.add((entry.topic, *key))
        if key in done:
            stats.late += 1
            continue
        record = buffer.setdefault(key, FrameRecord(msg.run, msg.seq))
        _fill(record, op, output, msg, stats)
        run_seqs = seqs_seen.setdefault(msg.run, [])
        position = bisect.bisect_left(run_seqs, msg.seq)
        if position == len(run_seqs) or run_seqs[position] != msg.seq:
            run_seqs.insert(position, msg.seq)
            if len(run_seqs) > lag:
                yield from ready(msg.run, run_seqs[-lag - 1])
    for run in sorted({k[0] for k in buffer}):
        yield from ready(run, max(k[1] for k in buffer if k[0] == run))


def _fill(record: FrameRecord, op: str, output: str, msg, stats: LogStats) -> None:
    arrays, meta = msg.arrays, msg.meta
    if output == "truth" and "anomaly" in arrays:
        record.truth = np.array(arrays["anomaly"], dtype=np.uint8)
    elif output == "frame" and "target" in arrays and "recon" in arrays:
        record.target, record.recon = _to_uint8(arrays["target"]), _to_uint8(arrays["recon"])
    elif output == "masks" and "masks" in arrays:
        record.masks[op] = np.array(arrays["masks"], dtype=bool)
        stats.segmenters.setdefault(op, str(meta.get("method", op)))
    elif output == "map" and "map" in arrays:
        if "metric" in meta:
            record.diffs[canonical_metric(str(meta["metric"]))] = np.array(arrays["map"], dtype=np.float32)
        elif meta.get("model") == "mnad" or op == "mnad":
            record.mnad = np.array(arrays["map"], dtype=np.float32)


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


@dataclass
class SweepResult:
    rows: list[dict[str, Fraction]]
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

    def row_label(self, row: int) -> str:
        return weights_label(self.rows[row])

    def setting_labels(self) -> list[str]:
        """Every mask setting's label in table order: no mask, gt, unsupervised, SAM (mean, max, single)."""
        rank = {"gt": 0, "sam": 2}
        ops = sorted(self.segmenters, key=lambda op: (rank.get(self.segmenters[op], 1), op))
        return ["no mask", *(f"{self.segmenters[op]} {mode}" for op in ops for mode in REFINE_MODES)]

    def setting_label(self, config: Config) -> str:
        if config.segmenter is None:
            return "no mask"
        return f"{self.segmenters.get(config.segmenter, config.segmenter)} {config.mode}"


class Sweep:
    """Feed frames with `add`; every configuration's metrics stream as they come."""

    def __init__(self, rows: list[dict[str, Fraction]] | None = None, overlay_frames: int = 6, every: int = 1):
        self.rows = rows if rows is not None else paper_weight_rows()
        self.every = every
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

    def _count(self, config: Config, scores: np.ndarray, labels: np.ndarray) -> None:
        metrics = self.metrics.get(config)
        if metrics is None:
            metrics = self.metrics[config] = PixelMetrics()
        metrics.update(scores, labels)
        self.frames[config] = self.frames.get(config, 0) + 1

    def add(self, frame: FrameRecord, segmenters: dict[str, str]) -> None:
        if frame.truth is None or frame.seq % self.every:
            return
        if frame.mnad is not None:
            self.baseline = self.baseline or PixelMetrics()
            mnad_labels = resize_nearest(frame.truth, frame.mnad.shape)
            self.baseline.update(frame.mnad, mnad_labels)
            self.baseline_frames += 1
            self._scenario(frame.run, "MNAD").update(frame.mnad, mnad_labels)
        if not frame.diffs:
            return
        shape, labels, masks = model_size_inputs(frame)
        usable = [i for i, row in enumerate(self.rows) if set(row) <= set(frame.diffs)]
        if self.default_row is None and usable:
            self.default_row = max(usable, key=lambda i: (len(self.rows[i]), i))
        pictures: dict[str, np.ndarray] = {}
        for i in usable:
            self.rows_seen.add(i)
            weights = {m: float(w) for m, w in self.rows[i].items()}
            fused = fuse({m: frame.diffs[m] for m in weights}, weights, shape)
            self._count(Config(i, None, "none"), fused, labels)
            if i == self.default_row:
                self._scenario(frame.run, "no mask").update(fused, labels)
                pictures["fused"] = fused
            for op, op_masks in masks.items():
                for mode in REFINE_MODES:
                    refined = refine(fused, op_masks, mode=mode, uncovered="keep")
                    self._count(Config(i, op, mode), refined, labels)
                    if i == self.default_row:
                        self._scenario(frame.run, f"{segmenters.get(op, op)} {mode}").update(refined, labels)
                        if mode == "mean":
                            pictures[f"refined ({segmenters.get(op, op)} mean)"] = refined
        self._keep_overlay(frame, labels, pictures)

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
        )


def model_size_inputs(frame: FrameRecord) -> tuple[tuple[int, int], np.ndarray, dict[str, np.ndarray]]:
    """The difference maps' (h, w) (the largest, should they differ) with labels and masks resized to it."""
    shape = max((m.shape for m in frame.diffs.values()), key=lambda s: (s[0] * s[1], s))
    labels = resize_nearest(frame.truth, shape)
    masks = {op: resize_nearest(m, shape) for op, m in sorted(frame.masks.items())}
    return shape, labels, masks


def configuration_map(
    frame: FrameRecord,
    weights: dict[str, Fraction],
    config: Config,
    shape: tuple[int, int],
    masks: dict[str, np.ndarray],
) -> np.ndarray | None:
    """One configuration's score map of a frame, or None when the frame lacks a map or mask it needs."""
    if not set(weights) <= set(frame.diffs) or (config.segmenter is not None and config.segmenter not in masks):
        return None
    float_weights = {m: float(w) for m, w in weights.items()}
    fused = fuse({m: frame.diffs[m] for m in float_weights}, float_weights, shape)
    if config.segmenter is None:
        return fused
    return refine(fused, masks[config.segmenter], mode=config.mode, uncovered="keep")


def component_configs(result: SweepResult) -> dict[str, Config]:
    """Configurations worth component metrics: the best-AP one and the default row per mask setting."""
    chosen: dict[str, Config] = {}
    scored = [c for c, m in result.metrics.items() if m.n_anomaly and m.n_normal]
    if scored:
        best = max(scored, key=lambda c: (result.metrics[c].compute()["AP"], -c.row))
        chosen[f"best AP: {weights_label(result.rows[best.row])}, {result.setting_label(best)}"] = best
    for config in sorted(result.metrics, key=lambda c: (c.segmenter or "", c.mode)):
        if config.row == result.default_row and config.mode in ("none", "mean") and config not in chosen.values():
            chosen[f"{weights_label(result.rows[config.row])}, {result.setting_label(config)}"] = config
    return chosen


def weights_label(weights: dict[str, Fraction]) -> str:
    """Short name of a weight row: `ssim`, `abs+ssim+perceptual (1/3)`, `all - temporal (1/4)`, `all (1/5)`."""
    names = list(weights)
    if len(names) == 1:
        return names[0]
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


def component_pass(
    path: str | Path, result: SweepResult, lag: int = 32, every: int = 1, progress: bool = True
) -> dict[str, dict]:
    """SegmentMeIfYouCan component metrics (a second read of the log) for `component_configs` and
    MNAD, each at its best pixel-F1 threshold from the first pass."""
    configs = component_configs(result)
    metrics = {name: ComponentMetrics(result.metrics[c].best_f1_threshold()) for name, c in configs.items()}
    if result.baseline is not None and result.baseline.n_anomaly:
        metrics["MNAD"] = ComponentMetrics(result.baseline.best_f1_threshold())
    for frame in tqdm(frames_from_log(path, LogStats(), lag), desc="components", unit="frame", disable=not progress):
        if frame.truth is None or frame.seq % every:
            continue
        if frame.mnad is not None and "MNAD" in metrics:
            metrics["MNAD"].update(frame.mnad, resize_nearest(frame.truth, frame.mnad.shape))
        if not frame.diffs:
            continue
        shape, labels, masks = model_size_inputs(frame)
        for name, config in configs.items():
            score_map = configuration_map(frame, result.rows[config.row], config, shape, masks)
            if score_map is not None:
                metrics[name].update(score_map, labels)
    return {name: m.compute() for name, m in metrics.items()}


def sweep_log(
    path: str | Path,
    lag: int = 32,
    every: int = 1,
    overlay_frames: int = 6,
    components: bool = True,
    progress: bool = True,
) -> SweepResult:
    """Compute every configuration's AP/FPR95/AUROC from one log (see the module docstring); with
    `components`, a second read adds component metrics for the headline configurations."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: log file not found; expected an MCAP file written by the recorder")
    if lag < 0 or every < 1:
        raise ValueError(f"sweep: lag must be >= 0 and every >= 1, got lag={lag}, every={every}")
    start = time.perf_counter()
    stats = LogStats()
    sweep = Sweep(overlay_frames=overlay_frames, every=every)
    for frame in tqdm(frames_from_log(path, stats, lag), desc="sweep", unit="frame", disable=not progress):
        sweep.add(frame, stats.segmenters)
    result = sweep.result(stats)
    if components:
        result.components = component_pass(path, result, lag, every, progress)
    result.seconds = time.perf_counter() - start
    return result
