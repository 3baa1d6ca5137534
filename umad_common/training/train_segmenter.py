"""Training the label-free segment net (umad_common.models.segment_net): per-pixel clusters learned
on normal drives, no labels.

Each step takes a batch of normal frames and makes two views of it: view 1 is the whole frame under
photometric jitter (blur, colour, noise: `train_features.photometric_view`), view 2 a random crop
of it, rescaled, maybe mirrored, under other jitter. The net's embeddings of view 1, cut and
resampled to view 2's crop, line up pixel by pixel with view 2's (mirrored back). At sampled pixels,
each view's balanced cluster assignment (Sinkhorn-Knopp over the prototypes, so no cluster takes
every pixel) is the target the other view's prototype scores must predict (SwAV's swapped
prediction, per pixel): clusters become invariant to colour and blur and equivariant to crops,
scale and flips, which is the PiCIE recipe with online prototypes instead of per-epoch k-means.

Only RGB of NORMAL drives is read (DATA/normal when present), never labels.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from umad_common.models.segment_net import SegmentNet, SegmentNetConfig
from umad_common.training.train_features import photometric_view

log = logging.getLogger("umad.train.segmenter")


@dataclass
class SegmenterTrainingConfig:
    epochs: int = 4  # passes over the loaded frames
    seed: int = 0
    size: tuple[int, int] = (128, 192)  # (h, w): the world model's image size, plain resize
    view: tuple[int, int] = (96, 128)  # (h, w) of the second view (the crop, rescaled)
    crop_scale: tuple[float, float] = (0.5, 1.0)  # crop side as a fraction of the frame's, uniform
    batch_size: int = 8
    max_frames: int = 1200  # frames loaded, spread evenly over the normal scenarios
    holdout: int = 1  # last normal drives (sorted) left out, as the world model does
    lr: float = 2e-3
    pixels: int = 4096  # aligned pixel positions sampled per step for the loss
    temperature: float = 0.1  # of the prototype scores' softmax
    sinkhorn_epsilon: float = 0.05  # sharpness of the balanced targets
    sinkhorn_iterations: int = 3

    def __post_init__(self) -> None:
        self.size, self.view = tuple(self.size), tuple(self.view)
        self.crop_scale = tuple(self.crop_scale)
        if any(v % 2 for v in (*self.size, *self.view)):
            raise ValueError(f"size {self.size} and view {self.view} must be even (embeddings at half size)")
        if not 0 < self.crop_scale[0] <= self.crop_scale[1] <= 1:
            raise ValueError(f"crop_scale {self.crop_scale}: expected 0 < low <= high <= 1")
        if self.epochs < 1 or self.batch_size < 1 or self.max_frames < 1 or self.holdout < 0:
            raise ValueError("epochs, batch_size and max_frames must be >= 1, holdout >= 0")


@torch.no_grad()
def sinkhorn(scores: torch.Tensor, epsilon: float, iterations: int) -> torch.Tensor:
    """(N, K) scores -> (N, K) soft assignments, each row summing to 1, each cluster taking about
    N/K of the mass (Sinkhorn-Knopp, as in SwAV)."""
    q = torch.exp((scores - scores.max()) / epsilon).T  # (K, N)
    q /= q.sum()
    clusters, n = q.shape
    for _ in range(iterations):
        q /= q.sum(dim=1, keepdim=True) * clusters
        q /= q.sum(dim=0, keepdim=True) * n
    return (q * n).T


def swapped_prediction_loss(
    model: SegmentNet, z1: torch.Tensor, z2: torch.Tensor, cfg: SegmenterTrainingConfig
) -> torch.Tensor:
    """SwAV's loss on (N, D) aligned embeddings of two views: each view's scores predict the
    other's balanced assignment."""
    s1, s2 = model.scores(z1), model.scores(z2)  # (N, K)
    q1 = sinkhorn(s1, cfg.sinkhorn_epsilon, cfg.sinkhorn_iterations)
    q2 = sinkhorn(s2, cfg.sinkhorn_epsilon, cfg.sinkhorn_iterations)
    p1 = F.log_softmax(s1 / cfg.temperature, dim=1)
    p2 = F.log_softmax(s2 / cfg.temperature, dim=1)
    return -0.5 * ((q2 * p1).sum(dim=1).mean() + (q1 * p2).sum(dim=1).mean())


def aligned_views(
    model: SegmentNet, batch: torch.Tensor, cfg: SegmenterTrainingConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, D) embeddings of the same scene points in two views of (B, 3, h, w) frames."""
    h, w = batch.shape[2:]
    scale = cfg.crop_scale[0] + (cfg.crop_scale[1] - cfg.crop_scale[0]) * float(torch.rand(1, generator=gen))
    ch, cw = 2 * round(h * scale / 2), 2 * round(w * scale / 2)  # even: the crop maps onto whole embedding cells
    top = 2 * int(torch.randint(0, (h - ch) // 2 + 1, (1,), generator=gen))
    left = 2 * int(torch.randint(0, (w - cw) // 2 + 1, (1,), generator=gen))
    mirror = bool(torch.rand(1, generator=gen) < 0.5)
    crop = batch[:, :, top : top + ch, left : left + cw]
    crop = F.interpolate(crop, size=cfg.view, mode="bilinear", align_corners=False, antialias=True)
    if mirror:
        crop = crop.flip(dims=(3,))
    e1 = model(photometric_view(batch, gen))[:, :, top // 2 : (top + ch) // 2, left // 2 : (left + cw) // 2]
    e2 = model(photometric_view(crop, gen))  # (B, D, view/2)
    if mirror:
        e2 = e2.flip(dims=(3,))
    e1 = F.normalize(F.interpolate(e1, size=e2.shape[2:], mode="bilinear", align_corners=False), dim=1)
    z1, z2 = e1.permute(0, 2, 3, 1).flatten(0, 2), e2.permute(0, 2, 3, 1).flatten(0, 2)  # (B*h'*w', D)
    pick = torch.randperm(z1.shape[0], generator=gen)[: cfg.pixels]
    return z1[pick], z2[pick]


def train_segment_net(
    frames: np.ndarray,
    cfg: SegmenterTrainingConfig,
    model_cfg: SegmentNetConfig | None = None,
    device: str | torch.device = "cpu",
) -> tuple[SegmentNet, dict]:
    """Train on (N, h, w, 3) uint8 normal frames on `device`; on the CPU deterministic for a given seed
    and thread count (a GPU lacks deterministic kernels for some steps: close, not equal).

    Returns the net on the CPU in eval mode and its training record (loss and seconds per epoch,
    total seconds, the device, the machine's load average while it ran)."""
    if frames.ndim != 4 or frames.shape[1:] != (*cfg.size, 3) or frames.dtype != np.uint8:
        raise ValueError(
            f"train_segment_net: expected (N, {cfg.size[0]}, {cfg.size[1]}, 3) uint8, got {frames.dtype} {frames.shape}"
        )
    device = torch.device(device)
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    try:
        return _train(frames, cfg, model_cfg or SegmentNetConfig(), device)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)


def _train(
    frames: np.ndarray, cfg: SegmenterTrainingConfig, model_cfg: SegmentNetConfig, device: torch.device
) -> tuple[SegmentNet, dict]:
    from tqdm import tqdm

    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    images = torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()  # (N, 3, h, w) uint8
    pixels = images.float().div_(255.0)
    model_cfg.mean = tuple(float(v) for v in pixels.mean(dim=(0, 2, 3)))
    model_cfg.std = tuple(float(v) for v in pixels.std(dim=(0, 2, 3)))
    del pixels
    model = SegmentNet(model_cfg).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    steps_per_epoch = max(1, len(images) // cfg.batch_size)
    steps = cfg.epochs * steps_per_epoch
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=cfg.lr, total_steps=steps, pct_start=0.1)
    history, load = [], [os.getloadavg()[0]]
    started = time.monotonic()
    progress = tqdm(total=steps, desc="train segmenter", unit="step")
    for epoch in range(cfg.epochs):
        epoch_start, losses = time.monotonic(), []
        order = torch.randperm(len(images), generator=gen)
        for step in range(steps_per_epoch):
            batch = (images[order[step * cfg.batch_size : (step + 1) * cfg.batch_size]].float() / 255.0).to(device)
            loss = swapped_prediction_loss(model, *aligned_views(model, batch, cfg, gen), cfg)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
            with torch.no_grad():
                model.prototypes.copy_(F.normalize(model.prototypes, dim=1))
            losses.append(loss.item())
            progress.update(1)
            progress.set_postfix(loss=f"{loss.item():.3f}")
        load.append(os.getloadavg()[0])
        history.append(
            {
                "epoch": epoch + 1,
                "loss": round(float(np.mean(losses)), 5),
                "seconds": round(time.monotonic() - epoch_start, 1),
            }
        )
    progress.close()
    record = {
        "objective": "per-pixel swapped prediction of balanced prototype assignments between a jittered frame and "
        "a jittered, rescaled, mirrored crop of it (SwAV per pixel, PiCIE's invariance and equivariance)",
        "train_config": asdict(cfg),
        "frames": int(len(images)),
        "steps": steps,
        "history": history,
        "seconds": round(time.monotonic() - started, 1),
        "threads": torch.get_num_threads(),
        "device": str(device),
        "load_average_1min": [round(v, 2) for v in load],
    }
    return model.cpu().eval().requires_grad_(False), record
