"""The UMAD world model: multimodal, action-conditioned latent dynamics on a spatial grid (RSSM).

Per model step t the camera image is encoded onto a coarse grid (image size / 4: 32 x 48 cells for
a 128 x 192 image); the lidar (as a 64 x W range image), the route map and the speed are encoded
into one vector that is broadcast onto the same grid. The recurrent state s_t = (h_t, z_t) lives on
that grid: a deterministic convolutional GRU map h_t and a stochastic Gaussian map z_t:

    h_t = ConvGRU(h_{t-1}, [z_{t-1}, a_{t-1}])  a = [throttle - brake, steer], the control after t-1
    predicting (imagine): the same on warp(h_{t-1}), warp(z_{t-1}); warp moves each cell as the scene moves
    prior      p(z_t | h_t)                     what the model expects without looking
    posterior  q(z_t | h_t, embed(o_t))         what it believes after looking
    decoder    (h_t, z_t) -> RGB image
    lidar head (h_t, z_t) -> the lidar view: the range of every pixel of the camera's frustum (optional)

A spatial state lets the model keep the layout of the scene it has seen (where the road, the
facades, the lane marks are) and move it with the car's motion, so the prior can predict frames
and the posterior needs only a few nats per cell to correct it. `observe` runs the posterior over a
sequence and reconstructs every frame; `imagine` rolls the prior forward with given actions and
decodes predicted frames. The image reaches the decoder only through the state (no skip connections
from encoder to decoder), and the posterior pays for every nat it moves away from the prior (the
KL term in training), so the model draws what normal driving taught it to expect: an object it
never saw is not reproduced, and that is the signal.

The preprocessing that defines the inputs (plain resize without crop, lidar range projection) lives
here too, so training, evaluation and the predictor operator feed the model identically.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from umad_common.datasets.sensor_rig import SensorRig
from umad_common.models.weights import config_from_dict, load_model, save_weights


@dataclass
class WorldModelConfig:
    image_height: int = 128  # camera resized (no crop) to image_height x image_width
    image_width: int = 192
    image_channels: tuple[int, ...] = (48, 96)  # encoder widths, one stride-2 stage each; the latent grid is
    #   image size / 2**len(image_channels) (32 x 48 by default: a 4 x 4 pixel cell keeps poles and lane
    #   marks; 8 x 8 cells, even with 2-4x the channels, drew them worse in the same time: docs/experiments.md)
    decoder_channels: tuple[int, ...] = (96, 48, 24)  # decoder widths: [0] on the grid, then one per
    #   x2 upsampling stage (len(image_channels) + 1 entries)
    res_blocks: int = 1  # residual 3x3 blocks on the grid, in the encoder and in the decoder
    lidar_rows: int = 64  # range image rows = lidar channels
    lidar_width: int = 128  # range image columns (360 degrees of azimuth)
    lidar_fov_up: float = 15.0  # degrees above the horizon covered by the top row
    lidar_fov_down: float = -25.0  # degrees of the bottom row
    lidar_scale: float = 50.0  # metres; the range image holds (x, y, z, range) / lidar_scale
    lidar_channels: tuple[int, ...] = (16, 32, 32, 64, 64)
    lidar_embed: int = 128
    route_size: int = 64  # route map resized to route_size x route_size
    route_channels: tuple[int, ...] = (16, 32, 32, 32)
    route_embed: int = 64
    speed_scale: float = 5.0  # speed input = speed_mps / speed_scale
    deter_channels: int = 32  # channels of the deterministic GRU map h: the memory of the drive so far
    stoch_channels: int = 8  # channels of the Gaussian map z: the only per-frame path from the image
    side_channels: int = 16  # lidar + route + speed embedding, broadcast onto the latent grid
    hidden_channels: int = 48  # width of the prior and posterior heads
    transition_kernel: int = 7  # kernel of the ConvGRU: how far (in cells) its update reaches per step
    max_shift: float = 4.0  # cells the motion warp may move a cell of the state per step; without the warp
    #   the 3-step predictions were worst at the image's sides (docs/experiments.md), where facades pass 2-3
    #   cells per step at 9 m/s, further than a convolution's reach
    motion_channels: int = 32  # width of the motion head that predicts the warp
    ground_flow: bool = False  # the warp starts from the flow a flat road makes under the camera at the
    #   current speed (below the horizon; `MotionWarp.ground_source`), and the head learns the rest: the
    #   learned warp alone moved the road near the car a fraction of the 1.5-4 cells per step it moves at
    #   9 m/s. Judged on validation seed 2 (docs/experiments.md: better 3-step predictions, no better AP with
    #   the full recipe); off until a model trained with it ships
    camera_fov: float = 90.0  # horizontal field of view (deg) of the camera, square pixels (AnoVox and the
    #   built-in world)
    camera_height: float = 1.8  # metres above the road (AnoVox and the built-in world)
    frame_rate: float = 10.0  # dataset frames per second (AnoVox: 10 Hz); a model step is frame_step frames
    min_std: float = 0.1  # floor of the latent standard deviation
    frame_step: int = 1  # dataset frames per model step the model was trained with
    lidar_head: bool = False  # decode the lidar as the camera sees it (`lidar_view`): the range of every pixel,
    #   reconstructed and predicted like the image, which the `lidar` difference compares with the returns
    #   (`umad train world-model --lidar-head` trains it with the model, `umad train lidar-head` adds one to a
    #   trained model; models saved before the head existed have none)
    lidar_view_scale: int = 2  # lidar view pixels per image pixel along each axis: at 2 (256 x 384 for the
    #   default 128 x 192 image, focal 192 px) a 0.5 m object at 25 m spans 3.8 x 3.8 view pixels
    lidar_decoder_channels: tuple[int, ...] = ()  # lidar decoder widths: [0] on the grid, then one per x2
    #   upsampling up to the image size (len(image_channels) + 1 entries; empty: 32 on the grid, halving from the
    #   second upsampling on, (32, 32, 16) by default); a last pixel shuffle reaches the view

    def __post_init__(self) -> None:
        for name in (
            "image_channels",
            "decoder_channels",
            "lidar_channels",
            "route_channels",
            "lidar_decoder_channels",
        ):
            setattr(self, name, tuple(int(c) for c in getattr(self, name)))
        factor = 2 ** len(self.image_channels)
        if self.image_height % factor or self.image_width % factor:
            raise ValueError(
                f"image size {self.image_height}x{self.image_width} must be divisible by {factor} "
                f"(2 ** len(image_channels))"
            )
        if len(self.decoder_channels) != len(self.image_channels) + 1:
            raise ValueError(
                f"decoder_channels {self.decoder_channels} has {len(self.decoder_channels)} entries; expected "
                f"len(image_channels) + 1 = {len(self.image_channels) + 1} (the grid, then one per upsampling)"
            )
        if not self.lidar_decoder_channels:
            self.lidar_decoder_channels = tuple(32 >> max(0, i - 1) for i in range(len(self.image_channels) + 1))
        if self.lidar_head and len(self.lidar_decoder_channels) != len(self.image_channels) + 1:
            raise ValueError(
                f"lidar_decoder_channels {self.lidar_decoder_channels} has {len(self.lidar_decoder_channels)} entries; "
                f"expected len(image_channels) + 1 = {len(self.image_channels) + 1} (the grid, then one per upsampling)"
            )
        if self.lidar_view_scale < 1:
            raise ValueError(
                f"lidar_view_scale {self.lidar_view_scale} must be at least 1 (view pixels per image pixel)"
            )
        lidar_factor = 2 ** len(self.lidar_channels)
        if self.lidar_rows % lidar_factor or self.lidar_width % lidar_factor:
            raise ValueError(
                f"lidar range image {self.lidar_rows}x{self.lidar_width} must be divisible by {lidar_factor}"
            )
        if self.route_size % 2 ** len(self.route_channels):
            raise ValueError(f"route_size {self.route_size} must be divisible by {2 ** len(self.route_channels)}")
        if self.transition_kernel % 2 == 0:
            raise ValueError(f"transition_kernel {self.transition_kernel} must be odd")
        if self.max_shift <= 0:
            raise ValueError(f"max_shift {self.max_shift} must be positive (cells per step)")

    @property
    def grid(self) -> tuple[int, int]:
        """(rows, columns) of the latent grid."""
        stages = len(self.image_channels)
        return self.image_height >> stages, self.image_width >> stages

    @property
    def lidar_view_shape(self) -> tuple[int, int]:
        """(rows, columns) of the lidar view: the camera's frustum at `lidar_view_scale` x the image size."""
        return self.image_height * self.lidar_view_scale, self.image_width * self.lidar_view_scale

    @property
    def deter_dim(self) -> int:
        return self.deter_channels * self.grid[0] * self.grid[1]

    @property
    def stoch_dim(self) -> int:
        return self.stoch_channels * self.grid[0] * self.grid[1]

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> WorldModelConfig:
        return config_from_dict(cls, values, "world model")


# ---------------------------------------------------------------------------------------------
# Input preprocessing (numpy, per frame)


def resize_rgb(rgb: np.ndarray, config: WorldModelConfig) -> np.ndarray:
    """(H, W, 3) uint8 camera -> (h, w, 3) uint8 at model size; plain area resize, no crop."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"camera image has shape {rgb.shape}; expected (H, W, 3)")
    return cv2.resize(rgb, (config.image_width, config.image_height), interpolation=cv2.INTER_AREA)


def resize_route(route: np.ndarray | None, config: WorldModelConfig) -> np.ndarray:
    """(192, 192) uint8 route map (or None: no route) -> (route_size, route_size) uint8."""
    if route is None:
        return np.zeros((config.route_size, config.route_size), np.uint8)
    route = np.asarray(route)
    if route.ndim == 3:
        route = route[..., 0]
    return cv2.resize(route, (config.route_size, config.route_size), interpolation=cv2.INTER_AREA)


def lidar_range_image(points: np.ndarray | None, config: WorldModelConfig) -> np.ndarray:
    """Spherical projection of a (N, 4) cloud to a (4, rows, width) float32 range view.

    AnoVox stores (x, -y, z, intensity) with CARLA's y pointing right, so the stored frame is
    x forward, y left, z up. Column = azimuth (forward at the centre, left to the left), row =
    elevation from `lidar_fov_up` (top) to `lidar_fov_down`. Where several points fall in one pixel
    the nearest wins. Channels (x, y, z, range) / lidar_scale; empty pixels are 0.
    """
    rows, width = config.lidar_rows, config.lidar_width
    image = np.zeros((4, rows, width), np.float32)
    if points is None or len(points) == 0:
        return image
    points = np.asarray(points, np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"lidar points have shape {points.shape}; expected (N, 4)")
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rng = np.sqrt(x * x + y * y + z * z)
    keep = np.isfinite(rng) & (rng > 0.1)
    x, y, z, rng = x[keep], y[keep], z[keep], rng[keep]
    azimuth = np.arctan2(y, x)
    elevation = np.degrees(np.arctan2(z, np.sqrt(x * x + y * y)))
    col = np.clip(((0.5 - azimuth / (2 * np.pi)) * width).astype(np.int64), 0, width - 1)
    span = config.lidar_fov_up - config.lidar_fov_down
    row = np.clip(((config.lidar_fov_up - elevation) / span * rows).astype(np.int64), 0, rows - 1)
    pixel = row * width + col
    order = np.lexsort((rng, pixel))  # by pixel, nearest first
    first = np.ones(len(order), bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    chosen = order[first]
    values = np.stack([x[chosen], y[chosen], z[chosen], rng[chosen]]) / config.lidar_scale
    image.reshape(4, -1)[:, pixel[chosen]] = values
    return image


class LidarReturns(NamedTuple):
    """The lidar returns that land in the camera's view, nearest first per view pixel."""

    row: np.ndarray  # (N,) int64 row in the lidar view (`WorldModelConfig.lidar_view_shape`)
    col: np.ndarray  # (N,) int64 column
    range: np.ndarray  # (N,) float32 metres from the lidar
    rise: np.ndarray  # (N,) float32 the beam's climb per metre (the z of its unit direction, the vehicle's axes)


def lidar_returns(points: np.ndarray | None, config: WorldModelConfig, rig: SensorRig) -> LidarReturns:
    """The (N, 4) AnoVox cloud's points in front of the camera that land in the lidar view, projected
    with the drive's camera and mounts (`rig`); where several land in one view pixel the nearest wins."""
    rows, cols = config.lidar_view_shape
    if points is None or len(points) == 0:
        empty = np.zeros(0, np.int64)
        return LidarReturns(empty, empty, np.zeros(0, np.float32), np.zeros(0, np.float32))
    points = np.asarray(points, np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"lidar points have shape {points.shape}; expected (N, 4)")
    row, col, depth = rig.project(points[:, :3], (rows, cols))
    rng = np.linalg.norm(points[:, :3], axis=1)
    keep = (depth > 0.1) & (row >= 0) & (row < rows) & (col >= 0) & (col < cols) & np.isfinite(rng)
    row, col, rng = row[keep], col[keep], rng[keep]
    up = points[keep, :3] @ np.asarray(rig.lidar_axes, np.float32)[2] if rig.lidar_axes else points[keep, 2]
    rise = up / np.maximum(rng, 1e-6)
    pixel = row * cols + col
    order = np.lexsort((rng, pixel))  # by pixel, nearest first
    first = np.ones(len(order), bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    chosen = order[first]
    return LidarReturns(row[chosen], col[chosen], rng[chosen].astype(np.float32), rise[chosen].astype(np.float32))


def lidar_view(returns: LidarReturns, config: WorldModelConfig) -> np.ndarray:
    """(rows, columns) float32 view of the returns' ranges in metres, 0 where none landed."""
    view = np.zeros(config.lidar_view_shape, np.float32)
    view[returns.row, returns.col] = returns.range
    return view


def action_of(throttle: float, brake: float, steer: float) -> np.ndarray:
    """The model's action [throttle - brake, steer] as (2,) float32."""
    return np.array([throttle - brake, steer], np.float32)


# ---------------------------------------------------------------------------------------------
# Building blocks


def conv_stack(in_channels: int, channels: tuple[int, ...]) -> nn.Sequential:
    """Stride-2 4x4 convolutions: (B, C, H, W) -> (B, channels[-1], H / 2^k, W / 2^k)."""
    layers: list[nn.Module] = []
    for out_channels in channels:
        layers += [nn.Conv2d(in_channels, out_channels, 4, stride=2, padding=1), nn.SiLU()]
        in_channels = out_channels
    return nn.Sequential(*layers)


class ResBlock(nn.Module):
    """x + conv3x3(silu(conv3x3(x))): more depth on the grid at no cost in resolution."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1), nn.SiLU(), nn.Conv2d(channels, channels, 3, padding=1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.silu(x + self.body(x))


def upsample_stack(channels: tuple[int, ...], out_channels: int) -> nn.Sequential:
    """From channels[0] on the grid, per further entry: nearest x2 upsampling and a 3x3 convolution
    (no transposed convolutions: they leave a checkerboard the difference maps would see); then a
    3x3 convolution to out_channels (no final activation)."""
    layers: list[nn.Module] = []
    for in_channels, next_channels in zip(channels[:-1], channels[1:], strict=True):
        layers += [nn.Upsample(scale_factor=2.0), nn.Conv2d(in_channels, next_channels, 3, padding=1), nn.SiLU()]
    layers.append(nn.Conv2d(channels[-1], out_channels, 3, padding=1))
    return nn.Sequential(*layers)


class UpsampledConv(nn.Module):
    """Nearest x2 upsampling, then a 3x3 convolution (padding 1), computed without the upsampled map.

    Output row 2i + a (a = 0, 1) of the convolution reads upsampled rows 2i + a - 1 .. 2i + a + 1,
    which repeat only two input rows: i - 1, i for a = 0 (kernel rows 0 | 1 + 2) and i, i + 1 for
    a = 1 (kernel rows 0 + 1 | 2); columns likewise. Each of the four output phases (a, b) is so a
    2x2 convolution of the input with sums of the kernel's taps, and one convolution of the padded
    input computes all four: 4/9 of the multiplications, no map four times the input's size. For
    inference (`WorldModel.fold_upsampling`): the folded kernels are a copy of the convolution's."""

    FOLD = ((1.0, 0.0, 0.0), (0.0, 1.0, 1.0)), ((1.0, 1.0, 0.0), (0.0, 0.0, 1.0))  # [phase][tap][kernel row]

    def __init__(self, upsample: nn.Upsample, conv: nn.Conv2d):
        super().__init__()
        if upsample.mode != "nearest" or upsample.scale_factor not in (2, (2, 2)) or upsample.size is not None:
            raise ValueError(f"UpsampledConv: expected nearest x2 upsampling, got {upsample}")
        if conv.kernel_size != (3, 3) or conv.padding != (1, 1) or conv.stride != (1, 1) or conv.groups != 1:
            raise ValueError(f"UpsampledConv: expected a 3x3 convolution with padding 1, got {conv}")
        fold = torch.tensor(self.FOLD, dtype=conv.weight.dtype, device=conv.weight.device)
        kernels = torch.einsum("atk,bsl,oikl->aboits", fold, fold, conv.weight.detach())  # (2, 2, O, I, 2, 2)
        self.register_buffer("kernels", kernels.flatten(0, 2).contiguous(), persistent=False)  # (4 O, I, 2, 2)
        bias = conv.bias.detach() if conv.bias is not None else conv.weight.new_zeros(conv.out_channels)
        self.register_buffer("bias", bias.repeat(4), persistent=False)
        self.out_channels = conv.out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, I, h, w) -> (N, O, 2h, 2w)."""
        n, _, h, w = x.shape
        phases = F.conv2d(F.pad(x, (1, 1, 1, 1)), self.kernels, self.bias)  # (N, 4 O, h + 1, w + 1)
        # phase (a, b) of input cell (i, j): phases[:, a, b, :, i + a, j + b]
        phases = phases.view(n, 2, 2, self.out_channels, h + 1, w + 1)
        rows = [torch.stack([phases[:, a, b, :, a : a + h, b : b + w] for b in (0, 1)], dim=-1) for a in (0, 1)]
        return torch.stack(rows, dim=3).reshape(n, self.out_channels, 2 * h, 2 * w)  # (N, O, h, a, w, b)


def fold_upsampling(stack: nn.Sequential) -> nn.Sequential:
    """`stack`'s layers with each nearest upsampling and the convolution after it as one `UpsampledConv`."""
    layers: list[nn.Module] = []
    for layer in stack:
        if layers and isinstance(layers[-1], nn.Upsample):
            layers[-1] = UpsampledConv(layers[-1], layer)
        else:
            layers.append(layer)
    return nn.Sequential(*layers)


class VectorEncoder(nn.Module):
    """(B, C, H, W) -> (B, embed): a conv stack, then one linear layer (lidar and route)."""

    def __init__(self, in_channels: int, channels: tuple[int, ...], height: int, width: int, embed: int):
        super().__init__()
        self.convs = conv_stack(in_channels, channels)
        flat = channels[-1] * (height >> len(channels)) * (width >> len(channels))
        self.out = nn.Sequential(nn.Linear(flat, embed), nn.LayerNorm(embed), nn.SiLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.convs(x).flatten(1))


class ConvGRUCell(nn.Module):
    """A GRU whose state is a map and whose gates are convolutions (the DreamerV2 variant: the reset
    gate scales the candidate, the update gate starts biased towards keeping the state)."""

    def __init__(self, in_channels: int, channels: int, kernel: int):
        super().__init__()
        self.gates = nn.Conv2d(in_channels + channels, 3 * channels, kernel, padding=kernel // 2)
        self.norm = nn.GroupNorm(1, 3 * channels)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        reset, candidate, update = self.norm(self.gates(torch.cat([x, h], dim=1))).chunk(3, dim=1)
        candidate = torch.tanh(torch.sigmoid(reset) * candidate)
        update = torch.sigmoid(update - 1.0)
        return update * candidate + (1 - update) * h


class MotionWarp(nn.Module):
    """Moves the state with the scene before the GRU updates it.

    Driving forward, the scene flows outward from the vanishing point, faster at the sides and the
    nearer it is. With `ground_flow`, the warp starts from the flow of a flat road at the current
    speed (`ground_source`); a small head reads the state, the action and each cell's position and
    adds a displacement per cell, in cells, bounded by `max_shift` (what is not road: facades, cars,
    a road that is not flat). The maps are then resampled bilinearly from where their content was a
    step before. The head's last layer starts at zero, so an untrained warp is the road's flow alone
    (or the identity without `ground_flow`) and the model learns the rest."""

    def __init__(self, in_channels: int, config: WorldModelConfig):
        super().__init__()
        self.max_shift, self.ground_flow = config.max_shift, config.ground_flow
        hidden = config.motion_channels
        self.net = nn.Sequential(
            nn.Conv2d(in_channels + 2, hidden, 5, padding=2),
            nn.SiLU(),
            nn.Conv2d(hidden, hidden, 3, padding=1),
            nn.SiLU(),
            nn.Conv2d(hidden, 2, 3, padding=1),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)
        rows, cols = config.grid
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, rows), torch.linspace(-1, 1, cols), indexing="ij")
        self.register_buffer("position", torch.stack([xs, ys])[None], persistent=False)  # (1, 2, rows, cols)
        self.register_buffer(
            "cell", torch.tensor([2.0 / max(cols - 1, 1), 2.0 / max(rows - 1, 1)]), persistent=False
        )  # one cell in grid_sample's [-1, 1] units, (x, y)
        # Road flow: a road point seen at (u, v) pixels from the image centre (v > 0: below the horizon)
        # lies at depth d = f · camera_height / v; after the camera moves t metres forward it is at d - t,
        # so a step before it was seen at (u, v) / (1 + k), k = t · v / (f · camera_height).
        cell_px = config.image_width / cols
        focal = config.image_width / 2 / math.tan(math.radians(config.camera_fov) / 2)  # px, square pixels
        u = (torch.arange(cols) + 0.5) * cell_px - config.image_width / 2
        v = (torch.arange(rows) + 0.5) * cell_px - config.image_height / 2
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        self.register_buffer("offset", torch.stack([uu, vv])[None] / cell_px, persistent=False)  # cells from the centre
        self.register_buffer(
            "road_rate", (vv.clamp(min=0) / (focal * config.camera_height))[None, None], persistent=False
        )  # k per metre of travel, (1, 1, rows, cols)

    def ground_source(self, travel: torch.Tensor) -> torch.Tensor:
        """(B, 2, rows, cols) shift in cells to where the road's content was before the camera moved
        `travel` (B,) metres forward; zero above the horizon."""
        k = self.road_rate * travel.float().view(-1, 1, 1, 1)
        return -self.offset * k / (1 + k)

    def forward(self, features: torch.Tensor, maps: torch.Tensor, travel: torch.Tensor | None = None) -> torch.Tensor:
        """Warp `maps` (B, C, rows, cols) by the motion read from `features` (B, F, rows, cols) and, with
        `ground_flow`, the road's flow after `travel` (B,) metres forward (None: standing still)."""
        position = self.position.to(features.dtype).expand(features.shape[0], -1, -1, -1)
        shift = self.max_shift * torch.tanh(self.net(torch.cat([features, position], dim=1)).float())
        if self.ground_flow and travel is not None:
            shift = shift + self.ground_source(travel)
        source = self.position + shift * self.cell[None, :, None, None]  # where each cell's content was
        return F.grid_sample(
            maps.float(), source.permute(0, 2, 3, 1), mode="bilinear", padding_mode="border", align_corners=True
        ).to(maps.dtype)


def grid_head(in_channels: int, hidden: int, out_channels: int) -> nn.Sequential:
    """Per-cell Gaussian parameters on the latent grid (3x3 conv, then 1x1)."""
    return nn.Sequential(nn.Conv2d(in_channels, hidden, 3, padding=1), nn.SiLU(), nn.Conv2d(hidden, out_channels, 1))


class Observation(NamedTuple):
    """A batch of observation sequences, model-ready tensors."""

    rgb: torch.Tensor  # (B, T, 3, H, W) float in [0, 1]
    lidar: torch.Tensor  # (B, T, 4, rows, width) range view
    route: torch.Tensor  # (B, T, 1, R, R) float in [0, 1]
    speed: torch.Tensor  # (B, T, 1) speed_mps / speed_scale

    def to(self, device: torch.device | str) -> Observation:
        """The same observation with every tensor on `device` (no copy where it is there already)."""
        return Observation(*(tensor.to(device) for tensor in self))


class State(NamedTuple):
    h: torch.Tensor  # (..., deter_dim) deterministic map, (deter_channels, rows, cols) flattened
    z: torch.Tensor  # (..., stoch_dim) stochastic map, (stoch_channels, rows, cols) flattened


class ObserveResult(NamedTuple):
    states: State  # posterior states, each (B, T, .)
    prior_mean: torch.Tensor  # (B, T, stoch_dim)
    prior_std: torch.Tensor
    post_mean: torch.Tensor
    post_std: torch.Tensor
    rgb: torch.Tensor | None  # (B, T, 3, H, W) reconstructions in [0, 1]; None when not decoded


class ImagineResult(NamedTuple):
    states: State  # prior states, each (B, n, .)
    rgb: torch.Tensor | None  # (B, n, 3, H, W) predicted frames; None when not decoded


# ---------------------------------------------------------------------------------------------
# The model


class WorldModel(nn.Module):
    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.config = c = config
        self.image_encoder = nn.Sequential(
            conv_stack(3, c.image_channels), *(ResBlock(c.image_channels[-1]) for _ in range(c.res_blocks))
        )  # (B, C, rows, cols)
        self.lidar_encoder = VectorEncoder(4, c.lidar_channels, c.lidar_rows, c.lidar_width, c.lidar_embed)
        self.route_encoder = VectorEncoder(1, c.route_channels, c.route_size, c.route_size, c.route_embed)
        self.side = nn.Linear(c.lidar_embed + c.route_embed + 1, c.side_channels)  # + speed
        self.motion = MotionWarp(c.deter_channels + c.stoch_channels + 2, c)
        self.gru = ConvGRUCell(c.stoch_channels + 2, c.deter_channels, c.transition_kernel)
        self.prior_net = grid_head(c.deter_channels, c.hidden_channels, 2 * c.stoch_channels)
        embed_channels = c.image_channels[-1] + c.side_channels
        self.posterior_net = grid_head(c.deter_channels + embed_channels, c.hidden_channels, 2 * c.stoch_channels)
        self.image_decoder = nn.Sequential(
            nn.Conv2d(c.deter_channels + c.stoch_channels, c.decoder_channels[0], 3, padding=1),
            nn.SiLU(),
            *(ResBlock(c.decoder_channels[0]) for _ in range(c.res_blocks)),
            upsample_stack(c.decoder_channels, 3),
        )
        if c.lidar_head:
            rows, cols = c.grid
            ys, xs = torch.meshgrid(torch.linspace(-1, 1, rows), torch.linspace(-1, 1, cols), indexing="ij")
            self.register_buffer("cell_position", torch.stack([xs, ys])[None], persistent=False)  # (1, 2, rows, cols)
            self.lidar_decoder = nn.Sequential(
                nn.Conv2d(c.deter_channels + c.stoch_channels + 2, c.lidar_decoder_channels[0], 3, padding=1),
                nn.SiLU(),
                upsample_stack(c.lidar_decoder_channels, c.lidar_view_scale**2),
                nn.PixelShuffle(c.lidar_view_scale),
            )  # log range (metres) per view pixel
            nn.init.constant_(self.lidar_decoder[2][-1].bias, math.log(20.0))

    # -- pieces ---------------------------------------------------------------------------------

    def initial_state(self, batch: int) -> State:
        """The state before a drive's first frame (zeros)."""
        weight = self.prior_net[0].weight
        return State(weight.new_zeros(batch, self.config.deter_dim), weight.new_zeros(batch, self.config.stoch_dim))

    def as_grid(self, flat: torch.Tensor) -> torch.Tensor:
        """(B, C * rows * cols) -> (B, C, rows, cols)."""
        return flat.view(flat.shape[0], -1, *self.config.grid)

    def embed(self, obs: Observation) -> torch.Tensor:
        """(B, T, ...) observations -> (B, T, C_image + side_channels, rows, cols) on the latent grid."""
        b, t = obs.rgb.shape[:2]
        image = self.image_encoder(obs.rgb.flatten(0, 1) - 0.5)  # (BT, C, rows, cols)
        side = torch.cat(
            [
                self.lidar_encoder(obs.lidar.flatten(0, 1)),
                self.route_encoder(obs.route.flatten(0, 1) - 0.5),
                obs.speed.flatten(0, 1),
            ],
            dim=-1,
        )
        side = self.side(side)[:, :, None, None].expand(-1, -1, *image.shape[2:])  # (BT, S, rows, cols)
        grid = torch.cat([image, side], dim=1)
        return grid.view(b, t, *grid.shape[1:])

    def _gaussian(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, raw_std = params.chunk(2, dim=1)  # channel halves -> (B, stoch_channels, rows, cols) each
        return mean.flatten(1), F.softplus(raw_std).flatten(1) + self.config.min_std

    def transition(
        self, state: State, action: torch.Tensor, move: bool, speed: torch.Tensor | None = None
    ) -> torch.Tensor:
        """h_t from s_{t-1} and the action a_{t-1} (B, 2) taken after it -> (B, deter_dim).

        `move` (predicting: `imagine`) first moves the state with the scene (MotionWarp; with
        `ground_flow` it needs `speed` (B,): the model's speed input, m/s / speed_scale, of the frame
        the rollout started from, taken as constant over the step), then the GRU updates it.
        Filtering (`observe`) leaves the warp out: a warp also carries what the posterior drew a step
        before, an anomaly included, into the next frame's prior, so the reconstructions would learn
        to redraw an object they never saw once it has been in view (chosen on validation seed 2: with
        the warp in both, the 3-step predictions gained and AP without masks fell; docs/experiments.md)."""
        h, z = self.as_grid(state.h), self.as_grid(state.z)
        action_grid = action[:, :, None, None].expand(-1, -1, *z.shape[2:]).to(z.dtype)
        if move:
            c = self.config
            if c.ground_flow and speed is None:
                raise ValueError("transition: this model's warp follows the road at the current speed; pass `speed`")
            travel = None if speed is None else speed.reshape(-1) * c.speed_scale * c.frame_step / c.frame_rate
            state_grid = torch.cat([h, z], dim=1)
            h, z = self.motion(torch.cat([state_grid, action_grid], dim=1), state_grid, travel).split(
                [h.shape[1], z.shape[1]], dim=1
            )
        return self.gru(torch.cat([z, action_grid], dim=1), h).flatten(1)

    def prior(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """p(z_t | h_t): mean and std, each (B, stoch_dim)."""
        return self._gaussian(self.prior_net(self.as_grid(h)))

    def posterior(self, h: torch.Tensor, embed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q(z_t | h_t, o_t) from h (B, deter_dim) and one step's embedding grid (B, E, rows, cols)."""
        return self._gaussian(self.posterior_net(torch.cat([self.as_grid(h), embed], dim=1)))

    def decode(self, state: State) -> torch.Tensor:
        """States (N, .) -> RGB (N, 3, H, W) in [0, 1]."""
        grid = torch.cat([self.as_grid(state.h), self.as_grid(state.z)], dim=1)
        return torch.sigmoid(self.image_decoder(grid))

    def decode_lidar(self, state: State) -> torch.Tensor:
        """States (N, .) -> the lidar view's range (N, rows, columns) in metres, as the state expects it."""
        if not self.config.lidar_head:
            raise ValueError("decode_lidar: this world model has no lidar head (config lidar_head is false)")
        return torch.exp(self.decode_lidar_log(state).float())

    def decode_lidar_log(self, state: State) -> torch.Tensor:
        """States (N, .) -> log range (N, rows, columns): what training compares with the returns."""
        h = self.as_grid(state.h)
        position = self.cell_position.to(h.dtype).expand(h.shape[0], -1, -1, -1)
        grid = torch.cat([h, self.as_grid(state.z), position], dim=1)  # where a cell looks: the road's range
        #   under a cell follows from its row alone, which convolutions cannot see without it
        return self.lidar_decoder(grid)[:, 0].clamp(-3.0, 6.0)

    def fold_upsampling(self) -> None:
        """For inference: the decoder's upsamplings and the convolutions after them as `UpsampledConv`
        (less CPU for the world-model operator, the same images as the unfolded decoder's up to float
        rounding; docs/experiments.md). The folded kernels are copies of the weights: neither train nor
        save the model after this."""
        self.image_decoder[-1] = fold_upsampling(self.image_decoder[-1])
        if self.config.lidar_head:
            self.lidar_decoder[2] = fold_upsampling(self.lidar_decoder[2])

    # -- sequences ------------------------------------------------------------------------------

    def observe(
        self,
        obs: Observation,
        prev_actions: torch.Tensor,
        state: State | None = None,
        sample: bool = False,
        images: bool = True,
    ) -> ObserveResult:
        """Filter a sequence with the posterior and reconstruct each frame from its state.

        Args:
            obs: observations of steps 0..T-1.
            prev_actions: (B, T, 2) row t = the action taken after step t-1 (zeros at a drive start).
            state: the state before step 0 (default: a drive start).
            sample: draw z from the posterior (training) instead of taking its mean.
            images: decode the reconstructions (False: the states only, `rgb` is None).
        """
        b, t = obs.rgb.shape[:2]
        embed = self.embed(obs)  # (B, T, E, rows, cols)
        state = state or self.initial_state(b)
        hs, zs, prior_stats, post_stats = [], [], [], []
        for step in range(t):
            h = self.transition(state, prev_actions[:, step], move=False)
            prior_stats.append(self.prior(h))
            mean, std = self.posterior(h, embed[:, step])
            post_stats.append((mean, std))
            z = mean + std * torch.randn_like(std) if sample else mean
            state = State(h, z)
            hs.append(h)
            zs.append(z)
        states = State(torch.stack(hs, 1), torch.stack(zs, 1))  # (B, T, .)
        rgb = None
        if images:
            rgb = self.decode(State(states.h.flatten(0, 1), states.z.flatten(0, 1))).view(b, t, -1, *obs.rgb.shape[3:])
        return ObserveResult(
            states=states,
            prior_mean=torch.stack([m for m, _ in prior_stats], 1),
            prior_std=torch.stack([s for _, s in prior_stats], 1),
            post_mean=torch.stack([m for m, _ in post_stats], 1),
            post_std=torch.stack([s for _, s in post_stats], 1),
            rgb=rgb,
        )

    def imagine(
        self,
        state: State,
        actions: torch.Tensor,
        n: int | None = None,
        speed: torch.Tensor | None = None,
        images: bool = True,
    ) -> ImagineResult:
        """Roll the prior forward n steps from `state` (B, .) with actions (B, >=n, 2) (row k = the
        action after imagined step k-1, i.e. after `state` for k = 0) and decode the predicted frames.
        `speed` (B,): the model's speed input of the frame `state` was filtered on (needed with
        `ground_flow`). The prior mean is used: predictions are deterministic. `images`: decode the
        predicted frames (False: the states only, `rgb` is None)."""
        n = actions.shape[1] if n is None else n
        if actions.shape[1] < n:
            raise ValueError(f"imagine: {actions.shape[1]} actions for {n} steps; expected at least {n}")
        hs, zs = [], []
        for step in range(n):
            h = self.transition(state, actions[:, step], move=True, speed=speed)
            state = State(h, self.prior(h)[0])
            hs.append(state.h)
            zs.append(state.z)
        states = State(torch.stack(hs, 1), torch.stack(zs, 1))
        if not images:
            return ImagineResult(states, None)
        rgb = self.decode(State(states.h.flatten(0, 1), states.z.flatten(0, 1)))
        return ImagineResult(states, rgb.view(state.h.shape[0], n, *rgb.shape[1:]))


# ---------------------------------------------------------------------------------------------
# Weights on disk: MODEL.safetensors + MODEL.json (config and training record)


def save_world_model(model: WorldModel, path: str | Path, record: dict | None = None) -> Path:
    """Write the weights (safetensors) and a JSON beside them with the config and `record`."""
    return save_weights(model, path, model.config.to_dict(), record)


def load_world_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[WorldModel, dict]:
    """Load MODEL.safetensors + MODEL.json; returns the model (on `device`, eval mode) and the JSON record."""
    return load_model(path, "world model", lambda config, _: WorldModel(WorldModelConfig.from_dict(config)), device)
