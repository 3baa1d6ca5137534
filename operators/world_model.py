"""World-model predictor: per frame, the reconstruction x̂_t and the predictions x̂_{t|t-i}.

Frames of a run arrive in order (ordered operator). Every `stride` received frames (seq 0, stride,
2·stride, ...) the model takes a step: the posterior state s_t is computed from the previous state,
the previous step's action and this frame's camera, lidar, speed and route, and decoded into x̂_t.
The rollouts started at the previous n steps are each advanced by one prior step with the action
actually taken, so x̂_{t|t-i} (row i-1 of `preds`) is the frame predicted from the state of i model
steps earlier, never having seen the frames since; a new rollout starts from s_t and keeps the speed
of its frame (a model with `ground_flow` moves the road by it at every step). At a run's start
there is no earlier state: `pred_valid[i-1]` is 0 until i steps have passed.

Frames between model steps (stride > 1) get their own target and a reconstruction from the
posterior of their own observation on top of the last step's state, without advancing the state or
the rollouts; they carry no predictions (`preds` zeros, `pred_valid` all 0). The model was trained
with one step per `frame_step` dataset frames (in its JSON); stride should match it.

With a lidar head (`WorldModelConfig.lidar_head`), a scored frame also carries the lidar returns that
land in the camera's view (projected with the drive's sensor setup, the lidar message's meta
`sensors`; AnoVox's rig where a drive has none) and, for each, the range the model's reconstructed
lidar view expects there: what the `lidar` difference compares. A model without the head sends
none, and says so once when it loads.

A frame the source does not score (meta `skip`, `umad eval --every k`) still moves the state and the
rollouts on, but nothing is decoded: the runtime passes it on as a skip marker.

In live mode the runtime passes over frames that were lost or stale (it processes the newest ready
frame), so seq may jump. A gap of up to `max_gap_steps` model steps is bridged as the model would
without looking: through each missed step the state moves on by the transition and the prior (the
last action held), and the rollouts move on too, so x̂_{t|t-i} still predicts from i model steps
back; no rollout starts at a missed step, so its row stays `pred_valid` 0. A longer gap restarts the
run's state as at seq 0: the prior rolled that far without an observation is no better than a blank
state, and bridging costs a transition per missed step. In lossless mode there are no gaps.

Each run has its own state (`RunState`), kept from its first frame to its end-of-run marker: a
source that sends runs side by side (`runs_in_flight`) interleaves their frames here, and with
`replicas: k` each run is one replica's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Frame, Input, Operator, Output, input_array
from umad_common.datasets.sensor_rig import SensorRig
from umad_common.models.device import DeviceName, bf16_supported, device_field, resolve_device

if TYPE_CHECKING:
    import torch

    from umad_common.models.world_model import Observation, State


class WorldModelParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    model: str = Field(
        default="umad_common/assets/world_model.safetensors",
        description="world model weights (safetensors) with its JSON config beside it; relative to the graph folder",
    )
    horizon: int = Field(
        default=3, ge=1, le=32, description="n: predictions x̂_{t|t-i} made i = 1..n model steps (i·stride frames) back"
    )
    stride: int = Field(
        default=1,
        ge=1,
        description="the model steps on every stride-th frame of a run (seq % stride == 0); frames in between get "
        "a reconstruction from the last step's state and no predictions",
    )
    max_gap_steps: int = Field(
        default=10,
        ge=0,
        description="live mode: a gap of up to this many model steps whose frames were passed over is bridged "
        "with the model's prior; a longer gap restarts the run's state",
    )
    threads: int = Field(default=1, ge=1, description="torch CPU threads of this process")
    device: DeviceName = device_field()
    precision: Literal["float32", "bfloat16", "auto"] = Field(
        default="float32",
        description="bfloat16: the model runs under bfloat16 autocast (less CPU on a CPU with AVX-512 BF16; AP and "
        "FPR95 those of float32 to a fraction of a point on validation seed 2, docs/experiments.md; on a CPU "
        "without it, about 4x the CPU of float32); auto: bfloat16 where the device has fast bfloat16 kernels, "
        "else float32; the images it publishes stay float32",
    )


@dataclass
class RunState:
    """Where the model stands along one run."""

    state: State  # the posterior of the last model step (the initial state before the first)
    pending_action: torch.Tensor  # (1, 2): the action of the last model step's frame
    rollouts: list[tuple[State, torch.Tensor] | None]  # prior rollouts advanced to the last step and the
    #   speed of the frame each started from; [i-1] started i steps before it (None: at a missed step)
    steps: int = 0  # model steps taken
    last_seq: int = 0  # the last frame processed


class WorldModelPredictor(Operator):
    """Runs the world model along each run and publishes target, recon, preds and pred_valid."""

    kind = "world_model"
    inputs = (Input("camera"), Input("lidar"), Input("ego"), Input("route"))
    outputs = ("frame",)
    Params = WorldModelParams
    ordered = True
    fixed_params = ("model", "device", "precision")  # precision: the recurrent state keeps the dtype it was made in

    @classmethod
    def input_paths(cls, params: BaseModel) -> dict[str, str]:
        return {"model": params.model}

    def __init__(self, params: BaseModel | dict | None = None, context=None):
        super().__init__(params, context)
        import torch  # here, not at the top: every replica imports this module to check the graph

        from umad_common.models import world_model

        self.torch, self.wm = torch, world_model
        torch.set_num_threads(self.params.threads)
        self.device = resolve_device(self.params.device)
        self.model_path = self.context.resolve(self.params.model)
        self.model, _ = world_model.load_world_model(self.model_path, self.device)
        self.model.fold_upsampling()
        self.config = self.model.config
        fast_bfloat16 = bf16_supported(self.device)
        self.bfloat16 = self.params.precision == "bfloat16" or (self.params.precision == "auto" and fast_bfloat16)
        if self.params.precision == "bfloat16" and not fast_bfloat16:
            self.context.log.warning(
                "world_model: precision bfloat16 on %s, which has no fast bfloat16 kernels (AVX-512 BF16 or AMX on a "
                "CPU): about 4x the CPU of float32; precision auto runs float32 here",
                self.device,
            )
        if not self.config.lidar_head:
            self.context.log.warning(
                "world_model: %s has no lidar head (config lidar_head: trained without one, or saved before it existed); "
                "the camera maps run, the lidar difference gets no returns. Add one with `umad train lidar-head DATA "
                "--world-model %s --out NEW`",
                self.model_path,
                self.model_path,
            )
        self.assumed_rig_runs: set[str] = set()
        self.trained_frame_step = int(self.config.frame_step)
        self.runs: dict[str, RunState] = {}  # run -> its state, from its first frame to its end

    def fresh_run(self) -> RunState:
        """A run's start: initial state, no rollouts, no pending action."""
        return RunState(self.model.initial_state(1), self.torch.zeros(1, 2, device=self.device), [])

    def end_run(self, run: str) -> dict[str, Output]:
        self.runs.pop(run, None)
        return {}

    def update_params(self, params: BaseModel) -> None:
        horizon_changed = params.horizon != self.params.horizon
        super().update_params(params)
        self.torch.set_num_threads(params.threads)
        if horizon_changed:
            for run in self.runs.values():
                run.rollouts = run.rollouts[: params.horizon]

    def observation(self, frame: Frame) -> tuple[Observation, np.ndarray, np.ndarray]:
        """Model inputs (B = T = 1) on the model's device, the target (h, w, 3) float32 and the action
        (2,) of this frame."""
        c, wm, torch = self.config, self.wm, self.torch
        rgb = wm.resize_rgb(np.asarray(input_array(frame, "camera", "rgb", self.kind), np.uint8), c)
        ego = np.asarray(input_array(frame, "ego", "ego", self.kind), np.float32).reshape(-1)
        if ego.shape != (4,):
            raise ValueError(
                f"world_model {frame.frame_id}: ego has shape {ego.shape}; expected (4,) [speed, throttle, brake, steer]"
            )
        lidar = wm.lidar_range_image(input_array(frame, "lidar", "points", self.kind), c)
        route = wm.resize_route(input_array(frame, "route", "route", self.kind), c)
        target = rgb.astype(np.float32) / 255.0
        obs = wm.Observation(
            rgb=torch.from_numpy(target).permute(2, 0, 1)[None, None],
            lidar=torch.from_numpy(lidar)[None, None],
            route=torch.from_numpy(route.astype(np.float32) / 255.0)[None, None, None],
            speed=torch.tensor([[[ego[0] / c.speed_scale]]]),
        )
        return obs.to(self.device), target, wm.action_of(ego[1], ego[2], ego[3])

    def rig_of(self, frame: Frame) -> SensorRig:
        """The drive's camera and mounts from the lidar message's meta `sensors`; AnoVox's rig, said
        once per run, where the drive has no sensor setup (the benchmark layout)."""
        sensors = frame.inputs["lidar"].meta.get("sensors")
        if sensors:
            return SensorRig.from_sensors(sensors, f"world_model {frame.frame_id}")
        if frame.run not in self.assumed_rig_runs:
            self.assumed_rig_runs.add(frame.run)
            self.context.log.warning(
                "world_model %s: the lidar carries no sensor setup; the lidar view assumes AnoVox's rig", frame.frame_id
            )
        return SensorRig.anovox()

    def lidar_arrays(self, frame: Frame, posterior: State) -> dict[str, np.ndarray]:
        """The returns in the camera's view: `lidar_pixel` (N, 2) int32 (row, column) in the target
        image, `lidar_range` (N,) float32 metres, `lidar_expected` (N,) float32, the range the
        reconstructed lidar view holds at each return's view pixel, and `lidar_expected_height` (N,)
        float32, how far above the vehicle's origin (the ground, in CARLA's and AnoVox's rigs) the
        point the model expected along that beam lies."""
        c, wm = self.config, self.wm
        points = input_array(frame, "lidar", "points", self.kind)
        rig = self.rig_of(frame)
        returns = wm.lidar_returns(points, c, rig)
        expected = np.ascontiguousarray(self.model.decode_lidar(posterior)[0].cpu().numpy()[returns.row, returns.col])
        scale = c.lidar_view_scale
        return {
            "lidar_pixel": np.stack([returns.row // scale, returns.col // scale], axis=1).astype(np.int32),
            "lidar_range": returns.range,
            "lidar_expected": expected.astype(np.float32),
            "lidar_expected_height": (rig.lidar_location[2] + expected * returns.rise).astype(np.float32),
        }

    def missed_steps(self, run: RunState, seq: int) -> int:
        """Model steps (seqs on the stride) strictly between the run's last frame processed and
        `seq`: 0 unless the runtime passed frames over (live mode)."""
        stride = self.params.stride
        return max(0, (seq - 1) // stride - run.last_seq // stride)

    def bridge(self, run: RunState, missed: int) -> None:
        """Carry the state over `missed` model steps without their frames: at each, the state moves
        on by the transition and the prior's mean with the last action held, and the rollouts one
        prior step, a missed step starting none; those that would then be older than `horizon`
        steps at the next frame are dropped unadvanced."""
        State, n = self.wm.State, self.params.horizon
        for _ in range(missed):
            hidden = self.model.transition(run.state, run.pending_action, move=False)
            run.state = State(hidden, self.model.prior(hidden)[0])
            run.rollouts = [None, *self.advance(run.rollouts[: n - 1], run.pending_action)]

    def advance(
        self, rollouts: list[tuple[State, torch.Tensor] | None], action: torch.Tensor
    ) -> list[tuple[State, torch.Tensor] | None]:
        """Each rollout one prior step on with the pending `action`, moving with the scene."""
        State, advanced = self.wm.State, []
        for rollout in rollouts:
            if rollout is None:
                advanced.append(None)
                continue
            origin, speed = rollout
            h_pred = self.model.transition(origin, action, move=True, speed=speed)
            advanced.append((State(h_pred, self.model.prior(h_pred)[0]), speed))
        return advanced

    def process(self, frame: Frame) -> dict[str, Output]:
        with self.torch.no_grad(), self.torch.autocast(self.device.type, self.torch.bfloat16, enabled=self.bfloat16):
            return self.step(frame)

    def step(self, frame: Frame) -> dict[str, Output]:
        """`process` without gradients: one frame through the model."""
        torch, State = self.torch, self.wm.State
        gap = 0
        run = self.runs.get(frame.run)
        if run is None or frame.seq == 0:
            run = self.runs[frame.run] = self.fresh_run()
        else:
            gap = self.missed_steps(run, frame.seq)
            if gap > self.params.max_gap_steps:
                run = self.runs[frame.run] = self.fresh_run()
            else:
                self.bridge(run, gap)
        run.last_seq = frame.seq
        obs, target, action = self.observation(frame)
        n = self.params.horizon
        h, w = self.config.image_height, self.config.image_width
        recon = np.zeros((h, w, 3), np.float32)  # stays blank on a frame nobody scores: nothing is drawn
        preds = np.zeros((n, h, w, 3), np.float32)
        valid = np.zeros(n, np.uint8)
        model_step = frame.seq % self.params.stride == 0
        embed = self.model.embed(obs)[:, 0]
        hidden = self.model.transition(run.state, run.pending_action, move=False)
        posterior = State(hidden, self.model.posterior(hidden, embed)[0])
        scored = not frame.inputs["camera"].meta.get("skip")
        if model_step:
            advanced = self.advance(run.rollouts, run.pending_action)
            if scored:
                rows = [i for i, rollout in enumerate(advanced) if rollout is not None]
                batch = [posterior, *(advanced[i][0] for i in rows)]
                states = State(torch.cat([s.h for s in batch]), torch.cat([s.z for s in batch]))
                images = self.model.decode(states).float().permute(0, 2, 3, 1).cpu().numpy()
                recon = images[0]
                preds[rows] = images[1:]
                valid[rows] = 1
            run.state = posterior
            run.rollouts = [(posterior, obs.speed.reshape(1)), *advanced][:n]
            run.pending_action = torch.from_numpy(action)[None].to(self.device)
            run.steps += 1
        elif scored:
            recon = self.model.decode(posterior)[0].float().permute(1, 2, 0).cpu().numpy()
        meta = {
            "model": self.model_path.name,
            "model_step": bool(model_step),
            "steps": run.steps,
            "trained_frame_step": self.trained_frame_step,
            "bfloat16": self.bfloat16,
        }
        if gap:
            meta["gap_steps"] = gap  # model steps missed just before this frame (a restart: `steps` starts over)
        arrays = {
            "target": target,
            "recon": np.ascontiguousarray(recon, np.float32),
            "preds": preds,
            "pred_valid": valid,
        }
        if self.config.lidar_head and scored:
            arrays.update(self.lidar_arrays(frame, posterior))
        return {"frame": Output(arrays, meta)}
