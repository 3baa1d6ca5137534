"""`umad calibrate DATA --world-model MODEL --out FILE.json`: fit the `calibrated` normalisation.

Runs the world model operator over held-out NORMAL drives (those its JSON lists as
`heldout_drives`; every normal drive, with a warning, when it lists none), computes every metric's
raw map per frame and stores q = the 99.9th percentile of each metric's raw values (rule:
umad_common.differences.normalization). Only the camera, lidar, ego and route of a frame are read:
labels are never opened, so a benchmark without label files calibrates the same.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
from collections.abc import Iterator
from pathlib import Path

from umad_common import ASSETS, recorded_path
from umad_common.commands.checks import model_file, normal_drives, writable_output
from umad_common.commands.common import (
    add_data_argument,
    add_frames_argument,
    add_out_argument,
    add_topics_argument,
)

log = logging.getLogger("umad.calibrate")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_data_argument(parser)
    add_topics_argument(parser)
    parser.add_argument(
        "--world-model", type=Path, required=True, help="world model weights (MODEL.safetensors + MODEL.json)"
    )
    parser.add_argument(
        "--features",
        type=Path,
        default=None,
        help=f"label-free feature net for the perceptual metric (default {ASSETS / 'feature_net.safetensors'} when present)",
    )
    parser.add_argument(
        "--vgg-weights", type=Path, default=None, help="also calibrate perceptual/vgg16 with this VGG16 file"
    )
    parser.add_argument(
        "--metric",
        action="append",
        default=[],
        metavar="PKG.MOD:CLASS",
        help="also calibrate a user's own DifferenceMetric (repeatable)",
    )
    add_out_argument(parser, help="calibration JSON to write")
    add_frames_argument(parser, 240, help="at most this many frames, split over the drives (default 240)")
    parser.add_argument(
        "--horizon", type=int, default=3, help="predictions per frame, as the graph's world model (default 3)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def calibration_drives(data: Path, record: dict, topics: str | None = None) -> tuple[list, str]:
    """The label-free drives to calibrate on and why: the model's held-out normal drives when it names them."""
    from umad_common.datasets.formats import normal_root, training_drives

    root = normal_root(data)
    drives = training_drives(data, topics)
    heldout = set(record.get("heldout_drives") or [])
    chosen = [d for d in drives if d.name in heldout]
    if chosen:
        return chosen, "world model's held-out normal drives"
    log.warning(
        "%s lists no held-out drive found under %s: calibrating on every normal drive (scales will be low)",
        "world model",
        root,
    )
    return drives, "every normal drive (world model lists no held-out drive here)"


def sensor_frames(scenario, limit: int) -> Iterator:
    """The first `limit` frames of a label-free drive (`label_free_drive`: its reader cannot open a
    label) as the replayer sends them to the world model: camera, lidar (with the drive's rig), ego, route."""
    from umad_common.dataflow.api.operator import frame_of
    from umad_operators.replayer import frame_outputs
    from umad_operators.world_model import WorldModelPredictor

    ports = [port.name for port in WorldModelPredictor.inputs]
    for seq in range(min(len(scenario), limit)):
        outputs = frame_outputs(scenario[seq], scenario.name, scenario.sensors)
        yield frame_of(outputs, ports, scenario.name, seq, producer="calibrate")


def run(args: argparse.Namespace) -> int:
    normal_drives(args.data, "DATA", args.topics)
    model_file(args.world_model, "--world-model", "world model")
    if args.features is not None:
        model_file(args.features, "--features", "perceptual feature net")
    writable_output(args.out, "--out", folder=False)
    import torch
    from tqdm import tqdm

    from umad_common.differences import METRICS, CalibrationFitter, MetricOptions, build_metric, range_pairs
    from umad_common.models.weights import weight_paths
    from umad_operators.world_model import WorldModelPredictor

    if args.frames < 1:
        raise SystemExit(f"--frames is {args.frames}; expected at least 1")
    torch.set_num_threads(args.threads)
    weights, record_path = weight_paths(args.world_model)
    if not record_path.is_file():
        raise SystemExit(f"{record_path}: world model config not found; expected it beside {weights.name}")
    record = json.loads(record_path.read_text())
    stride = int(record.get("config", {}).get("frame_step", 1))  # as the graph runs it on 10 Hz frames
    predictor = WorldModelPredictor(
        {"model": str(weights.resolve()), "horizon": args.horizon, "stride": stride, "threads": args.threads}
    )

    features = args.features
    if features is None and (ASSETS / "feature_net.safetensors").is_file():
        features = ASSETS / "feature_net.safetensors"
    metrics = [build_metric(name) for name in METRICS if name != "perceptual"]
    if features is not None:
        metrics.append(build_metric("perceptual", MetricOptions(features=features)))
    else:
        log.warning("no feature net file: the perceptual metric is not calibrated")
    if args.vgg_weights is not None:
        metrics.append(build_metric("perceptual", MetricOptions(vgg_weights=args.vgg_weights)))
    metrics += [build_metric(path, MetricOptions(features=features)) for path in args.metric]

    scenarios, why = calibration_drives(args.data, record, args.topics)
    per_drive = -(-args.frames // len(scenarios))
    plan = []  # frames taken from the start of each drive (the world model needs them in order)
    for scenario in scenarios:
        plan.append(min(len(scenario), per_drive, args.frames - sum(plan)))
    fitter = CalibrationFitter()
    frames = 0
    with tqdm(total=sum(plan), desc="calibrate", unit="frame") as progress:
        for scenario, limit in zip(scenarios, plan, strict=True):
            for frame in sensor_frames(scenario, limit):
                arrays = predictor.process(frame)["frame"].arrays
                target, recon, preds, valid = (arrays[k] for k in ("target", "recon", "preds", "pred_valid"))
                lidar = range_pairs(arrays)
                for metric in metrics:
                    if metric.needs_predictions and not valid.any():
                        continue  # run start: no prediction yet; its zeros are a rule, not a normal value
                    if metric.needs_lidar and lidar is None:
                        continue  # a world model without a lidar head: no lidar scale
                    fitter.add(metric.calibration_key, metric(target, recon, preds, valid, lidar=lidar))
                frames += 1
                progress.update(1)
    if frames == 0:
        raise SystemExit(f"{args.data}: the calibration drives {[d.name for d in scenarios]} hold no frames")
    info = {
        "data": recorded_path(args.data),
        "drives": [d.name for d in scenarios],
        "drives_chosen": why,
        "frames": frames,
        "stride": stride,
        "horizon": args.horizon,
        "image_size": list(target.shape[:2]),
        "world_model": recorded_path(weights),
        "world_model_sha256": sha256(weights),
        "features": recorded_path(features) if features else None,
        "features_sha256": sha256(features) if features else None,
        "vgg_weights": recorded_path(args.vgg_weights) if args.vgg_weights else None,
        "labels_read": False,
    }
    calibration = fitter.fit(info)
    calibration.save(args.out)
    log.info("wrote %s: %s", args.out, {k: round(v, 5) for k, v in calibration.scales.items()})
    return 0
