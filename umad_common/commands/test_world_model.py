"""`umad test world-model MODEL DATA`: how good a trained world model is, before it goes in a graph.

DATA is a benchmark (normal/ and anomalous/) or a folder of normal drives: AnoVox folders or
recordings (`umad data info DATA` shows what is read; `--topics` picks a recording's topics). Prints,
on the normal drives the model never trained on (named in MODEL.json), the PSNR of the
reconstruction and of the predictions 1..horizon steps ahead, and, on DATA/anomalous, the mean
|error| inside anomalies against road pixels outside them (drives with semantic labels; the ratio
must be well above 1), then
the same PSNRs for each normal drive (`per_drive`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from umad_common.commands.checks import drives, model_file
from umad_common.commands.common import add_data_argument, add_topics_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, help="MODEL or MODEL.safetensors (with MODEL.json beside it)")
    add_data_argument(parser, help="drives: a benchmark (normal/ and anomalous/) or a folder of normal drives")
    add_topics_argument(parser)
    parser.add_argument("--horizon", type=int, default=3, help="prediction steps to score (default 3)")
    parser.add_argument("--normal-limit", type=int, default=None, help="score only the first N unseen normal drives")
    parser.add_argument("--anomalous-limit", type=int, default=None, help="score only the first N anomalous drives")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")


def run(args: argparse.Namespace) -> int:
    model_file(args.model, "MODEL", "world model")
    drives(args.data, "DATA", args.topics)
    import torch

    from umad_common.models.world_model import load_world_model
    from umad_common.training.evaluate_world_model import evaluate_world_model, unseen_normal_drives

    if args.horizon < 1:
        raise SystemExit(f"--horizon is {args.horizon}; expected at least 1")
    torch.set_num_threads(args.threads)
    model, record = load_world_model(args.model)
    if not unseen_normal_drives(args.data, record, args.topics) and not (args.data / "anomalous").is_dir():
        raise SystemExit(
            f"{args.data}: no normal drive the model did not train on and no anomalous/ folder; expected "
            "drives it never saw"
        )
    figures = evaluate_world_model(
        model,
        args.data,
        record,
        args.horizon,
        normal_limit=args.normal_limit,
        anomalous_limit=args.anomalous_limit,
        topics=args.topics,
    )
    print(json.dumps(rounded(figures), indent=2))
    return 0


def rounded(value):
    """Floats to 4 decimals, inside dicts too (the per-drive figures)."""
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    return round(value, 4) if isinstance(value, float) else value
