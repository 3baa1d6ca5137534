"""The paper's ablation from one recorded log: every fusion weight row x every mask setting, no model run.

Frames come from the log through `umad_replay.frames.frames_from_log` (truth, difference maps, masks
per segmenter, the MNAD map, regrouped by `(run, seq)`). Each configuration fuses and refines
exactly as the live operators do (`umad_common.refine.fuse` and `refine`, so a sweep row equals the
live pipeline's numbers) and streams its pixels into its own `PixelMetrics`: memory is one 1 MiB
histogram per configuration plus a few frames in flight. With `components`, a second read of the
log adds SegmentMeIfYouCan component metrics for the headline configurations at their best pixel-F1
thresholds, and per scenario the figures of the best row under each headline mask setting and of
the shipped configuration (the first pass follows only the default row per scenario). The first
pass also feeds the report's diagnosis (`umad_common.metrics.diagnosis`): where each map's top 1 %
of pixels lies by semantic class, and the anomaly's frame-relative score against frames since it
first became visible.

Rows and settings (`umad_replay.configurations`): the paper's 15 weight rows in its order, then ours
(`WeightRow.extra`): two more groups; every group with SSIM again with the shift-tolerant SSIM
(`ssim_shift`) in its place; then every group again on `robust`-normalised maps
(`umad_common.differences.robust` of the logged min-max maps, equal to robust normalisation of the
raw maps); then the lidar difference alone and every min-max group with it added at `LIDAR_SHARE`;
last, the shipped configuration's weights (`umad_replay.protocol.shipped_configuration`: what the
graph as run fused), where no row above has them with its refinement. Rows of the paper's maps at
min-max are scored per segmenter with the refinements mean, max, single (the paper's),
single_keep_raw and mean_pixel (ours), plus no mask; the others with `mean` and `mean_pixel`
refinement and no mask only. A row whose map the log lacks (a graph without `diff_ssim_shift`) is
skipped. The log's metadata gives the protocol (`umad_replay.protocol`): data, models, the PD network.

With `workers` > 1 the first pass runs in that many processes, each reading the whole log and
scoring its share of the weight rows (`umad_replay.first_pass.Sweep.owns`); the first also follows
the frames (the default row, MNAD, per scenario, diagnosis, overlays). Each configuration sees the
same frames in the same order with the same arithmetic, so the result is the one process's, bit for
bit. The second pass deals the scored frames out among as many processes and puts their components
back in the order of one read (`second_pass`).

This module holds the entry point (`sweep_log`), the table it returns (`SweepResult`) and the choice
of what the second pass scores; the jobs live beside it: `configurations` (the rows, cells and their
names), `row_scoring` (one frame's fused and refined maps), `first_pass`, `component_pass` and
`shares` (the processes and what each scores). They never import this module.
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from umad_common.dataflow.process.replica import one_blas_thread
from umad_common.dataflow.record.mcap_log import LogError, describe_loss, read_metadata, recording_outcome
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import fusion_note
from umad_replay.component_pass import component_pass
from umad_replay.configurations import REFINE_MODES, Config, WeightRow, masks_name, weights_label
from umad_replay.first_pass import OverlayFrame, Sweep, first_pass_share
from umad_replay.frames import LogStats, frames_from_log
from umad_replay.protocol import run_protocol, shipped_configuration
from umad_replay.shares import share_pool


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
        label = label if normalization == "minmax" else f"{label}, {normalization}"
        return label + fusion_note(self.rows[row].above_lidar_weight, self.rows[row].lidar_camera_exponent)

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


def first_pass_result(sweep: Sweep, stats: LogStats) -> SweepResult:
    """The table of a first pass (`sweep`, share 0 with the other shares merged) over a log read with `stats`."""
    overlays = sweep.overlays()
    return SweepResult(
        rows=sweep.rows,
        metrics=sweep.metrics,
        frames=sweep.frames,
        baseline=sweep.baseline,
        baseline_frames=sweep.baseline_frames,
        default_row=sweep.default_row,
        per_scenario=sweep.per_scenario,
        overlays=overlays,
        stats=stats,
        segmenters=dict(stats.segmenters),
        skipped_rows=[i for i in range(len(sweep.rows)) if i not in sweep.rows_seen],
        scenario_tags=sweep.scenario_tags,
        frames_evaluated={run: sorted(seqs) for run, seqs in sweep.frames_evaluated.items()},
        score_shapes=sweep.score_shapes,
        truth_shapes=sweep.truth_shapes,
        every=sweep.every,
        diagnosis=sweep.diagnosis.compute(),
        shipped=sweep.shipped_config(),
    )


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
    are one process's (`umad_replay.component_pass`)."""
    configs, best = component_configs(result), scenario_configs(result)
    thresholds = {name: result.metrics[c].best_f1_threshold() for name, c in configs.items()}
    if result.baseline is not None and result.baseline.n_anomaly:
        thresholds["MNAD"] = result.baseline.best_f1_threshold()
    return component_pass(
        Path(path), result.rows, configs, best, thresholds, result.per_scenario, lag, every, progress, workers
    )


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
                pool.submit(first_pass_share, path, lag, every, shipped, (index, workers))
                for index in range(1, workers)
            ]
        for frame in tqdm(frames_from_log(path, stats, lag), desc="sweep", unit="frame", disable=not progress):
            sweep.add(frame, stats.segmenters)
        for other in others:
            sweep.merge_rows(*other.result())
        result = first_pass_result(sweep, stats)
        result.protocol = run_protocol(metadata, stats.map_notes)
        if incomplete:
            result.protocol["incomplete"] = incomplete
        if components:
            result.components = second_pass(path, result, lag, every, progress, workers)
    result.seconds = time.perf_counter() - start
    return result
