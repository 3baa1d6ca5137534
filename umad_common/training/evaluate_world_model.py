"""How good is a trained world model: PSNR on normal drives it never saw, and the anomaly / road
error ratio.

- Normal drives the model never saw: every Scenario_* under DATA/normal (or DATA) that is not one
  of the `training_drives` named in MODEL.json, so the training folder gives its held-out drives
  and any other folder of normal drives gives all of them. Per drive, the posterior is filtered
  from the drive's start; figures: PSNR of the reconstruction x̂_t and of the predictions
  x̂_{t|t-k} for k = 1..horizon (the prior rolled k steps forward from the posterior state of
  frame t-k with the actions actually taken and the speed of frame t-k, never having seen the
  frames since). With a lidar head, the same for the lidar view: the median absolute range error
  (metres) over the lidar returns in the camera's view, of the reconstruction and of each prediction.
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

from umad_common.datasets.drive import Drive
from umad_common.datasets.formats import find_drives, label_free_drive, normal_root, open_drive
from umad_common.models.world_model import State, WorldModel
from umad_common.training.world_model_data import DriveArrays, load_drive, observation_batch, scale_speed
from umad_common.training.world_model_step import psnr

ROAD_TAGS = (1, 24)


@torch.no_grad()
def filter_drive(model: WorldModel, drive: DriveArrays, chunk: int = 32) -> tuple[State, np.ndarray]:
    """The posterior over a whole drive from its start: states (T, .) and reconstructions
    (T, H, W, 3) float32 in [0, 1] (`lidar_errors` decodes the lidar view from the states)."""
    hs, zs, recons = [], [], []
    state = None
    for start in range(0, len(drive), chunk):
        length = min(chunk, len(drive) - start)
        obs, prev_actions = observation_batch([drive], [(0, start)], length)
        result = model.observe(scale_speed(obs, model.config), prev_actions, state=state)
        state = State(result.states.h[:, -1], result.states.z[:, -1])
        hs.append(result.states.h[0])
        zs.append(result.states.z[0])
        recons.append(result.rgb[0].permute(0, 2, 3, 1).numpy())
    return State(torch.cat(hs), torch.cat(zs)), np.concatenate(recons)


@torch.no_grad()
def predict_drive(model: WorldModel, drive: DriveArrays, posterior: State, horizon: int, chunk: int = 32):
    """Yields (k, frames, predicted, states) for k = 1..horizon: the frames t >= k of the drive, the
    predictions x̂_{t|t-k} (len, H, W, 3) and their prior states, made by advancing the prior one step
    at a time with the action taken after each frame, from the posterior state of frame t-k."""
    actions = torch.from_numpy(drive.action)  # (T, 2) the action taken after frame t
    speed = torch.from_numpy(drive.speed) / model.config.speed_scale  # row j: the speed of origin frame j
    states = posterior
    for k in range(1, horizon + 1):
        if len(drive) <= k:
            return
        h = model.transition(
            State(states.h[:-1], states.z[:-1]),
            actions[k - 1 : len(drive) - 1],
            move=True,
            speed=speed[: len(drive) - k],
        )
        states = State(h, model.prior(h)[0])  # row j: prediction of frame j + k
        images = [
            model.decode(State(states.h[i : i + chunk], states.z[i : i + chunk])).permute(0, 2, 3, 1).numpy()
            for i in range(0, len(h), chunk)
        ]
        yield k, np.arange(k, len(drive)), np.concatenate(images), states


@torch.no_grad()
def lidar_errors(model: WorldModel, states: State, views: np.ndarray, chunk: int = 32) -> np.ndarray:
    """|r̂ - r| in metres of every lidar return in `views` (N, rows, columns), metres, 0 where none)
    against the lidar view decoded from `states` (N, .)."""
    errors = []
    for i in range(0, len(views), chunk):
        expected = model.decode_lidar(State(states.h[i : i + chunk], states.z[i : i + chunk])).numpy()
        view = views[i : i + chunk].astype(np.float32)
        hit = view > 0
        errors.append(np.abs(expected[hit] - view[hit]))
    return np.concatenate(errors) if errors else np.zeros(0, np.float32)


def unseen_normal_drives(data: Path, record: dict, topics: str | None = None, every: int = 1) -> list[Drive]:
    """Normal drives under DATA that the model did not train on (by the names in its record), label-free,
    every `every`-th frame kept."""
    trained = set(record.get("training_drives") or [])
    drives = [label_free_drive(path, every, topics) for path in find_drives(normal_root(Path(data)))]
    return [drive for drive in drives if drive.name not in trained]


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
    model: WorldModel,
    data: Path,
    record: dict,
    horizon: int = 3,
    normal_limit: int | None = None,
    anomalous_limit: int | None = None,
    topics: str | None = None,
) -> dict:
    """Figures of `model` on DATA: its unseen normal drives (up to `normal_limit`) and DATA/anomalous
    (up to `anomalous_limit` drives). Returns PSNRs (reconstruction, prediction k = 1..horizon),
    the error inside / outside anomalies and their ratio, and the PSNRs of each normal drive
    (`per_drive`, by drive name): which drives are hard. The ratio reads the road from semantic labels:
    drives without them (recordings) are left out of it. `topics`: a recording's topic per role."""
    config = model.config
    model.eval()
    figures: dict = {}
    normal = unseen_normal_drives(data, record, topics, config.frame_step)[:normal_limit]
    squared = {k: 0.0 for k in range(horizon + 1)}  # k = 0: the reconstruction
    counts = {k: 0 for k in range(horizon + 1)}
    per_drive: dict[str, dict[str, float]] = {}
    range_errors: dict[int, list[np.ndarray]] = {k: [] for k in range(horizon + 1)}
    for unseen in normal:
        drive = load_drive(unseen, config)
        target = drive.rgb.astype(np.float32) / 255.0
        posterior, recon = filter_drive(model, drive)
        drive_squared = {0: float(((recon - target) ** 2).sum())}
        drive_counts = {0: target.size}
        if config.lidar_head:
            range_errors[0].append(lidar_errors(model, posterior, drive.view))
        for k, frames, predicted, states in predict_drive(model, drive, posterior, horizon):
            drive_squared[k] = float(((predicted - target[frames]) ** 2).sum())
            drive_counts[k] = predicted.size
            if config.lidar_head:
                range_errors[k].append(lidar_errors(model, states, drive.view[frames]))
        for k in drive_squared:
            squared[k] += drive_squared[k]
            counts[k] += drive_counts[k]
        per_drive[unseen.name] = psnr_figures(drive_squared, drive_counts)
    if normal:
        figures["normal_drives"] = len(normal)
        figures["normal_frames"] = counts[0] // (config.image_height * config.image_width * 3)
        figures.update(psnr_figures(squared, counts))
        if config.lidar_head:
            for k, errors in range_errors.items():
                name = "recon_range_error_m" if k == 0 else f"pred{k}_range_error_m"
                figures[name] = float(np.median(np.concatenate(errors))) if errors else float("nan")

    anomalous_root = Path(data) / "anomalous"
    paths = find_drives(anomalous_root) if anomalous_root.is_dir() else []
    paths = paths[:anomalous_limit] if anomalous_limit else paths
    labelled = [open_drive(path, config.frame_step, topics) for path in paths]
    labelled = [drive for drive in labelled if "semantic" in drive.modalities]
    sums = {"anomaly": 0.0, "road": 0.0}
    pixels = {"anomaly": 0, "road": 0}
    for scenario in labelled:
        drive = load_drive(label_free_drive(scenario.path, config.frame_step, topics), config)
        _, recon = filter_drive(model, drive)
        error = np.abs(recon - drive.rgb.astype(np.float32) / 255.0).mean(-1)  # (T, h, w)
        anomaly, road = label_masks(scenario, config.image_height, config.image_width)
        for name, mask in (("anomaly", anomaly), ("road", road)):
            sums[name] += float(error[mask].sum())
            pixels[name] += int(mask.sum())
    if labelled:
        figures["anomalous_drives"] = len(labelled)
        figures["anomaly_pixels"] = pixels["anomaly"]
        figures["anomaly_error"] = sums["anomaly"] / max(pixels["anomaly"], 1)
        figures["road_error"] = sums["road"] / max(pixels["road"], 1)
        figures["anomaly_road_ratio"] = figures["anomaly_error"] / max(figures["road_error"], 1e-12)
    if per_drive:
        figures["per_drive"] = per_drive
    return figures


def psnr_figures(squared: dict[int, float], counts: dict[int, int]) -> dict[str, float]:
    """`recon_psnr` (k = 0) and `pred{k}_psnr` from summed squared errors and value counts per k."""
    return {
        ("recon_psnr" if k == 0 else f"pred{k}_psnr"): psnr(squared[k] / counts[k])
        for k in sorted(squared)
        if counts[k]
    }
