"""`umad test world-model MODEL DATA`: how good a trained world model is, before it goes in a graph.

Prints held-out normal PSNR (reconstruction and one-step prediction) and, on DATA/anomalous, the
mean |error| inside anomalies against road pixels outside them (the ratio must be well above 1).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, help="MODEL or MODEL.safetensors (with MODEL.json beside it)")
    parser.add_argument("data", type=Path, help="the benchmark folder it was trained on (normal/ and anomalous/)")
    parser.add_argument("--anomalous-limit", type=int, default=None, help="evaluate only the first N anomalous drives")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")


def run(args: argparse.Namespace) -> int:
    import torch

    from umad_common.models.world_model import load_world_model
    from umad_common.training.evaluate_world_model import evaluate_world_model

    torch.set_num_threads(args.threads)
    model, record = load_world_model(args.model)
    figures = evaluate_world_model(model, args.data, record.get("heldout_drives", []), args.anomalous_limit)
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in figures.items()}, indent=2))
    return 0
