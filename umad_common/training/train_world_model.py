"""Training the world model on normal drives: the epoch loop, across processes, and its checkpoints.

Each epoch trains on every drive's windows (`umad_common.training.world_model_data`) one step at a
time (`umad_common.training.world_model_step`) and ends with a checkpoint (MODEL.train.pt: model,
optimizer, epoch, history; read back with `torch.load(weights_only=True)`) and the weights
(MODEL.safetensors + MODEL.json), so `--resume` continues where training stopped and gives the same
weights as an uninterrupted run with the same seed, thread count and --epochs.

Across processes (`umad_common.training.distributed`), each rank computes the losses of its share of
every step's windows (`TrainingStep`, wrapped in DistributedDataParallel, which averages the
gradients); every rank draws the same window order and augmentations, so a step trains the same
windows whatever the number of processes, and rank 0 writes the files.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from umad_common.models.device import bf16_supported
from umad_common.models.weights import weight_paths
from umad_common.models.world_model import WorldModel, WorldModelConfig, save_world_model
from umad_common.training.distributed import Rank
from umad_common.training.world_model_data import (
    Light,
    epoch_windows,
    guaranteed_windows,
    load_normal_drives,
    observation_batch,
    scale_speed,
    view_batch,
)
from umad_common.training.world_model_step import TrainConfig, TrainingStep, psnr

log = logging.getLogger("umad.train.world_model")


def train_world_model(
    data: Path,
    out: Path,
    epochs: int = 16,
    seed: int = 0,
    resume: bool = False,
    threads: int = 2,
    model_config: WorldModelConfig | None = None,
    train_config: TrainConfig | None = None,
    command: str | None = None,
    device: str | torch.device = "cpu",
    rank: Rank | None = None,
    topics: str | None = None,
) -> dict:
    """Train on the normal drives under `data` on `device`; writes OUT.safetensors, OUT.json, OUT.train.pt.

    `command` (the command line that asked for this training) and the device are recorded in the JSON.
    Returns the JSON record written beside the weights (configs, held-out drives, loss history, time).
    `rank`: this process's place in a training across processes (`umad_common.training.distributed`,
    which starts the ranks); each rank runs `threads` threads and trains on its share of every
    step's `batch_size` windows, which must split evenly over the ranks. None: one process. `topics`:
    a recording's topic per role (`umad_common.datasets.topics`).
    """
    rank = rank or Rank()
    torch.set_num_threads(threads)
    device = rank.device(torch.device(device))
    model_config = model_config or WorldModelConfig()
    train = train_config or TrainConfig()
    if train.batch_size % rank.world:
        raise ValueError(
            f"batch_size {train.batch_size} does not split over {rank.world} processes; expected a multiple of "
            f"{rank.world} (each process trains on batch_size / processes windows per step)"
        )
    checkpoint_path = Path(str(weight_paths(out)[0].with_suffix("")) + ".train.pt")
    checkpoint = None
    if resume:
        if rank.writes and not checkpoint_path.is_file():
            raise FileNotFoundError(f"{checkpoint_path}: no training checkpoint to resume from")
        if rank.writes:
            checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=True)
        checkpoint = rank.from_rank_zero(checkpoint)  # the files are rank 0's; other machines may not see them
        model_config = WorldModelConfig.from_dict(checkpoint["model_config"])
        train = TrainConfig(**checkpoint["train_config"])
        if checkpoint["seed"] != seed:
            raise ValueError(f"{checkpoint_path}: trained with seed {checkpoint['seed']}; resume asked for seed {seed}")

    started = time.perf_counter()
    drives, heldout = load_normal_drives(Path(data), model_config, train.holdout, rank.writes, topics)
    frames = sum(len(d) for d in drives)
    log.info("%d normal drives, %d frames in memory (held out: %s)", len(drives), frames, heldout)

    torch.manual_seed(seed)
    model = WorldModel(model_config).to(device, memory_format=torch.channels_last)
    bf16 = train.bf16 and bf16_supported(device)
    if train.bf16 and not bf16:
        log.warning("%s has no bfloat16 support here: training in float32 (slower, same model)", device)
    optimizer = torch.optim.Adam(model.parameters(), lr=train.learning_rate)
    steps_per_epoch = guaranteed_windows(drives, train.sequence_length) // train.batch_size
    if steps_per_epoch == 0:
        raise ValueError(
            f"{data}: fewer than {train.batch_size} windows of {train.sequence_length} frames in the normal drives; "
            "expected more or longer drives (or a smaller --batch-size / --sequence-length)"
        )
    total_steps = steps_per_epoch * epochs
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: 0.1 + 0.45 * (1 + math.cos(math.pi * min(step / total_steps, 1.0)))
    )
    history: list[dict] = []
    first_epoch = 0
    if checkpoint is not None:
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        schedule.load_state_dict(checkpoint["schedule"])
        history = list(checkpoint["history"])
        first_epoch = int(checkpoint["epoch"]) + 1

    if first_epoch >= epochs:
        raise ValueError(f"{checkpoint_path}: already trained {first_epoch} epochs; ask for more than {epochs}")
    lidar = model_config.lidar_head
    model.train()
    training_step = TrainingStep(model, train, bf16)
    if rank.distributed:
        from torch.nn.parallel import DistributedDataParallel

        training_step = DistributedDataParallel(
            training_step, device_ids=[device.index] if device.type == "cuda" else None
        )
    bar = tqdm(
        total=total_steps,
        initial=first_epoch * steps_per_epoch,
        desc="world model",
        unit="step",
        disable=not rank.writes,
    )
    step_seconds = 0.0  # in the training steps of this run, without loading drives or writing files
    for epoch in range(first_epoch, epochs):
        rng = np.random.default_rng([seed, epoch])
        torch.manual_seed(seed * 100_003 + epoch + 1_000_003 * rank.index)  # each rank its own posterior samples
        windows = epoch_windows(drives, train.sequence_length, rng)
        sums = {"loss": 0.0, "rgb_l1": 0.0, "rgb_ssim": 0.0, "rgb_mse": 0.0, "pred_mse": 0.0, "kl": 0.0}
        if lidar:
            sums.update(lidar_l1=0.0, pred_lidar_l1=0.0)
        epoch_started = time.perf_counter()
        for step in range(steps_per_epoch):
            batch = windows[step * train.batch_size : (step + 1) * train.batch_size]
            mirrored = list(rng.random(len(batch)) < train.mirror)  # drawn for the whole step on every rank
            lights = (
                [Light.draw(rng) if rng.random() < train.relight else None for _ in batch] if train.relight else None
            )
            batch, mirrored = rank.share(batch), rank.share(mirrored)
            lights = rank.share(lights) if lights is not None else None
            obs, prev_actions = observation_batch(drives, batch, train.sequence_length, mirrored, lights)
            obs, prev_actions = scale_speed(obs, model_config).to(device), prev_actions.to(device)
            views = view_batch(drives, batch, train.sequence_length, mirrored).to(device) if lidar else None
            terms = training_step(obs, prev_actions, views)
            optimizer.zero_grad(set_to_none=True)
            terms["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), train.grad_clip)
            optimizer.step()
            schedule.step()
            values = {key: float(value.detach()) for key, value in terms.items()}
            for key, value in values.items():
                sums[key] += value
            bar.update(1)
            bar.set_postfix(
                epoch=epoch + 1,
                loss=f"{values['loss']:.4f}",
                psnr=f"{psnr(values['rgb_mse']):.2f}",
                pred_psnr=f"{psnr(values['pred_mse']):.2f}",
            )
        step_seconds += time.perf_counter() - epoch_started
        means = rank.mean({key: value / steps_per_epoch for key, value in sums.items()})
        history.append(
            {"epoch": epoch + 1, **means, "psnr": psnr(means["rgb_mse"]), "pred_psnr": psnr(means["pred_mse"])}
        )
        record = {
            "train_config": asdict(train),
            "command": command,
            "seed": seed,
            "epochs": epoch + 1,
            "threads": threads,
            **({"processes": rank.world} if rank.distributed else {}),
            "device": str(device),
            "data": str(data),
            "training_drives": [d.name for d in drives],
            "heldout_drives": heldout,
            "training_frames": frames,
            "train_seconds": round(time.perf_counter() - started, 1),
            "samples_per_second": round(
                (epoch + 1 - first_epoch) * steps_per_epoch * train.batch_size / step_seconds, 3
            ),
            "history": history,
        }
        if not rank.writes:
            continue
        save_world_model(model, out, record)
        torch.save(
            {
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "schedule": schedule.state_dict(),
                "epoch": epoch,
                "seed": seed,
                "history": history,
                "model_config": model_config.to_dict(),
                "train_config": asdict(train),
            },
            checkpoint_path,
        )
    bar.close()
    return record
