"""The component pass: a second read of the log, once the first pass has ranked every configuration.

It scores SegmentMeIfYouCan component metrics (`umad_common.metrics.components`) of chosen
configurations at fixed thresholds, and per scenario the pixel metrics of other chosen
configurations; which, and at what thresholds, the caller decides from the first pass's table
(`umad_replay.sweep.second_pass`). Each configuration's map is drawn in full here
(`umad_replay.row_scoring.configuration_map`): components need the pixels, not counts per mask.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from umad_common.metrics.components import ComponentMetrics, frame_components
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import resize_nearest
from umad_replay.configurations import Config, WeightRow
from umad_replay.frames import LogStats, frames_from_log
from umad_replay.row_scoring import MaskSet, configuration_map, model_size_inputs
from umad_replay.shares import dealt, share_pool


def component_pass(
    path: Path,
    rows: list[WeightRow],
    configs: dict[str, Config],
    best: dict[str, Config],
    thresholds: dict[str, float],
    per_scenario: dict[str, dict[str, PixelMetrics]],
    lag: int,
    every: int,
    progress: bool,
    workers: int,
) -> dict[str, dict]:
    """Component metrics of `configs` (name -> configuration) and of MNAD, each at its threshold in
    `thresholds` (returned: name -> `ComponentMetrics.compute()`), and per scenario the pixel metrics
    of `best` (name -> configuration), pooled into `per_scenario` (run -> name -> metrics).

    With `workers` > 1 the scored frames are dealt out in turn among that many processes, each
    reading the whole log; their components are put back in the order of one read, so the figures
    are one process's."""
    task = partial(_component_pass_share, Path(path), rows, configs, best, thresholds, lag, every)
    with ExitStack() as stack:
        others = []
        if workers > 1:
            pool = share_pool(stack, workers)
            others = [pool.submit(task, (index, workers), False) for index in range(1, workers)]
        shares = [task((0, workers), progress), *(other.result() for other in others)]
    for share in shares:
        for run, per_run in share.per_scenario.items():
            merged = per_scenario.setdefault(run, {})
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
class ComponentPassShare:
    """What one share of the component pass found, for `component_pass` to put together."""

    components: dict[str, list[FrameComponents]]  # name -> its frames of this share
    per_scenario: dict[str, dict[str, PixelMetrics]]  # run -> best configuration's name -> metrics


def _component_pass_share(
    path: Path,
    rows: list[WeightRow],
    configs: dict[str, Config],
    best: dict[str, Config],
    thresholds: dict[str, float],
    lag: int,
    every: int,
    share: tuple[int, int],
    progress: bool,
) -> ComponentPassShare:
    """The component pass over the scored frames k, k + n, ... of one read (`share` = (k, n))."""
    out = ComponentPassShare({name: [] for name in thresholds}, {})
    position = -1
    frames = tqdm(frames_from_log(path, LogStats(), lag), desc="second pass", unit="frame", disable=not progress)
    for frame in frames:
        if frame.truth is None or frame.seq % every:
            continue
        position += 1
        if not dealt(position, share):
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
