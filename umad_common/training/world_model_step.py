"""One training step of the world model: the recipe (`TrainConfig`), the losses and the open-loop
rollouts they score, as one module (`TrainingStep`) that DistributedDataParallel can wrap.

The model filters a batch of windows with its posterior, rolls its prior open loop from some of
those states (`open_loop_predictions`), and is scored on the reconstructions and the predictions
(`world_model_loss`: L1 + SSIM and a balanced, free-nats KL; with a lidar head `lidar_terms`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from umad_common.models.world_model import ImagineResult, Observation, ObserveResult, State, WorldModel


@dataclass
class TrainConfig:
    """The training recipe: windows, optimizer, losses and augmentations (recorded with the weights)."""

    sequence_length: int = 8  # model steps per training window
    batch_size: int = 4  # windows per optimizer step
    learning_rate: float = 1e-3  # Adam, cosine-decayed to 10 % over all steps
    grad_clip: float = 100.0
    kl_weight: float = 1e-6  # per nat of KL(posterior || prior) summed over the latent map, against the
    #   per-pixel mean absolute error
    kl_balance: float = 0.8  # share of the KL gradient that trains the prior (DreamerV2 balancing)
    free_nats: float = 0.02  # KL per latent value (nats) below which it is not penalised
    sample_posterior: bool = False  # decode a sample of the posterior in training (as Dreamer) instead of
    #   its mean; the mean trains faster and sharper, the KL still prices every nat it moves from the prior
    prediction_steps: int = 3  # open-loop prior rollout per window, ending at its last frame, whose decoded
    #   frames are trained like reconstructions (the predictions x̂_{t|t-k} the temporal map compares)
    prediction_starts: int = 1  # rollouts per window, from consecutive posterior states: the last
    #   `prediction_starts` states that leave `prediction_steps` frames after them
    prediction_weight: float = 1.0  # weight of that prediction loss next to the reconstruction loss
    ssim_weight: float = 0.2  # weight of the 1 - SSIM loss (structure: edges, texture) next to the L1
    holdout: int = 1  # last normal drives (sorted) kept out of training for evaluation
    mirror: float = 0.0  # share of training windows mirrored left to right (camera, lidar, route and
    #   steering together): a drive the model never saw, at no cost in training time
    lidar_weight: float = 1.0  # weight of the lidar view's loss (mean |log range error| over the returns, in
    #   reconstructions and predictions) next to the image's; models without a lidar head ignore it
    relight: float = 0.0  # share of training windows re-lit: one random gamma, brightness and colour cast
    #   over all the window's frames (`relight_window`), for light the normal drives show rarely or never
    bf16: bool = True  # bfloat16 autocast and channels-last convolutions (faster on CPUs with AVX-512
    #   BF16, docs/experiments.md; float32 where the CPU has no bfloat16); the loss stays float32

    def __post_init__(self) -> None:
        if not 1 <= self.prediction_steps < self.sequence_length:
            raise ValueError(
                f"prediction_steps {self.prediction_steps} must be at least 1 and below sequence_length "
                f"{self.sequence_length} (the rollout starts from a posterior state inside the window)"
            )
        if not 0.0 <= self.mirror <= 1.0:
            raise ValueError(f"mirror {self.mirror} must be a share of the windows, between 0 and 1")
        if not 0.0 <= self.relight <= 1.0:
            raise ValueError(f"relight {self.relight} must be a share of the windows, between 0 and 1")
        if not 1 <= self.prediction_starts <= self.sequence_length - self.prediction_steps:
            raise ValueError(
                f"prediction_starts {self.prediction_starts} must be between 1 and sequence_length - prediction_steps "
                f"= {self.sequence_length - self.prediction_steps} (each rollout starts from a posterior state "
                "that leaves prediction_steps frames after it)"
            )


def gaussian_kl(mean_q, std_q, mean_p, std_p) -> torch.Tensor:
    """KL(q || p) of diagonal Gaussians, summed over the last axis."""
    return (torch.log(std_p / std_q) + (std_q**2 + (mean_q - mean_p) ** 2) / (2 * std_p**2) - 0.5).sum(-1)


def ssim_loss(a: torch.Tensor, b: torch.Tensor, sigma: float = 1.5, radius: int = 5) -> torch.Tensor:
    """Mean 1 - SSIM of two (N, 3, H, W) batches in [0, 1], Gaussian window, per channel."""
    x = torch.arange(-radius, radius + 1, dtype=a.dtype, device=a.device)
    kernel = torch.exp(-(x**2) / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    channels = a.shape[1]
    kx = kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    ky = kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:
        t = F.conv2d(F.pad(t, (radius, radius, 0, 0), mode="reflect"), kx, groups=channels)
        return F.conv2d(F.pad(t, (0, 0, radius, radius), mode="reflect"), ky, groups=channels)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    k1, k2 = 0.01**2, 0.03**2
    ssim = ((2 * mu_a * mu_b + k1) * (2 * cov + k2)) / ((mu_a**2 + mu_b**2 + k1) * (var_a + var_b + k2))
    return 1 - ssim.mean()


def image_loss(predicted: torch.Tensor, target: torch.Tensor, train: TrainConfig) -> tuple[torch.Tensor, ...]:
    """L1 + ssim_weight x (1 - SSIM) of (B, T, 3, H, W) images, computed in float32; also the two
    terms and the (detached) MSE."""
    predicted = predicted.float()
    error = predicted - target
    l1 = error.abs().mean()
    ssim = ssim_loss(predicted.flatten(0, 1), target.flatten(0, 1))
    return l1 + train.ssim_weight * ssim, l1, ssim, error.detach().pow(2).mean()


def world_model_loss(
    result: ObserveResult, predicted: torch.Tensor, obs: Observation, train: TrainConfig
) -> dict[str, torch.Tensor]:
    """Image reconstruction (L1 + SSIM), the same on the open-loop predictions, plus balanced,
    free-nats KL; returns every term.

    The L1 is the same per-pixel |x - x̂| the absolute difference map measures: it keeps lane marks
    sharp instead of averaging them away; the SSIM term asks for the local structure (edges,
    texture) the SSIM map compares. `predicted` (B, starts x steps, 3, H, W) are frames of the window
    as the prior drew them from earlier posterior states (`open_loop_predictions`): without this term only the
    KL teaches the prior, and the posterior can make it cheap by widening both distributions. The KL
    is summed over the latent map, so the posterior pays for every cell where it departs from what
    the prior expected. The MSE is reported for the PSNR."""
    recon, rgb_l1, rgb_ssim, rgb_mse = image_loss(result.rgb, obs.rgb, train)
    terms = {"rgb_l1": rgb_l1, "rgb_ssim": rgb_ssim, "rgb_mse": rgb_mse}
    prediction, _, _, pred_mse = image_loss(predicted, prediction_targets(obs.rgb, train), train)
    terms["pred_mse"] = pred_mse
    post = (result.post_mean.float(), result.post_std.float())
    prior = (result.prior_mean.float(), result.prior_std.float())
    kl_prior = gaussian_kl(*(t.detach() for t in post), *prior).mean()
    kl_post = gaussian_kl(*post, *(t.detach() for t in prior)).mean()
    kl = train.kl_balance * kl_prior + (1 - train.kl_balance) * kl_post
    free = train.free_nats * post[0].shape[-1]
    terms["kl"] = kl_prior.detach()
    terms["loss"] = recon + train.prediction_weight * prediction + train.kl_weight * torch.clamp(kl, min=free)
    return terms


def lidar_view_loss(log_range: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
    """Mean |log r̂ - log r| (about the relative range error) over the view pixels a return landed in;
    (N, rows, columns) each, `view` in metres with 0 where there is no return."""
    hit = view > 0
    if not hit.any():
        return log_range.float().sum() * 0.0
    return (log_range.float()[hit] - torch.log(view[hit])).abs().mean()


def lidar_terms(
    model: WorldModel, result: ObserveResult, predicted: ImagineResult, views: torch.Tensor, train: TrainConfig
) -> dict[str, torch.Tensor]:
    """The lidar view's loss of the reconstructions and the open-loop predictions (`lidar_view_loss`),
    and both weighted by `lidar_weight` as `lidar_loss`."""
    b, t = views.shape[:2]
    states = result.states
    recon = model.decode_lidar_log(State(states.h.flatten(0, 1), states.z.flatten(0, 1)))
    recon_l1 = lidar_view_loss(recon, views.flatten(0, 1))
    imagined = predicted.states
    pred = model.decode_lidar_log(State(imagined.h.flatten(0, 1), imagined.z.flatten(0, 1)))
    pred_l1 = lidar_view_loss(pred, prediction_targets(views, train).flatten(0, 1))
    return {
        "lidar_l1": recon_l1.detach(),
        "pred_lidar_l1": pred_l1.detach(),
        "lidar_loss": train.lidar_weight * (recon_l1 + train.prediction_weight * pred_l1),
    }


def rollout_starts(length: int, train: TrainConfig) -> range:
    """Window indices of the posterior states the open-loop rollouts start from."""
    first = length - train.prediction_steps - train.prediction_starts
    return range(first, first + train.prediction_starts)


def open_loop_predictions(
    model: WorldModel,
    result: ObserveResult,
    prev_actions: torch.Tensor,
    speed: torch.Tensor,
    train: TrainConfig,
    images: bool = True,
) -> ImagineResult:
    """The prior rolled `prediction_steps` steps from each start state (`rollout_starts`) with the
    actions taken and the speed (B, T, 1) of the start frame, all rollouts in one batch: the frames
    (B, starts x steps, 3, H, W), start by start, and the states (B x starts, steps, .)."""
    starts = rollout_starts(result.states.h.shape[1], train)
    steps = train.prediction_steps
    h = torch.stack([result.states.h[:, s] for s in starts], 1).flatten(0, 1)  # (B * starts, deter_dim)
    z = torch.stack([result.states.z[:, s] for s in starts], 1).flatten(0, 1)
    actions = torch.stack([prev_actions[:, s + 1 : s + 1 + steps] for s in starts], 1).flatten(0, 1)
    start_speed = torch.stack([speed[:, s, 0] for s in starts], 1).flatten()
    imagined = model.imagine(State(h, z), actions, speed=start_speed, images=images)  # (B * starts, steps, ...)
    if not images:
        return imagined
    rgb = imagined.rgb.view(prev_actions.shape[0], len(starts) * steps, *imagined.rgb.shape[2:])
    return ImagineResult(imagined.states, rgb)


def prediction_targets(frames: torch.Tensor, train: TrainConfig) -> torch.Tensor:
    """The frames `open_loop_predictions` predicts, in its order, from (B, T, ...) (images or lidar views)."""
    steps = train.prediction_steps
    return torch.cat([frames[:, s + 1 : s + 1 + steps] for s in rollout_starts(frames.shape[1], train)], 1)


def psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


class TrainingStep(torch.nn.Module):
    """The forward pass of one training step as one module: the model filters the windows, rolls
    its prior open loop and is scored (`world_model_loss`, and `lidar_terms` with a lidar head).
    DistributedDataParallel hooks a module's `forward`, so wrapping this (not the model, whose
    `observe` and `imagine` are not its forward) averages the gradients of the whole step."""

    def __init__(self, model: WorldModel, train: TrainConfig, bf16: bool):
        super().__init__()
        self.model = model
        self.train_config = train
        self.bf16 = bf16

    def forward(self, obs: Observation, prev_actions: torch.Tensor, views: torch.Tensor | None) -> dict:
        """Every loss term of the windows; "loss" is the one to minimise."""
        model, train = self.model, self.train_config
        with torch.autocast(obs.rgb.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            result = model.observe(obs, prev_actions, sample=train.sample_posterior)
            predicted = open_loop_predictions(model, result, prev_actions, obs.speed, train)
            lidar_part = lidar_terms(model, result, predicted, views, train) if views is not None else {}
        terms = world_model_loss(result, predicted.rgb, obs, train)
        if lidar_part:
            terms.update(lidar_part)
            terms["loss"] = terms["loss"] + terms.pop("lidar_loss")
        return terms
