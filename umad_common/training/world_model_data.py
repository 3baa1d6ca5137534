"""The normal drives in memory and the training windows cut from them.

Only normal drives are read (DATA/normal if it exists, else DATA), and of each frame only the
model's inputs: camera, lidar, ego and route; never a label. Every frame is resized once into
memory (`DriveArrays`); each epoch cuts every drive into windows of `sequence_length` model steps at
a seeded random offset and visits them in a seeded order (`epoch_windows`). A batch of windows
becomes the model's tensors (`observation_batch`, `view_batch`), each window optionally mirrored
left to right (`mirror_window`) or re-lit (`relight_window`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from umad_common.datasets.drive import Drive
from umad_common.datasets.formats import training_drives
from umad_common.datasets.sensor_rig import SensorRig
from umad_common.models.world_model import (
    Observation,
    WorldModelConfig,
    action_of,
    lidar_range_image,
    lidar_returns,
    lidar_view,
    resize_rgb,
    resize_route,
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


def scale_speed(obs: Observation, config: WorldModelConfig) -> Observation:
    return obs._replace(speed=obs.speed / config.speed_scale)


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
