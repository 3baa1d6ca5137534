"""MNAD predictor: the memory-guided autoencoder baseline (Park et al. 2020) as a graph operator.

Input `camera` (replayer/camera, `rgb` (H, W, 3) uint8); output `map`: the per-pixel squared L2
reconstruction error at the model size (128x192 by default; the camera is plainly resized, so
labels align by nearest resize). The memory is frozen at inference: the operator is stateless and
frames may go to any replica in any order.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from umad_common import ASSETS
from umad_common.dataflow import Frame, Input, Operator, Output, input_array
from umad_common.models.device import DeviceName, device_field, resolve_device

SHIPPED_WEIGHTS = ASSETS / "mnad.safetensors"


class MnadParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    weights: str | None = Field(
        default=None,
        description="MNAD weights (.safetensors with its .json beside it), relative to the graph folder unless "
        "absolute; default: the checkpoint shipped for the built-in world (umad_common/assets/mnad.safetensors)",
    )
    threads: int = Field(default=1, ge=1, description="torch CPU threads of this operator process")
    device: DeviceName = device_field()


class MnadPredictor(Operator):
    """Per-frame MNAD anomaly map."""

    kind = "mnad"
    fixed_params = ("device",)
    inputs = (Input("camera"),)
    outputs = ("map",)
    Params = MnadParams

    @classmethod
    def input_paths(cls, params: BaseModel) -> dict[str, str]:
        return {} if params.weights is None else {"weights": params.weights}

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        import torch

        from umad_common.models.mnad import load_mnad

        torch.set_num_threads(self.params.threads)
        self.device = resolve_device(self.params.device)
        path = SHIPPED_WEIGHTS if self.params.weights is None else self.context.resolve(self.params.weights)
        self.model, record = load_mnad(path, self.device)  # raises WeightsError naming the file
        self.weights_name = path.name
        self.trained_on = record.get("training", {}).get("data")

    def process(self, frame: Frame) -> dict[str, Output]:
        from umad_common.models.mnad import to_input

        rgb = input_array(frame, "camera", "rgb", self.kind)
        x = to_input(rgb, self.model.cfg).to(self.device)  # raises on a non-(H, W, 3) uint8 image
        score_map = self.model.anomaly_map(x)[0].cpu().numpy().astype("float32")
        return {"map": Output({"map": score_map}, {"model": "mnad", "score": "l2", "weights": self.weights_name})}
