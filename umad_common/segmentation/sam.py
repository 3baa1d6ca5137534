"""segment-anything's automatic mask generator on a local checkpoint file (never downloaded).

The package needs torchvision and so torch 2.14.1: it runs in its own environment
(built by the shipped `umad_common/scripts/sam_env.sh`; graph field `python: .venv-sam/bin/python`). Its masks overlap.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common import SAM_ENV_SCRIPT
from umad_common.dataflow import Context, Frame
from umad_common.models.device import DeviceName, device_field, resolve_device
from umad_common.segmentation.base import SegmenterMethod


class Sam(SegmenterMethod):
    """segment-anything masks, largest first. Construction loads the package, the checkpoint
    (`torch.load(weights_only=True)` or safetensors) and the model, so a bad setting fails at start."""

    name = "sam"

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        checkpoint: str = Field(
            "",
            description="segment-anything state dict file (.pth or .safetensors) for `model`, relative to the "
            "graph's folder unless absolute; never downloaded",
        )
        model: Literal["vit_b", "vit_l", "vit_h"] = Field("vit_b", description="model size")
        points_per_side: int = Field(16, ge=1, description="prompt grid is points_per_side^2 points (SAM's own 32)")
        pred_iou_thresh: float = Field(0.88, ge=0, le=1, description="drop masks whose predicted IoU is below")
        stability_score_thresh: float = Field(0.95, ge=0, le=1, description="drop masks less stable than this")
        min_mask_region_area: int = Field(0, ge=0, description="remove holes and islands below this (px); 0 = off")
        device: DeviceName = device_field()

    def __init__(self, params: BaseModel, context: Context):
        super().__init__(params, context)
        p = self.params
        if not p.checkpoint:
            raise ValueError("segmenter method 'sam' needs option checkpoint (a local checkpoint file)")
        checkpoint = context.resolve(p.checkpoint)
        if not checkpoint.is_file():
            raise FileNotFoundError(
                f"segmenter method 'sam': checkpoint file {checkpoint} does not exist; expected a segment-anything "
                f"{p.model} state dict (.pth or .safetensors) named by option checkpoint"
            )
        try:
            import torch
            from segment_anything import SamAutomaticMaskGenerator, sam_model_registry
        except ImportError as exc:
            raise ImportError(
                f"segmenter method 'sam' needs the segment-anything package (and torchvision) but importing it "
                f"failed ({exc}); build its environment with `bash {SAM_ENV_SCRIPT} .venv-sam` and run this operator there with "
                "the graph field `python: .venv-sam/bin/python`"
            ) from exc
        device = resolve_device(p.device)
        if checkpoint.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(checkpoint), device=str(device))
        else:
            state = torch.load(checkpoint, map_location=device, weights_only=True)
        model = sam_model_registry[p.model](checkpoint=None)
        try:
            model.load_state_dict(state)
        except RuntimeError as exc:
            raise ValueError(f"segmenter: {checkpoint} is not a {p.model} SAM checkpoint: {exc}") from None
        model.to(device).eval()
        self.torch = torch
        self.generator = SamAutomaticMaskGenerator(
            model,
            points_per_side=p.points_per_side,
            pred_iou_thresh=p.pred_iou_thresh,
            stability_score_thresh=p.stability_score_thresh,
            min_mask_region_area=p.min_mask_region_area,
            output_mode="binary_mask",
        )

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        rgb = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
        with self.torch.inference_mode():
            records = self.generator.generate(rgb)
        if not records:
            return np.zeros((0, *image.shape[:2]), dtype=bool)
        records.sort(key=lambda r: -int(r["area"]))
        return np.stack([np.asarray(r["segmentation"], dtype=bool) for r in records])
