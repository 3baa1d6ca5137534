"""Fusion of difference maps and mask-level refinement: the arithmetic shared by the live operators
(`operators/fusion.py`, `operators/mask_refiner.py`) and the offline sweep over a recorded log.

Pure numpy, no state: the same inputs give bit-identical outputs wherever they run.

Rules (docs/design.md, "Fusion" and "Mask-level refinement"):

- `fuse` is the weighted sum of the maps present, divided by the sum of their weights (a weighted
  mean). With a fixed set of metrics that division is one constant for every frame, so every
  ranking metric (AP, FPR95, AUROC) equals the paper's plain weighted sum; when a metric is absent
  from a frame (a difference operator joining late, leaving, or missing the live deadline) its
  weight simply drops out and the frame stays on the same [0, 1] scale instead of being deflated.
  A weight whose metric is absent is ignored; a map whose metric has no weight, or weight 0, does
  not contribute. If no present metric has a positive weight the fused map is all zeros.
- `weigh_down_above_lidar` (ours, before `fuse`): every map but the one that marks them is multiplied
  by `weight` at the pixels the lidar difference marks `above_returns` (above every lidar return
  near their column: the sky, and what the beams do not reach), where a camera map's disagreement
  is the light's and no object on the road stands.
- `scale_by_camera_agreement` (ours, after the weighing): the lidar map (the one that marks them) is
  multiplied by the other maps' weighted mean, divided by that mean's frame maximum, to the power
  `exponent`, then min-max rescaled over the frame. The lidar map's evidence counts where the camera
  maps disagree too: a car the lidar head does not draw but the camera model does loses it, an
  object neither model draws keeps it.
- `refine` scores each mask by the `mean` (paper default) or `max` of the fused map over its pixels
  and writes that score to every pixel of the mask. Where masks overlap, the highest score wins.
  `single` (the paper's single mask) keeps only the mask with the highest mean score and gives
  every other pixel the frame's lowest fused score; `single_keep_raw` keeps that mask too but
  leaves the other pixels to the uncovered rule. `none` returns the fused map unchanged.
  `mean_pixel` (ours) gives each covered pixel (1 - s) x its mask's mean + s x its own fused score,
  s = `pixel_share`: a small object inside a large segment keeps part of its own evidence, and
  within a mask the pixels keep their order.
  Pixels no (surviving) mask covers are `keep` (their fused score) or `zero`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

import cv2
import numpy as np

from umad_common.differences.normalization import minmax

RefineMode = Literal["mean", "mean_pixel", "max", "single", "single_keep_raw", "none"]
UncoveredRule = Literal["keep", "zero"]
REFINE_MODES: tuple[str, ...] = ("mean", "mean_pixel", "max", "single", "single_keep_raw", "none")
# mean_pixel's share of a pixel's own fused score: chosen on validation seeds 2 and 31 of the
# built-in world, never on an evaluated set (docs/experiments.md, "Scores across frames and regions")
PIXEL_SHARE = 0.2
UNCOVERED_RULES: tuple[str, ...] = ("keep", "zero")
MAX_CHUNK_ELEMENTS = 1 << 22  # bounds the (masks x pixels) float temporaries of the `max` mode


def resize_nearest(array: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of the last two axes to `shape` (h, w), any dtype.

    Each output pixel takes the input pixel under its centre (OpenCV's INTER_NEAREST_EXACT rule),
    so labels, instance ids and masks stay exact values and align with a plain image resize.
    """
    in_h, in_w = array.shape[-2:]
    out_h, out_w = shape
    if (in_h, in_w) == (out_h, out_w):
        return array
    rows = np.minimum(((np.arange(out_h) + 0.5) * in_h / out_h).astype(np.int64), in_h - 1)
    cols = np.minimum(((np.arange(out_w) + 0.5) * in_w / out_w).astype(np.int64), in_w - 1)
    return array[..., rows[:, None], cols[None, :]]


def resize_bilinear(score_map: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of a (h, w) score map to `shape` (h, w), float32."""
    score_map = np.asarray(score_map, dtype=np.float32)
    if score_map.shape == tuple(shape):
        return score_map
    return cv2.resize(score_map, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def fuse(
    maps: Mapping[str, np.ndarray],
    weights: Mapping[str, float],
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Weighted mean of the difference maps present (see the module docstring for the rule).

    Args:
        maps: metric name -> (h, w) score map, normalised to [0, 1].
        weights: metric name -> weight in [0, 1].
        shape: output (h, w); maps of another size are resized bilinearly. Default: the largest
            map's shape (every map when they agree).

    Returns:
        (h, w) float32 fused map.

    Raises:
        ValueError: no maps, a map that is not 2-D, or a negative weight.
    """
    if not maps:
        raise ValueError("fuse: no difference maps given; expected at least one (h, w) map")
    for metric, score_map in maps.items():
        if np.ndim(score_map) != 2:
            raise ValueError(f"fuse: map {metric!r} has shape {np.shape(score_map)}; expected (h, w)")
    for metric, weight in weights.items():
        if weight < 0:
            raise ValueError(f"fuse: weight of {metric!r} is {weight}; expected a value in [0, 1]")
    if shape is None:
        shape = max((np.shape(m) for m in maps.values()), key=lambda s: (s[0] * s[1], s))
    fused = np.zeros(shape, dtype=np.float64)
    total_weight = 0.0
    for metric in sorted(maps):  # fixed order: the result does not depend on arrival order
        weight = float(weights.get(metric, 0.0))
        if weight > 0:
            fused += weight * resize_bilinear(maps[metric], shape)
            total_weight += weight
    if total_weight > 0:
        fused /= total_weight
    return fused.astype(np.float32)


def weigh_down_above_lidar(
    maps: Mapping[str, np.ndarray], above: np.ndarray | None, marked_by: str, weight: float
) -> dict[str, np.ndarray]:
    """`maps` with every map but `marked_by`'s multiplied by `weight` where `above` (an (h, w) mask,
    resized nearest to each map) is set; unchanged where `above` is None or `weight` is 1."""
    if above is None or weight >= 1.0:
        return dict(maps)
    if np.ndim(above) != 2:
        raise ValueError(f"weigh_down_above_lidar: the mask has shape {np.shape(above)}; expected (h, w)")
    above = np.asarray(above, dtype=bool)
    out = {}
    for metric, score_map in maps.items():
        if metric == marked_by:
            out[metric] = score_map
            continue
        mask = resize_nearest(above, np.shape(score_map))
        out[metric] = np.where(mask, np.float32(weight) * score_map, score_map).astype(np.float32)
    return out


def scale_by_camera_agreement(
    maps: Mapping[str, np.ndarray], lidar: str, weights: Mapping[str, float], exponent: float
) -> dict[str, np.ndarray]:
    """`maps` with the `lidar` map times (m / max m) ** `exponent`, m the weighted mean (`fuse`, at the
    lidar map's size) of the other maps with a positive weight, then min-max rescaled over the frame;
    unchanged where `exponent` is 0, `lidar` is absent, no other map has weight or m is 0 everywhere."""
    others = {m: a for m, a in maps.items() if m != lidar and float(weights.get(m, 0.0)) > 0}
    if exponent == 0 or lidar not in maps or not others:
        return dict(maps)
    if exponent < 0:
        raise ValueError(f"scale_by_camera_agreement: the exponent is {exponent}; expected 0 or more")
    lidar_map = np.asarray(maps[lidar], dtype=np.float32)
    agreement = fuse(others, weights, lidar_map.shape)
    peak = float(agreement.max())
    if not peak > 0:
        return dict(maps)
    scaled = lidar_map * (agreement / np.float32(peak)) ** np.float32(exponent)
    return {**maps, lidar: minmax(scaled)}


def fusion_note(above_lidar_weight: float = 1.0, lidar_camera_exponent: float = 0.0) -> str:
    """How a fusion departs from the paper's weighted mean, for a row's name: `, camera ×0.25 above
    the lidar, lidar × camera^0.5`; empty for the paper's fusion."""
    above = "" if above_lidar_weight == 1.0 else f", camera ×{above_lidar_weight:g} above the lidar"
    agreement = "" if lidar_camera_exponent == 0.0 else f", lidar × camera^{lidar_camera_exponent:g}"
    return above + agreement


def used_weights(metrics: list[str] | set[str], weights: Mapping[str, float]) -> dict[str, float]:
    """The metrics of `metrics` that `fuse` actually uses, with their weights (sorted by name)."""
    return {m: float(weights[m]) for m in sorted(metrics) if float(weights.get(m, 0.0)) > 0}


def mask_scores(fused: np.ndarray, masks: np.ndarray, how: Literal["mean", "max"]) -> np.ndarray:
    """Per-mask score of the fused map: (K,) float64; empty masks score -inf (they paint nothing).

    `mean` is a (K x N) @ (N,) product; both modes work through chunks of masks so the float
    temporaries stay under MAX_CHUNK_ELEMENTS elements at any frame size.
    """
    flat_masks = masks.reshape(masks.shape[0], -1)
    flat_scores = np.asarray(fused, dtype=np.float64).reshape(-1)
    areas = flat_masks.sum(axis=1)
    scores = np.full(masks.shape[0], -np.inf)
    chunk = max(1, MAX_CHUNK_ELEMENTS // max(1, flat_scores.size))
    for start in range(0, masks.shape[0], chunk):
        block = flat_masks[start : start + chunk]
        if how == "mean":
            block_areas = areas[start : start + chunk]
            sums = block.astype(np.float64) @ flat_scores
            scores[start : start + chunk] = np.where(block_areas > 0, sums / np.maximum(block_areas, 1), -np.inf)
        else:
            scores[start : start + chunk] = np.where(block, flat_scores[None, :], -np.inf).max(axis=1)
    return scores


def paint_masks(scores: np.ndarray, masks: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Write each mask's score to its pixels, the highest score winning where masks overlap;
    pixels no mask covers (or only empty-scored masks) take `background`."""
    out = np.array(background, dtype=np.float32, copy=True)
    for k in np.argsort(scores, kind="stable"):  # ascending: a higher score is painted later, on top
        if np.isfinite(scores[k]):
            out[masks[k]] = scores[k]
    return out


def refine(
    fused: np.ndarray,
    masks: np.ndarray,
    mode: RefineMode = "mean",
    uncovered: UncoveredRule = "keep",
    pixel_share: float = PIXEL_SHARE,
) -> np.ndarray:
    """Mask-level refinement of a fused anomaly map.

    Args:
        fused: (h, w) fused score map.
        masks: (K, h, w) bool segment masks; K may be 0; masks may overlap.
        mode: `mean` | `max`: each mask's mean | max fused score written to its pixels, the highest
            score winning on overlaps; `single`: only the mask with the highest mean keeps its score
            (ties: the lowest index), every other pixel gets the frame's lowest fused score (the
            paper's single mask); `single_keep_raw`: the same survivor, the other pixels follow
            `uncovered`; `mean_pixel`: `mean`, then each covered pixel keeps `pixel_share` of its
            own fused score (ours); `none`: the fused map unchanged.
        uncovered: pixels no surviving mask covers: `keep` their fused score (a missed object still
            shows its raw evidence) or `zero`. Not used by `single`.
        pixel_share: in [0, 1], used by `mean_pixel` only.

    Returns:
        (h, w) float32 refined map.

    Raises:
        ValueError: unknown mode or rule, or masks whose shape does not match the map.
    """
    if mode not in REFINE_MODES:
        raise ValueError(f"refine: unknown mode {mode!r}; expected one of {REFINE_MODES}")
    if uncovered not in UNCOVERED_RULES:
        raise ValueError(f"refine: unknown uncovered rule {uncovered!r}; expected one of {UNCOVERED_RULES}")
    if not 0.0 <= pixel_share <= 1.0:
        raise ValueError(f"refine: pixel_share {pixel_share!r}; expected a share in [0, 1]")
    fused = np.asarray(fused, dtype=np.float32)
    if fused.ndim != 2:
        raise ValueError(f"refine: fused map has shape {fused.shape}; expected (h, w)")
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3 or masks.shape[1:] != fused.shape:
        raise ValueError(f"refine: masks have shape {masks.shape}; expected (K, {fused.shape[0]}, {fused.shape[1]})")
    if mode == "none":
        return fused.copy()
    if mode == "single":
        background = np.full_like(fused, fused.min() if fused.size else 0.0)
    else:
        background = fused if uncovered == "keep" else np.zeros_like(fused)
    if masks.shape[0] == 0:
        return np.array(background, dtype=np.float32, copy=True)
    scores = mask_scores(fused, masks, "max" if mode == "max" else "mean")
    if mode in ("single", "single_keep_raw"):
        scores = only_the_best(scores)
    painted = paint_masks(scores, masks, background)
    if mode == "mean_pixel":
        return with_pixel_share(painted, fused, masks.any(axis=0), pixel_share)
    return painted


def with_pixel_share(painted: np.ndarray, fused: np.ndarray, covered: np.ndarray, share: float) -> np.ndarray:
    """`painted` with each covered pixel's score (1 - share) x itself + share x the pixel's fused
    score (float32, the same operations wherever it runs)."""
    out = np.array(painted, dtype=np.float32, copy=True)
    out[covered] = np.float32(1.0 - share) * out[covered] + np.float32(share) * fused[covered]
    return out


def only_the_best(scores: np.ndarray) -> np.ndarray:
    """Mask scores with every mask but the highest-scoring one (ties: the lowest index) set to -inf."""
    best = int(np.argmax(scores))
    kept = np.full_like(scores, -np.inf)
    kept[best] = scores[best]
    return kept
