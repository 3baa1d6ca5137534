"""Training the label-free feature net (umad_common.models.feature_net) with dense VICReg.

Why this objective: Δ_PD should ignore what a world model gets wrong on normal scenes (blur, small
colour shifts, noise on fine texture: the error that swamps pixel metrics on windows, foliage and
lane edges) and respond to content it never saw. Two views of one normal frame share geometry but
differ photometrically; the loss asks their features to agree pixel by pixel (invariance), to
vary across pixels and frames (variance) and to use decorrelated channels (covariance), which
rules out collapse without labels, negatives, momentum encoders or big batches. An autoencoder's
encoder would instead keep exactly the high-frequency detail that makes pixel errors noisy.

Only RGB of NORMAL drives is read (DATA/normal when present), never labels.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from umad_common.models.feature_net import FeatureNet, FeatureNetConfig

log = logging.getLogger("umad.train.features")


@dataclass
class FeatureTrainingConfig:
    epochs: int = 4  # passes over the loaded frames
    seed: int = 0
    size: tuple[int, int] = (128, 192)  # (h, w): the world model's image size, plain resize
    crop: tuple[int, int] = (96, 128)  # (h, w) random crop, the same for both views
    batch_size: int = 12
    max_frames: int = 1200  # frames loaded, spread evenly over the normal scenarios
    holdout: int = 1  # last normal drives (sorted) left out, as the world model does, for calibration
    lr: float = 2e-3
    pixels_per_level: int = 2048  # feature positions sampled per level for the loss
    invariance_weight: float = 25.0  # VICReg's defaults
    variance_weight: float = 25.0
    covariance_weight: float = 1.0


def load_normal_rgb(data: Path, cfg: FeatureTrainingConfig, topics: str | None = None) -> tuple[np.ndarray, list[str]]:
    """(N, h, w, 3) uint8 camera frames of the normal training drives, resized to `cfg.size` and
    spread evenly over them (at most `cfg.max_frames`, the last `cfg.holdout` drives left out), and
    the names of the held-out drives. The segment net's training config has the same three fields.
    `topics`: a recording's topic per role (`umad_common.datasets.topics`)."""
    from umad_common.datasets.formats import normal_root, training_drives

    root = normal_root(data)
    drives = training_drives(data, topics, keep=("rgb",))
    keep = len(drives) - min(cfg.holdout, len(drives) - 1)
    scenarios = drives[:keep]
    size, max_frames = cfg.size, cfg.max_frames
    total = sum(len(s) for s in scenarios)
    stride = max(1, int(np.ceil(total / max_frames)))
    frames = []
    for scenario in scenarios:
        for index in range(0, len(scenario), stride):
            rgb = scenario[index].rgb
            frames.append(cv2.resize(rgb, (size[1], size[0]), interpolation=cv2.INTER_AREA))
    log.info(
        "loaded %d normal frames (every %d of %d) from %d training drives in %s",
        len(frames),
        stride,
        total,
        len(scenarios),
        root,
    )
    return np.stack(frames), [d.name for d in drives[keep:]]


def gaussian_blur(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Blur each image of (B, 3, h, w) with its own sigma (B,); sigma 0 leaves it unchanged."""
    radius = 4
    taps = torch.arange(-radius, radius + 1, dtype=x.dtype, device=x.device)
    kernel = torch.exp(-0.5 * (taps[None] / sigma.clamp_min(1e-3)[:, None]) ** 2)  # (B, 9)
    kernel = kernel / kernel.sum(dim=1, keepdim=True)
    b, c, h, w = x.shape
    planes = x.reshape(1, b * c, h, w)
    k = kernel.repeat_interleave(c, dim=0)  # (B*3, 9)
    planes = F.conv2d(F.pad(planes, (radius, radius, 0, 0), mode="replicate"), k.view(b * c, 1, 1, -1), groups=b * c)
    planes = F.conv2d(F.pad(planes, (0, 0, radius, radius), mode="replicate"), k.view(b * c, 1, -1, 1), groups=b * c)
    return planes.view(b, c, h, w)


def photometric_view(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """A view that differs the way a reconstruction does: blur, colour jitter, noise. (B,3,h,w).
    The random numbers come from `gen` on the CPU, whatever device `x` is on."""
    b = x.shape[0]

    def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
        return (lo + (hi - lo) * torch.rand(b, *shape, generator=gen)).to(x.device)

    x = gaussian_blur(x, uniform(0.0, 1.6))
    gray = x.mean(dim=1, keepdim=True)
    x = gray + (x - gray) * uniform(0.75, 1.25, 1, 1, 1)  # saturation
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = mean + (x - mean) * uniform(0.8, 1.2, 1, 1, 1) + uniform(-0.08, 0.08, 1, 1, 1)  # contrast, brightness
    x = x * uniform(0.95, 1.05, 3, 1, 1)  # white balance
    x = x + torch.randn(x.shape, generator=gen).to(x.device) * uniform(0.0, 0.03, 1, 1, 1)
    return x.clamp(0.0, 1.0)


def vicreg_terms(z1: torch.Tensor, z2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Invariance, variance and covariance terms for two (N, D) sets of paired embeddings."""
    invariance = F.mse_loss(z1, z2)
    variance = z1.new_zeros(())
    covariance = z1.new_zeros(())
    for z in (z1, z2):
        z = z - z.mean(dim=0)
        variance = variance + F.relu(1.0 - torch.sqrt(z.var(dim=0) + 1e-4)).mean() / 2
        cov = (z.T @ z) / (z.shape[0] - 1)
        off_diagonal = cov - torch.diag(torch.diag(cov))
        covariance = covariance + off_diagonal.pow(2).sum() / z.shape[1] / 2
    return invariance, variance, covariance


def dense_vicreg_loss(
    levels1: list[torch.Tensor],
    levels2: list[torch.Tensor],
    cfg: FeatureTrainingConfig,
    gen: torch.Generator,
) -> torch.Tensor:
    """Mean over the four levels of VICReg on the same sampled pixel positions of both views.

    The loss acts on the very features Δ_PD compares, with no projector in between: a projector
    absorbs the invariance and leaves the backbone sensitive to blur (on a blur + inpainting proxy
    of reconstructions the finest level's anomaly AP collapsed with VICReg's projector:
    docs/experiments.md).
    """
    total = levels1[0].new_zeros(())
    for f1, f2 in zip(levels1, levels2, strict=True):
        v1 = f1.permute(0, 2, 3, 1).flatten(0, 2)  # (B*h*w, C)
        v2 = f2.permute(0, 2, 3, 1).flatten(0, 2)
        pick = torch.randperm(v1.shape[0], generator=gen)[: cfg.pixels_per_level]
        inv, var, cov = vicreg_terms(v1[pick], v2[pick])
        total = total + cfg.invariance_weight * inv + cfg.variance_weight * var + cfg.covariance_weight * cov
    return total / len(levels1)


def train_feature_net(
    frames: np.ndarray,
    cfg: FeatureTrainingConfig,
    data_name: str = "",
    heldout: list[str] | None = None,
    device: str | torch.device = "cpu",
) -> tuple[FeatureNet, dict]:
    """Train on (N, h, w, 3) uint8 normal frames on `device`; on the CPU deterministic for a given seed
    and thread count (a GPU lacks deterministic kernels for some steps: close, not equal). Returns the
    model on the CPU and its record (`{"training": {...}}`, for `save_feature_net`)."""
    device = torch.device(device)
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    try:
        return _train(frames, cfg, data_name, heldout or [], device)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)


def _train(
    frames: np.ndarray, cfg: FeatureTrainingConfig, data_name: str, heldout: list[str], device: torch.device
) -> tuple[FeatureNet, dict]:
    from tqdm import tqdm

    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    images = torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()  # (N, 3, h, w) uint8
    pixels = images.float().div_(255.0)
    mean = tuple(float(v) for v in pixels.mean(dim=(0, 2, 3)))
    std = tuple(float(v) for v in pixels.std(dim=(0, 2, 3)))
    del pixels
    model = FeatureNet(FeatureNetConfig(mean=mean, std=std)).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    steps_per_epoch = max(1, len(images) // cfg.batch_size)
    steps = cfg.epochs * steps_per_epoch
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=cfg.lr, total_steps=steps, pct_start=0.1)
    (ch, cw), (h, w) = cfg.crop, images.shape[2:]
    started = time.monotonic()
    progress = tqdm(total=steps, desc="train features", unit="step")
    for _ in range(cfg.epochs):
        order = torch.randperm(len(images), generator=gen)
        for step in range(steps_per_epoch):
            index = order[step * cfg.batch_size : (step + 1) * cfg.batch_size]
            top = int(torch.randint(0, h - ch + 1, (1,), generator=gen))
            left = int(torch.randint(0, w - cw + 1, (1,), generator=gen))
            batch = images[index, :, top : top + ch, left : left + cw].float() / 255.0
            if bool(torch.rand(1, generator=gen) < 0.5):
                batch = batch.flip(dims=(3,))
            batch = batch.to(device)
            loss = dense_vicreg_loss(model(photometric_view(batch, gen)), model(photometric_view(batch, gen)), cfg, gen)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
            progress.update(1)
            progress.set_postfix(loss=f"{loss.item():.3f}")
    progress.close()
    training = {
        "objective": "dense VICReg on the feature levels of two photometric views (blur, colour, noise)",
        "data": data_name,
        "heldout_drives": heldout,
        "frames": int(len(images)),
        "size": list(cfg.size),
        "crop": list(cfg.crop),
        "epochs": cfg.epochs,
        "steps": steps,
        "batch_size": cfg.batch_size,
        "seed": cfg.seed,
        "final_loss": round(float(loss.item()), 5),
        "seconds": round(time.monotonic() - started, 1),
        "threads": torch.get_num_threads(),
        "device": str(device),
    }
    return model.cpu().eval().requires_grad_(False), {"training": training}
