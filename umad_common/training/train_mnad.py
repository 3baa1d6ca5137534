"""Training the MNAD baseline (umad_common.models.mnad) on normal drives only.

The paper's recipe, reconstruction variant: Adam (lr 2e-4) with cosine annealing, loss = MSE
reconstruction + 0.1 compactness + 0.1 separateness, memory items updated after every step from
the batch's queries. Frames are the normal drives' camera images (DATA/normal when present),
plainly resized to the model size, as the predictor operator sees them.

Deterministic: the seed fixes the initial weights, the memory and the batch order, and torch's
deterministic algorithms are on; the same data, seed and thread count give the same file.
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

from umad_common.models.mnad import Mnad, MnadConfig

log = logging.getLogger("umad.train.mnad")


@dataclass
class MnadTrainingConfig:
    epochs: int = 3  # passes over the loaded frames (the shipped checkpoint: 3, ~10 min on one busy core)
    seed: int = 0
    batch_size: int = 8
    lr: float = 2e-4  # the paper's Adam learning rate, cosine-annealed to 0
    max_frames: int = 1200  # frames loaded, spread evenly over the normal scenarios


def frames_to_tensor(frames: np.ndarray) -> torch.Tensor:
    """(N, h, w, 3) uint8 -> (N, 3, h, w) float32 in [-1, 1], MNAD's input range."""
    return torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float() / 127.5 - 1.0


def train_mnad(
    frames: np.ndarray,
    train_cfg: MnadTrainingConfig,
    model_cfg: MnadConfig | None = None,
    progress: bool = True,
) -> tuple[Mnad, dict]:
    """Train MNAD on (N, h, w, 3) uint8 normal frames already at the model size.

    Returns:
        the model in eval mode and a training record (losses, steps, seconds) for its JSON.

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
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        return _train(frames, train_cfg, model_cfg, progress)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)


def _train(
    frames: np.ndarray, train_cfg: MnadTrainingConfig, model_cfg: MnadConfig, progress: bool
) -> tuple[Mnad, dict]:
    torch.manual_seed(train_cfg.seed)
    order_rng = np.random.default_rng(train_cfg.seed)
    model = Mnad(model_cfg).train()
    data = frames_to_tensor(frames)
    batch_size = min(train_cfg.batch_size, len(frames))
    steps_per_epoch = len(frames) // batch_size  # drop the ragged last batch: batch norm needs >= 2
    total_steps = steps_per_epoch * train_cfg.epochs
    optimizer = torch.optim.Adam(model.parameters(), lr=train_cfg.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, total_steps))
    start = time.perf_counter()
    history: list[dict[str, float]] = []
    bar = tqdm(total=total_steps, desc="train mnad", unit="step", disable=not progress)
    for epoch in range(train_cfg.epochs):
        order = order_rng.permutation(len(frames))
        sums = {"reconstruction": 0.0, "compactness": 0.0, "separateness": 0.0}
        for step in range(steps_per_epoch):
            batch = data[torch.from_numpy(order[step * batch_size : (step + 1) * batch_size])]
            out = model(batch)
            loss, parts = model.loss(batch, out)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
            model.update_memory(out.query)
            for key, value in parts.items():
                sums[key] += value
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, rec=f"{parts['reconstruction']:.4f}")
        history.append({key: value / steps_per_epoch for key, value in sums.items()})
        log.info("epoch %d/%d: %s", epoch + 1, train_cfg.epochs, history[-1])
    bar.close()
    record = {
        "training": {
            **asdict(train_cfg),
            "frames": int(len(frames)),
            "steps": total_steps,
            "seconds": round(time.perf_counter() - start, 1),
            "threads": torch.get_num_threads(),
            "losses_per_epoch": history,
        }
    }
    return model.eval(), record


def load_normal_frames(data: Path, cfg: MnadConfig, max_frames: int) -> np.ndarray:
    """(N, h, w, 3) uint8 camera frames of the normal drives (DATA/normal when present), resized to
    the model size and spread evenly over all drives. Label files are never opened."""
    from umad_common.datasets.anovox import find_scenarios, label_free_scenario, normal_root

    root = normal_root(Path(data))
    scenarios = [label_free_scenario(path, keep=("rgb",)) for path in find_scenarios(root)]
    if not scenarios:
        raise FileNotFoundError(f"{root}: no Scenario_* folders with normal drives found")
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
