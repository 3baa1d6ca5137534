"""How good is a trained world model: held-out normal PSNR and the anomaly / road error ratio.

- Held-out normal drives (named in MODEL.json, kept out of training): PSNR of the posterior
  reconstruction x̂_t and of the one-step prediction x̂_{t|t-1} (decoded prior).
- Anomalous drives (DATA/anomalous): mean |x − x̂_t| (over r, g, b) inside the anomaly mask against
  the same on road pixels outside it (semantic tag 1 road or 24 road line). The model never saw an
  anomaly, so it should not draw one: the ratio must be well above 1. Labels are resized
  nearest-neighbour to the model size, as the accumulator does.

    umad test world-model umad_common/assets/world_model.safetensors data/synth
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from umad_common.models.world_model import State, WorldModel
from umad_common.training.train_world_model import (
    DriveArrays,
    load_drive,
    normal_root,
    observation_batch,
    open_inputs_only,
    psnr,
    scale_speed,
)

ROAD_TAGS = (1, 24)


@torch.no_grad()
def reconstruct_drive(model: WorldModel, drive: DriveArrays, chunk: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Filter a whole drive from its start; returns reconstructions and one-step predictions, both
    (T, H, W, 3) float32 in [0, 1] (the prediction of frame 0 is from the initial state)."""
    recons, preds = [], []
    state = None
    for start in range(0, len(drive), chunk):
        length = min(chunk, len(drive) - start)
        obs, prev_actions = observation_batch([drive], [(0, start)], length)
        result = model.observe(scale_speed(obs, model.config), prev_actions, state=state)
        state = State(result.states.h[:, -1], result.states.z[:, -1])
        prior_rgb, _ = model.decode(State(result.states.h[0], result.prior_mean[0]), with_lidar=False)
        recons.append(result.rgb[0].permute(0, 2, 3, 1).numpy())
        preds.append(prior_rgb.permute(0, 2, 3, 1).numpy())
    return np.concatenate(recons), np.concatenate(preds)


def label_masks(scenario, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, h, w) bool anomaly mask and road-outside-anomaly mask at model size (nearest resize)."""
    anomaly, road = [], []
    for i in range(len(scenario)):
        frame = scenario[i]
        if frame.semantic is None:
            raise ValueError(f"{scenario.name} frame {frame.frame_id}: no semantic image; the road mask needs it")
        an = cv2.resize(np.asarray(frame.anomaly, np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
        sem = cv2.resize(np.asarray(frame.semantic, np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
        anomaly.append(an == 1)
        road.append(np.isin(sem, ROAD_TAGS) & (an == 0))
    return np.stack(anomaly), np.stack(road)


def evaluate_world_model(
    model: WorldModel, data: Path, heldout: list[str], anomalous_limit: int | None = None
) -> dict[str, float | int]:
    """Figures of `model` on DATA: held-out normal drives by name, and DATA/anomalous (up to
    `anomalous_limit` drives). Returns PSNRs, the error inside / outside anomalies and their ratio."""
    from umad_common.datasets.anovox import AnoVoxScenario, find_scenarios

    config = model.config
    model.eval()
    figures: dict[str, float | int] = {}
    heldout_paths = [p for p in find_scenarios(normal_root(Path(data))) if p.name in set(heldout)]
    recon_se, pred_se, values = 0.0, 0.0, 0
    for path in heldout_paths:
        drive = load_drive(open_inputs_only(path, config.frame_step), config)
        recon, pred = reconstruct_drive(model, drive)
        target = drive.rgb.astype(np.float32) / 255.0
        recon_se += float(((recon - target) ** 2).sum())
        pred_se += float(((pred[1:] - target[1:]) ** 2).sum())
        values += target.size
    if values:
        frames = values // (config.image_height * config.image_width * 3)
        figures["heldout_drives"] = len(heldout_paths)
        figures["heldout_recon_psnr"] = psnr(recon_se / values)
        figures["heldout_pred1_psnr"] = psnr(
            pred_se / (values - 3 * config.image_height * config.image_width * len(heldout_paths))
        )
        figures["heldout_frames"] = int(frames)

    anomalous_root = Path(data) / "anomalous"
    paths = find_scenarios(anomalous_root) if anomalous_root.is_dir() else []
    paths = paths[:anomalous_limit] if anomalous_limit else paths
    sums = {"anomaly": 0.0, "road": 0.0}
    counts = {"anomaly": 0, "road": 0}
    for path in paths:
        drive = load_drive(open_inputs_only(path, config.frame_step), config)
        recon, _ = reconstruct_drive(model, drive)
        error = np.abs(recon - drive.rgb.astype(np.float32) / 255.0).mean(-1)  # (T, h, w)
        scenario = AnoVoxScenario(path, every=config.frame_step)
        anomaly, road = label_masks(scenario, config.image_height, config.image_width)
        for name, mask in (("anomaly", anomaly), ("road", road)):
            sums[name] += float(error[mask].sum())
            counts[name] += int(mask.sum())
    if paths:
        figures["anomalous_drives"] = len(paths)
        figures["anomaly_pixels"] = counts["anomaly"]
        figures["anomaly_error"] = sums["anomaly"] / max(counts["anomaly"], 1)
        figures["road_error"] = sums["road"] / max(counts["road"], 1)
        figures["anomaly_road_ratio"] = figures["anomaly_error"] / max(figures["road_error"], 1e-12)
    return figures
