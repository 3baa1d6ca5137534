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

log = logging.getLogger("umad.calibrate")
ASSETS = Path(__file__).resolve().parents[1] / "assets"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "data", type=Path, help="benchmark folder (its normal/ drives are used) or a folder of normal drives"
    )
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
    parser.add_argument("--out", type=Path, required=True, help="calibration JSON to write")
    parser.add_argument(
        "--frames", type=int, default=240, help="at most this many frames, split over the drives (default 240)"
    )
    parser.add_argument(
        "--horizon", type=int, default=3, help="predictions per frame, as the graph's world model (default 3)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def calibration_drives(data: Path, record: dict) -> tuple[list[Path], str]:
    """The drives to calibrate on and why: the model's held-out normal drives when it names them."""
    from umad_common.datasets.anovox import find_scenarios
    from umad_common.training.train_features import normal_root

    root = normal_root(data)
    drives = find_scenarios(root)
    if not drives:
        raise SystemExit(f"{root}: no Scenario_* folders; expected AnoVox normal drives")
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


def sensor_frames(drive: Path, every: int, limit: int) -> Iterator:
    """Frames of one drive as the replayer sends them: camera, lidar, ego and route only (the
    reader is blind to label folders, so no label file is ever opened)."""
    import numpy as np

    from umad_common.messages import Message
    from umad_common.operator import Frame
    from umad_common.training.train_features import label_free_scenario

    scenario = label_free_scenario(drive, every=every)
    for seq in range(min(len(scenario), limit)):
        item = scenario[seq]
        ego = item.ego
        lidar = item.lidar if item.lidar is not None else np.zeros((0, 4), np.float32)
        route = item.route if item.route is not None else np.zeros((192, 192), np.uint8)
        arrays = {
            "camera": {"rgb": item.rgb},
            "lidar": {"points": lidar},
            "ego": {"ego": np.array([ego.speed_mps, ego.throttle, ego.brake, ego.steer], np.float32)},
            "route": {"route": route},
        }
        yield Frame(
            scenario.name,
            seq,
            0,
            inputs={port: Message(scenario.name, seq, 0, producer="calibrate", arrays=a) for port, a in arrays.items()},
        )


def run(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    from operators.world_model import WorldModelPredictor
    from umad_common.differences import METRICS, CalibrationFitter, MetricOptions, build_metric
    from umad_common.models.world_model import weight_paths

    if args.frames < 1:
        raise SystemExit(f"--frames is {args.frames}; expected at least 1")
    torch.set_num_threads(args.threads)
    weights, record_path = weight_paths(args.world_model)
    predictor = WorldModelPredictor({"model": str(weights.resolve()), "horizon": args.horizon, "threads": args.threads})
    record = json.loads(record_path.read_text())
    every = int(record.get("config", {}).get("frame_step", 1))

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

    drives, why = calibration_drives(args.data, record)
    per_drive = -(-args.frames // len(drives))
    fitter = CalibrationFitter()
    frames = 0
    with tqdm(total=min(args.frames, per_drive * len(drives)), desc="calibrate", unit="frame") as progress:
        for drive in drives:
            for frame in sensor_frames(drive, every, min(per_drive, args.frames - frames)):
                arrays = predictor.process(frame)["frame"].arrays
                target, recon, preds, valid = (arrays[k] for k in ("target", "recon", "preds", "pred_valid"))
                for metric in metrics:
                    if metric.needs_predictions and not valid.any():
                        continue  # run start: no prediction yet; its zeros are a rule, not a normal value
                    fitter.add(metric.calibration_key, metric(target, recon, preds, valid))
                frames += 1
                progress.update(1)
    if frames == 0:
        raise SystemExit(f"{args.data}: the calibration drives {[d.name for d in drives]} hold no frames")
    info = {
        "data": str(args.data),
        "drives": [d.name for d in drives],
        "drives_chosen": why,
        "frames": frames,
        "frame_step": every,
        "horizon": args.horizon,
        "image_size": list(target.shape[:2]),
        "world_model": str(weights),
        "world_model_sha256": sha256(weights),
        "features": str(features) if features else None,
        "features_sha256": sha256(features) if features else None,
        "vgg_weights": str(args.vgg_weights) if args.vgg_weights else None,
        "labels_read": False,
    }
    calibration = fitter.fit(info)
    calibration.save(args.out)
    log.info("wrote %s: %s", args.out, {k: round(v, 5) for k, v in calibration.scales.items()})
    return 0
