"""Fitting a lidar head to a trained world model, every other weight frozen.

The head learns to decode the lidar view from the states the model filters and predicts on the
normal drives, with the loss joint training uses (`umad_common.training.world_model_step.lidar_terms`);
the model's images, and so every camera map, stay bit for bit as they were.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from umad_common.models.device import bf16_supported
from umad_common.models.world_model import WorldModel, WorldModelConfig, load_world_model, save_world_model
from umad_common.training.world_model_data import (
    epoch_windows,
    guaranteed_windows,
    load_normal_drives,
    observation_batch,
    scale_speed,
    view_batch,
)
from umad_common.training.world_model_step import TrainConfig, lidar_terms, open_loop_predictions


def fit_lidar_head(
    data: Path,
    world_model: Path,
    out: Path,
    epochs: int = 8,
    seed: int = 0,
    threads: int = 2,
    train_config: TrainConfig | None = None,
    command: str | None = None,
    device: str | torch.device = "cpu",
    topics: str | None = None,
) -> dict:
    """Give a trained world model a lidar head: the model's other weights stay as they are (frozen, so
    its images and every camera map stay bit for bit the same) and the head learns to decode the lidar
    view from the states the model filters and predicts on the normal drives under `data`, with the
    loss joint training uses (`lidar_terms`). Writes OUT.safetensors + OUT.json (the model's record,
    plus `lidar_head_fit`: this fit's command, data, epochs and loss history)."""
    torch.set_num_threads(threads)
    device = torch.device(device)
    base, record = load_world_model(world_model, "cpu")
    if base.config.lidar_head:
        raise ValueError(f"{world_model}: already has a lidar head; expected a world model without one")
    config = WorldModelConfig.from_dict({**base.config.to_dict(), "lidar_head": True})
    train = train_config or TrainConfig(**record.get("train_config", {}))
    torch.manual_seed(seed)
    model = WorldModel(config)
    missing, unexpected = model.load_state_dict(base.state_dict(), strict=False)
    if unexpected or any(not key.startswith("lidar_decoder.") for key in missing):
        raise ValueError(
            f"{world_model}: tensors do not fit the model with a lidar head ({missing[:3]}, {unexpected[:3]})"
        )
    model.to(device).eval()
    bf16 = train.bf16 and bf16_supported(device)
    model.requires_grad_(False)
    model.lidar_decoder.requires_grad_(True)
    optimizer = torch.optim.Adam(model.lidar_decoder.parameters(), lr=train.learning_rate)

    started = time.perf_counter()
    drives, heldout = load_normal_drives(Path(data), config, train.holdout, topics=topics)
    steps_per_epoch = guaranteed_windows(drives, train.sequence_length) // train.batch_size
    if steps_per_epoch == 0:
        raise ValueError(f"{data}: fewer than {train.batch_size} windows of {train.sequence_length} frames")
    history: list[dict] = []
    bar = tqdm(total=steps_per_epoch * epochs, desc="lidar head", unit="step")
    for epoch in range(epochs):
        rng = np.random.default_rng([seed, epoch])
        windows = epoch_windows(drives, train.sequence_length, rng)
        sums = {"lidar_l1": 0.0, "pred_lidar_l1": 0.0}
        for step in range(steps_per_epoch):
            batch = windows[step * train.batch_size : (step + 1) * train.batch_size]
            obs, prev_actions = observation_batch(drives, batch, train.sequence_length)
            obs, prev_actions = scale_speed(obs, config).to(device), prev_actions.to(device)
            views = view_batch(drives, batch, train.sequence_length).to(device)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                with torch.no_grad():
                    result = model.observe(obs, prev_actions, images=False)
                    predicted = open_loop_predictions(model, result, prev_actions, obs.speed, train, images=False)
                terms = lidar_terms(model, result, predicted, views, train)
            optimizer.zero_grad(set_to_none=True)
            terms["lidar_loss"].backward()
            optimizer.step()
            for key in sums:
                sums[key] += float(terms[key])
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, lidar_l1=f"{float(terms['lidar_l1']):.4f}")
        history.append({"epoch": epoch + 1, **{key: value / steps_per_epoch for key, value in sums.items()}})
        fit = {
            "command": command,
            "data": str(data),
            "base_model": str(world_model),
            "seed": seed,
            "epochs": epoch + 1,
            "threads": threads,
            "device": str(device),
            "training_drives": [d.name for d in drives],
            "heldout_drives": heldout,
            "train_seconds": round(time.perf_counter() - started, 1),
            "history": history,
        }
        base_record = {key: value for key, value in record.items() if key != "config"}
        base_record["train_config"] = asdict(train)  # the recipe's fields of today, lidar_weight among them
        save_world_model(model.cpu(), out, {**base_record, "lidar_head_fit": fit})
        model.to(device)
    bar.close()
    return fit
