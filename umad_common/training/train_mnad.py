"""Training the MNAD baseline (umad_common.models.mnad) on normal drives only.

The paper's recipe, reconstruction variant: Adam (lr 2e-4) with cosine annealing, loss = MSE
reconstruction + 0.1 compactness + 0.1 separateness, memory items updated after every step from
the batch's queries. Frames are the normal drives' camera images (DATA/normal when present),
plainly resized to the model size, as the predictor operator sees them.

Deterministic: the seed fixes the initial weights, the memory and the batch order, and torch's
deterministic algorithms are on; the same data, seed, epochs and thread count give the same file.
A time budget (`minutes`) is turned into a number of epochs before training starts, by timing a few
steps of a throwaway copy; the record keeps that number, so `--epochs` reproduces the run. Like the
world model, it trains with bfloat16 autocast and channels-last convolutions where the CPU has
bfloat16 (faster: docs/experiments.md), the loss in float32.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from umad_common.models.device import bf16_supported
from umad_common.models.mnad import Mnad, MnadConfig

log = logging.getLogger("umad.train.mnad")


@dataclass
class MnadTrainingConfig:
    epochs: int = 3  # passes over the loaded frames (ignored when `minutes` is set)
    seed: int = 0
    batch_size: int = 8
    lr: float = 2e-4  # the paper's Adam learning rate, cosine-annealed to 0
    max_frames: int = 1200  # frames loaded, spread evenly over the normal scenarios
    minutes: float | None = None  # train for about this long: sets `epochs` from the measured step time
    bf16: bool = True  # bfloat16 autocast where the CPU (or GPU) supports it


def epochs_for_budget(frames: torch.Tensor, cfg: MnadTrainingConfig, model_cfg: MnadConfig, bf16: bool) -> int:
    """How many epochs fit in `cfg.minutes`: times 4 steps (after one warm-up) of a throwaway model."""
    model = Mnad(model_cfg).train().to(frames.device, memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    batch = frames[: cfg.batch_size]
    times = []
    for _ in range(5):
        start = time.perf_counter()
        training_step(model, optimizer, batch, bf16)
        times.append(time.perf_counter() - start)
    step_s = float(np.mean(times[1:]))
    steps_per_epoch = len(frames) // cfg.batch_size
    return max(1, int(cfg.minutes * 60 / (step_s * steps_per_epoch)))


def training_step(model: Mnad, optimizer: torch.optim.Optimizer, batch: torch.Tensor, bf16: bool) -> dict:
    """One step: forward (autocast on the batch's device), float32 loss, backward, Adam, memory update;
    returns the loss parts."""
    with torch.autocast(batch.device.type, dtype=torch.bfloat16, enabled=bf16):
        out = model(batch)
    out = out._replace(recon=out.recon.float(), query=out.query.float())
    loss, parts = model.loss(batch, out)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    model.update_memory(out.query)
    return parts


def frames_to_tensor(frames: np.ndarray) -> torch.Tensor:
    """(N, h, w, 3) uint8 -> (N, 3, h, w) float32 in [-1, 1], MNAD's input range."""
    return torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float() / 127.5 - 1.0


def train_mnad(
    frames: np.ndarray,
    train_cfg: MnadTrainingConfig,
    model_cfg: MnadConfig | None = None,
    progress: bool = True,
    device: str | torch.device = "cpu",
) -> tuple[Mnad, dict]:
    """Train MNAD on (N, h, w, 3) uint8 normal frames already at the model size, on `device`.

    Returns:
        the model on the CPU in eval mode and a training record (losses, steps, seconds, device) for
        its JSON.

    Raises:
        ValueError: frames of the wrong dtype/shape, or fewer frames than one batch.
    """
    model_cfg = model_cfg or MnadConfig()
    expected = (model_cfg.height, model_cfg.width, 3)
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[1:] != expected:
        raise ValueError(
            f"train_mnad: expected (N, {expected[0]}, {expected[1]}, 3) uint8 frames, got {frames.dtype} {frames.shape}"
        )
    if len(frames) < 2:
        raise ValueError(f"train_mnad: need at least 2 frames (batch norm), got {len(frames)}")
    device = torch.device(device)
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    try:
        return _train(frames, train_cfg, model_cfg, progress, device)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)


def _train(
    frames: np.ndarray, train_cfg: MnadTrainingConfig, model_cfg: MnadConfig, progress: bool, device: torch.device
) -> tuple[Mnad, dict]:
    data = frames_to_tensor(frames).contiguous(memory_format=torch.channels_last).to(device)
    batch_size = min(train_cfg.batch_size, len(frames))
    bf16 = train_cfg.bf16 and bf16_supported(device)
    epochs = train_cfg.epochs if train_cfg.minutes is None else epochs_for_budget(data, train_cfg, model_cfg, bf16)
    torch.manual_seed(train_cfg.seed)
    order_rng = np.random.default_rng(train_cfg.seed)
    model = Mnad(model_cfg).train().to(device, memory_format=torch.channels_last)
    steps_per_epoch = len(frames) // batch_size  # drop the ragged last batch: batch norm needs >= 2
    total_steps = steps_per_epoch * epochs
    optimizer = torch.optim.Adam(model.parameters(), lr=train_cfg.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, total_steps))
    start = time.perf_counter()
    history: list[dict[str, float]] = []
    bar = tqdm(total=total_steps, desc="train mnad", unit="step", disable=not progress)
    for epoch in range(epochs):
        order = order_rng.permutation(len(frames))
        sums = {"reconstruction": 0.0, "compactness": 0.0, "separateness": 0.0}
        for step in range(steps_per_epoch):
            batch = data[torch.from_numpy(order[step * batch_size : (step + 1) * batch_size]).to(device)]
            parts = training_step(model, optimizer, batch, bf16)
            schedule.step()
            for key, value in parts.items():
                sums[key] += value
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, rec=f"{parts['reconstruction']:.4f}")
        history.append(
            {
                "epoch": epoch + 1,
                **{key: value / steps_per_epoch for key, value in sums.items()},
                "seconds": round(time.perf_counter() - start, 1),
            }
        )
        log.info("epoch %d/%d: %s", epoch + 1, epochs, history[-1])
    bar.close()
    record = {
        "training": {
            **asdict(train_cfg),
            "epochs": epochs,
            "bf16": bf16,
            "frames": int(len(frames)),
            "steps": total_steps,
            "seconds": round(time.perf_counter() - start, 1),
            "threads": torch.get_num_threads(),
            "device": str(device),
            "losses_per_epoch": history,
        }
    }
    return model.cpu().eval(), record


def load_normal_frames(data: Path, cfg: MnadConfig, max_frames: int, topics: str | None = None) -> np.ndarray:
    """(N, h, w, 3) uint8 camera frames of the normal drives (DATA/normal when present), resized to
    the model size and spread evenly over all drives. Label files are never opened. `topics`: a
    recording's topic per role (`umad_common.datasets.topics`)."""
    from umad_common.datasets.formats import normal_root, training_drives

    root = normal_root(Path(data))
    scenarios = training_drives(data, topics, keep=("rgb",))
    total = sum(len(s) for s in scenarios)
    stride = max(1, int(np.ceil(total / max_frames)))
    frames = [
        cv2.resize(scenario[index].rgb, (cfg.width, cfg.height), interpolation=cv2.INTER_AREA)
        for scenario in tqdm(scenarios, desc="load normal drives", unit="drive")
        for index in range(0, len(scenario), stride)
    ]
    log.info(
        "loaded %d normal frames (every %d of %d) from %d drives in %s",
        len(frames),
        stride,
        total,
        len(scenarios),
        root,
    )
    return np.stack(frames)
