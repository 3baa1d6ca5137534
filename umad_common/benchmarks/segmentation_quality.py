"""How well a segmenter isolates anomalies, measured on labelled drives (docs/design.md: the
distance between unsupervised and ground-truth masks is where most of the AP is).

Per method, over every frame of the given drives, at the world model's size:

- `coverage`: the fraction of anomaly pixels covered by a mask that is at least half anomaly
  (ignore-labelled pixels excluded from a mask's area). A mean-refined mask that is mostly anomaly
  carries the anomaly's score; pixels of a mask that is mostly road are averaged away.
- `best_iou`: the mean over anomaly objects (the anomaly pixels of one instance id, or 4-connected
  anomaly regions without instance labels) of the best IoU any single mask reaches with the object.
- `normal_segment_px`: the area of the mask a normal pixel lies in, averaged over normal pixels
  (masks weighted by their normal pixels): how much averaging mean refinement gives the speckle of
  normal structure. Finer masks raise `coverage` trivially (one-pixel masks reach 100 %) but leave
  the speckle as it was; a good segmenter has both figures high.
- `masks_per_frame`, `ms_per_frame` (wall time of the segmenter operator's `process`, one thread)
  and `cpu_ms_per_frame` (its process CPU time: steadier than wall time on a shared machine).
- `refined_ap` / `pixel_ap`, when the frames carry a fused difference map (`fused_maps_along`
  runs a world model over the drives): pooled pixel AP after `mean` refinement with the masks
  (uncovered pixels keep their score), and of the fused map itself. This is what the masks are for.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from umad_common.dataflow import Frame, Output
from umad_common.dataflow.api.operator import frame_of
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import fuse, refine, resize_nearest
from umad_common.segmentation import connected_regions

IGNORE = 255
WORLD_MODEL_SIZE = (128, 192)  # (h, w)


@dataclass
class LabelledFrame:
    """One frame for the measurement: the world model's target plus full-size labels."""

    run: str
    seq: int
    target: np.ndarray  # (h, w, 3) float32 in [0, 1]
    anomaly: np.ndarray  # (H, W) uint8: 0 normal, 1 anomaly, 255 ignore
    instance: np.ndarray | None  # (H, W) int32, 0 = none
    semantic: np.ndarray | None  # (H, W) uint8
    fused: np.ndarray | None = None  # (h, w) float32 fused difference map, when measuring AP
    lidar: np.ndarray | None = None  # (N, 4) float32 (x, -y, z, intensity)
    sensors: dict | None = None  # the scenario's sensor setup (`read_sensor_setup`), the lidar's meta


@dataclass
class SegmenterQuality:
    """Figures of one segmenter configuration over a set of frames."""

    params: dict
    frames: int
    anomaly_pixels: int
    coverage: float
    best_iou: float
    normal_segment_px: float
    masks_per_frame: float
    ms_per_frame: float
    cpu_ms_per_frame: float
    refined_ap: float | None = None
    pixel_ap: float | None = None
    refined_fpr95: float | None = None  # false-positive rate at 95 % of the anomaly pixels found: a mask
    #   setting that lifts whole large segments can raise the AP and still flag much of the road
    pixel_fpr95: float | None = None

    def row(self) -> str:
        ap = (
            ""
            if self.refined_ap is None
            else f"AP {self.refined_ap:6.1%} (pixel {self.pixel_ap:5.1%})  "
            f"FPR95 {self.refined_fpr95:6.1%} (pixel {self.pixel_fpr95:5.1%})  "
        )
        return ap + (
            f"coverage {self.coverage:6.1%}  best IoU {self.best_iou:5.3f}  normal seg px {self.normal_segment_px:7.0f}  "
            f"masks/frame {self.masks_per_frame:6.1f}  "
            f"{self.ms_per_frame:6.1f} ms/frame ({self.cpu_ms_per_frame:5.1f} CPU)  {self.params}"
        )


def anovox_frames(
    root: Path, size: tuple[int, int] = WORLD_MODEL_SIZE, every: int = 1, world_model: Path | None = None
) -> Iterator[LabelledFrame]:
    """Frames of every scenario under `root` with at least one anomaly pixel; the camera resized
    (no crop, area interpolation) to `size` (h, w) like the world model's target. With a
    `world_model`, every frame of a drive goes through it in order and each yielded frame carries
    its fused difference map (see `fused_maps_along`)."""
    from umad_common.datasets.anovox import AnoVoxScenario, find_scenarios

    def drive(path: Path, step: int) -> Iterator[tuple[LabelledFrame, object]]:
        scenario = AnoVoxScenario(path)
        for seq in range(0, len(scenario), step):
            frame = scenario[seq]
            target = cv2.resize(frame.rgb, (size[1], size[0]), interpolation=cv2.INTER_AREA)
            sample = LabelledFrame(
                scenario.name,
                seq,
                target.astype(np.float32) / 255.0,
                frame.anomaly,
                frame.instance,
                frame.semantic,
                lidar=frame.lidar,
                sensors=scenario.sensors,
            )
            yield sample, frame

    def wanted(sample: LabelledFrame) -> bool:
        return sample.seq % every == 0 and bool((sample.anomaly == 1).any())

    for path in find_scenarios(root):
        if world_model is None:
            yield from (sample for sample, _ in drive(path, every) if wanted(sample))
        else:
            yield from (sample for sample in fused_maps_along(drive(path, 1), world_model) if wanted(sample))


def fused_maps_along(
    frames: Iterable[tuple[LabelledFrame, object]],
    world_model: Path,
    metrics: tuple[str, ...] = ("abs", "ssim"),
) -> Iterator[LabelledFrame]:
    """Attach to each labelled frame the fused map of a real world model's difference maps.

    `frames` holds (labelled frame, AnoVoxFrame) pairs of every frame of each drive in order (the
    world model is stateful); each map is min-max normalised per frame and fused with equal weights,
    the paper's plain setting.
    """
    from umad_common.differences import build_metric, minmax
    from umad_operators.replayer import frame_outputs
    from umad_operators.world_model import WorldModelPredictor

    predictor = WorldModelPredictor({"model": str(world_model), "threads": 1})
    ports = [port.name for port in WorldModelPredictor.inputs]
    difference = {name: build_metric(name) for name in metrics}
    weights = dict.fromkeys(metrics, 1.0)
    for sample, raw in frames:
        inputs = frame_of(frame_outputs(raw, sample.run), ports, sample.run, sample.seq)
        out = predictor.process(inputs)["frame"].arrays
        arrays = (out["target"], out["recon"], out["preds"], out["pred_valid"])
        maps = {name: minmax(metric(*arrays)) for name, metric in difference.items()}
        sample.fused = fuse(maps, weights)
        yield sample


def operator_frame(sample: LabelledFrame) -> Frame:
    """The segmenter operator's joined inputs for one labelled frame (lidar when the drive has it)."""
    truth = {"anomaly": sample.anomaly}
    if sample.instance is not None:
        truth["instance"] = sample.instance
    if sample.semantic is not None:
        truth["semantic"] = sample.semantic
    outputs = {"frame": Output({"target": sample.target}), "truth": Output(truth)}
    if sample.lidar is not None:
        outputs["lidar"] = Output({"points": sample.lidar}, {"sensors": sample.sensors} if sample.sensors else {})
    return frame_of(outputs, outputs, sample.run, sample.seq)


def frame_quality(
    masks: np.ndarray, anomaly: np.ndarray, instance: np.ndarray | None = None
) -> tuple[int, int, list[float], float, float]:
    """One frame's raw counts: (anomaly pixels, those covered by a >= 50 % anomaly mask, best IoU per
    anomaly object, sum over masks of normal pixels x mask area, sum over masks of normal pixels).

    Arrays are already at the masks' size. An object is the anomaly pixels of one instance id when
    `instance` is given (a thin-legged animal stays one object), else a 4-connected anomaly region.
    """
    is_anomaly = anomaly == 1
    valid = (anomaly != IGNORE).reshape(-1)
    total = int(is_anomaly.sum())
    if instance is not None:
        objects = np.unique(instance[is_anomaly], return_inverse=True)[1]
        object_ids = np.full(anomaly.shape, -1, dtype=np.int64)
        object_ids[is_anomaly] = objects.reshape(-1)
    else:
        object_ids = connected_regions(np.where(is_anomaly, 1, -1))
    object_count = int(object_ids.max()) + 1
    if masks.shape[0] == 0:
        return total, 0, [0.0] * object_count, 0.0, 0.0
    flat = masks.reshape(masks.shape[0], -1)
    inside = (flat & is_anomaly.reshape(-1)).sum(axis=1)
    area = (flat & valid).sum(axis=1)
    normal = area - inside
    pure = (inside > 0) & (inside * 2 >= area)
    covered = int((masks[pure].any(axis=0) & is_anomaly).sum())
    best = []
    for k in range(object_count):
        obj = (object_ids == k).reshape(-1)
        intersection = (flat & obj).sum(axis=1)
        union = area + obj.sum() - intersection
        best.append(float((intersection / np.maximum(union, 1)).max()))
    return total, covered, best, float((normal * area).sum()), float(normal.sum())


def measure_segmenter(params: dict, frames: Iterable[LabelledFrame]) -> SegmenterQuality:
    """Run the segmenter operator with `params` on every frame and score its masks."""
    from umad_operators.segmenter import Segmenter

    segmenter = Segmenter(params)
    count = total = covered = masks_total = 0
    seconds = cpu_seconds = normal_area = normal_pixels = 0.0
    refined_metrics, pixel_metrics = PixelMetrics(), PixelMetrics()
    best_ious: list[float] = []
    for sample in frames:
        frame = operator_frame(sample)
        start, cpu_start = time.perf_counter(), time.process_time()
        masks = segmenter.process(frame)["masks"].arrays["masks"]
        seconds += time.perf_counter() - start
        cpu_seconds += time.process_time() - cpu_start
        anomaly = resize_nearest(sample.anomaly, masks.shape[1:])
        instance = None if sample.instance is None else resize_nearest(sample.instance, masks.shape[1:])
        frame_total, frame_covered, frame_best, frame_normal_area, frame_normal = frame_quality(
            masks, anomaly, instance
        )
        normal_area += frame_normal_area
        normal_pixels += frame_normal
        if sample.fused is not None:
            labels = resize_nearest(sample.anomaly, sample.fused.shape)
            refined = refine(sample.fused, resize_nearest(masks, sample.fused.shape), mode="mean", uncovered="keep")
            refined_metrics.update(refined, labels)
            pixel_metrics.update(sample.fused, labels)
        count += 1
        total += frame_total
        covered += frame_covered
        masks_total += masks.shape[0]
        best_ious.extend(frame_best)
    if count == 0:
        raise ValueError("measure_segmenter: no frames with anomaly pixels; expected anomalous drives")
    return SegmenterQuality(
        params=dict(params),
        frames=count,
        anomaly_pixels=total,
        coverage=covered / max(total, 1),
        best_iou=float(np.mean(best_ious)) if best_ious else 0.0,
        normal_segment_px=normal_area / max(normal_pixels, 1.0),
        masks_per_frame=masks_total / count,
        ms_per_frame=1000.0 * seconds / count,
        cpu_ms_per_frame=1000.0 * cpu_seconds / count,
        **figures(refined_metrics, "refined"),
        **figures(pixel_metrics, "pixel"),
    )


def figures(metrics: PixelMetrics, prefix: str) -> dict[str, float]:
    """{prefix_ap, prefix_fpr95} of accumulated metrics; none without anomaly pixels."""
    if not metrics.n_anomaly:
        return {}
    result = metrics.compute()
    return {f"{prefix}_ap": float(result["AP"]), f"{prefix}_fpr95": float(result["FPR95"])}
