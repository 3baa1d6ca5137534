"""Training the world model on normal drives: data cache, loss, loop, checkpoints.

Only normal drives are read (DATA/normal if it exists, else DATA), and of each frame only the
model's inputs: camera, lidar, ego and route; never a label. Every frame is resized once into
memory, then each epoch cuts every drive into windows of `sequence_length` model steps at a seeded
random offset and visits them in a seeded order. Each epoch ends with a checkpoint
(MODEL.train.pt: model, optimizer, epoch, history; read back with `torch.load(weights_only=True)`)
and the weights (MODEL.safetensors + MODEL.json), so `--resume` continues where training stopped and
gives the same weights as an uninterrupted run with the same seed, thread count and --epochs.

Across processes (`umad_common.training.distributed`), each rank computes the losses of its share of
every step's windows (`TrainingStep`, wrapped in DistributedDataParallel, which averages the
gradients); every rank draws the same window order and augmentations, so a step trains the same
windows whatever the number of processes, and rank 0 writes the files.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from umad_common.datasets.drive import Drive, training_drives
from umad_common.datasets.sensor_rig import SensorRig
from umad_common.models.device import bf16_supported
from umad_common.models.weights import weight_paths
from umad_common.models.world_model import (
    ImagineResult,
    Observation,
    ObserveResult,
    State,
    WorldModel,
    WorldModelConfig,
    action_of,
    lidar_range_image,
    lidar_returns,
    lidar_view,
    resize_rgb,
    resize_route,
    save_world_model,
)
from umad_common.training.distributed import Rank

log = logging.getLogger("umad.train.world_model")


@dataclass
class TrainConfig:
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
    bf16: bool = True  # bfloat16 autocast and channels-last convolutions (2-3x faster on CPUs with
    #   AVX-512 BF16; training falls back to float32 where the CPU has none); the loss stays float32

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


@dataclass
class DriveArrays:
    """One drive, resized to model size and kept in memory."""

    name: str
    rgb: np.ndarray  # (T, H, W, 3) uint8
    lidar: np.ndarray  # (T, 4, rows, width) float16 range view
    route: np.ndarray  # (T, R, R) uint8
    speed: np.ndarray  # (T,) float32 m/s
    action: np.ndarray  # (T, 2) float32 [throttle - brake, steer] taken after frame t
    view: np.ndarray | None = None  # (T, rows, columns) float16 lidar view, metres (0: no return); None
    #   for a model without a lidar head

    def __len__(self) -> int:
        return len(self.rgb)


def load_drive(scenario: Drive, config: WorldModelConfig) -> DriveArrays:
    """Read a scenario's model inputs (camera, lidar, ego, route) at model size, and with a lidar head
    the lidar view its loss compares (projected with the drive's sensor setup, AnoVox's without one)."""
    rig = SensorRig.from_sensors(scenario.sensors, scenario.name) if scenario.sensors else SensorRig.anovox()
    rgb, lidar, route, speed, action, view = [], [], [], [], [], []
    for i in range(len(scenario)):
        frame = scenario[i]
        rgb.append(resize_rgb(frame.rgb, config))
        lidar.append(lidar_range_image(frame.lidar, config).astype(np.float16))
        if config.lidar_head:
            view.append(lidar_view(lidar_returns(frame.lidar, config, rig), config).astype(np.float16))
        route.append(resize_route(frame.route, config))
        speed.append(frame.ego.speed_mps)
        action.append(action_of(frame.ego.throttle, frame.ego.brake, frame.ego.steer))
    return DriveArrays(
        scenario.name,
        np.stack(rgb),
        np.stack(lidar),
        np.stack(route),
        np.array(speed, np.float32),
        np.stack(action),
        np.stack(view) if view else None,
    )


def load_normal_drives(
    data: Path, config: WorldModelConfig, holdout: int, progress: bool = True, topics: str | None = None
) -> tuple[list[DriveArrays], list[str]]:
    """All normal drives under DATA except the last `holdout`; returns (drives, held-out names).
    `topics`: a recording's topic per role (`umad_common.datasets.topics`)."""
    normal = training_drives(data, topics, config.frame_step)
    holdout = min(holdout, len(normal) - 1)
    train_drives, held = normal[: len(normal) - holdout], normal[len(normal) - holdout :]
    drives = []
    for drive in tqdm(train_drives, desc="loading drives", unit="drive", disable=not progress):
        drives.append(load_drive(drive, config))
    return drives, [d.name for d in held]


def observation_batch(
    drives: list[DriveArrays],
    windows: list[tuple[int, int]],
    length: int,
    mirrored: list[bool] | None = None,
    lights: list[Light | None] | None = None,
):
    """Windows (drive index, start) -> (Observation, prev_actions (B, L, 2)) tensors; `mirrored[i]`
    turns window i into its left-right mirror image (`mirror_window`), `lights[i]` re-lights it
    (`relight_window`)."""
    rgb, lidar, route, speed, prev = [], [], [], [], []
    for i, (d, start) in enumerate(windows):
        drive = drives[d]
        sl = slice(start, start + length)
        actions = np.zeros((length, 2), np.float32)
        actions[1:] = drive.action[start : start + length - 1]
        if start > 0:
            actions[0] = drive.action[start - 1]
        window = (drive.rgb[sl], drive.lidar[sl], drive.route[sl], actions)
        if mirrored is not None and mirrored[i]:
            window = mirror_window(*window)
        if lights is not None and lights[i] is not None:
            window = (relight_window(window[0], lights[i]), *window[1:])
        rgb.append(window[0])
        lidar.append(window[1])
        route.append(window[2])
        speed.append(drive.speed[sl])
        prev.append(window[3])
    obs = Observation(
        rgb=torch.from_numpy(np.stack(rgb)).permute(0, 1, 4, 2, 3).float().div_(255.0),
        lidar=torch.from_numpy(np.stack(lidar)).float(),
        route=torch.from_numpy(np.stack(route)).unsqueeze(2).float().div_(255.0),
        speed=torch.from_numpy(np.stack(speed)).unsqueeze(2),
    )
    return obs, torch.from_numpy(np.stack(prev))


def view_batch(
    drives: list[DriveArrays], windows: list[tuple[int, int]], length: int, mirrored: list[bool] | None = None
) -> torch.Tensor:
    """The lidar views of the windows, (B, L, rows, columns) float metres (0: no return), mirrored
    left to right where the window is (the view is the camera's frustum, so it flips with it)."""
    views = []
    for i, (d, start) in enumerate(windows):
        view = drives[d].view[start : start + length]
        views.append(view[..., ::-1] if mirrored is not None and mirrored[i] else view)
    return torch.from_numpy(np.ascontiguousarray(np.stack(views))).float()


def mirror_window(rgb: np.ndarray, lidar: np.ndarray, route: np.ndarray, actions: np.ndarray):
    """The same window driven in a mirrored world: the camera and the route map (heading up) flip
    left to right; the lidar range view's columns run over azimuth with forward at the centre, so
    they flip too and y (left) changes sign; the steering changes sign."""
    lidar = lidar[..., ::-1].copy()
    lidar[:, 1] *= -1
    actions = actions * np.array([1.0, -1.0], np.float32)
    return rgb[:, :, ::-1], lidar, route[:, :, ::-1], actions


@dataclass(frozen=True)
class Light:
    """One re-lighting of a window: x' = clip(gain_c * x ** gamma) on [0, 1] colour values."""

    gamma: float
    gain: tuple[float, float, float]

    @classmethod
    def draw(cls, rng: np.random.Generator) -> Light:
        """Gamma 0.6-1.6 (contrast of shadows and highlights), brightness x 0.5-1.6 and a colour cast
        of x 0.85-1.15 per channel, each log-uniform or uniform: from dusk to a harsh noon."""
        gamma = float(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))
        brightness = float(np.exp(rng.uniform(np.log(0.5), np.log(1.6))))
        cast = rng.uniform(0.85, 1.15, size=3)
        return cls(gamma, tuple(float(brightness * c) for c in cast))


def relight_window(rgb: np.ndarray, light: Light) -> np.ndarray:
    """(L, H, W, 3) uint8 frames of a window under `light` (the same for every frame, so the scene
    still moves as it did; only its light changes)."""
    lut = (np.arange(256, dtype=np.float32) / 255.0) ** light.gamma  # one table per channel
    tables = np.clip(lut[None, :] * np.array(light.gain, np.float32)[:, None], 0.0, 1.0)
    tables = (tables * 255.0 + 0.5).astype(np.uint8)  # (3, 256)
    return np.stack([tables[c][rgb[..., c]] for c in range(3)], axis=-1)


def scale_speed(obs: Observation, config: WorldModelConfig) -> Observation:
    return obs._replace(speed=obs.speed / config.speed_scale)


def epoch_windows(drives: list[DriveArrays], length: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Non-overlapping windows covering every drive from a random offset, in random order."""
    windows = []
    for d, drive in enumerate(drives):
        if len(drive) < length:
            continue
        offset = int(rng.integers(0, min(length, len(drive) - length + 1)))
        windows += [(d, s) for s in range(offset, len(drive) - length + 1, length)]
    order = rng.permutation(len(windows))
    return [windows[i] for i in order]


def guaranteed_windows(drives: list[DriveArrays], length: int) -> int:
    """How many windows `epoch_windows` yields at least, whatever the offsets drawn."""
    count = 0
    for drive in drives:
        if len(drive) >= length:
            worst_offset = min(length, len(drive) - length + 1) - 1
            count += (len(drive) - worst_offset - length) // length + 1
    return count


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
    from umad_common.models.world_model import load_world_model

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
