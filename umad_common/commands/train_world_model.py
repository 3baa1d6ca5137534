"""`umad train world-model DATA --out MODEL`: train the world model on the normal drives of DATA.

Reads DATA/normal when it exists (a generated benchmark), else every Scenario_* under DATA; never
reads labels. Writes MODEL.safetensors, MODEL.json (config, held-out drives, loss history) and the
resumable checkpoint MODEL.train.pt (not needed to use the model).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", type=Path, help="AnoVox folder (a generated benchmark or a folder of normal drives)")
    parser.add_argument(
        "--out", type=Path, required=True, help="output path without suffix, e.g. umad_common/assets/world_model"
    )
    parser.add_argument("--epochs", type=int, default=16, help="total epochs (with --resume: up to this many)")
    parser.add_argument("--seed", type=int, default=0, help="seed of initialisation, window order and latent noise")
    parser.add_argument(
        "--resume", action="store_true", help="continue from MODEL.train.pt with the configs stored in it"
    )
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (results depend on it)")
    parser.add_argument("--batch-size", type=int, default=None, help="windows per step (default from TrainConfig)")
    parser.add_argument("--sequence-length", type=int, default=None, help="model steps per window (default 8)")
    parser.add_argument(
        "--holdout", type=int, default=None, help="last N normal drives kept out for evaluation (default 1)"
    )
    parser.add_argument("--frame-step", type=int, default=None, help="dataset frames per model step (default 1)")


def run(args: argparse.Namespace) -> int:
    # On a shared machine, OpenMP threads that spin while waiting make 2 threads slower than 1;
    # passive waiting must be chosen before torch loads its OpenMP runtime.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from umad_common.models.world_model import WorldModelConfig
    from umad_common.training.train_world_model import TrainConfig, train_world_model

    train = TrainConfig()
    for name in ("batch_size", "sequence_length", "holdout"):
        if getattr(args, name) is not None:
            setattr(train, name, getattr(args, name))
    model_config = WorldModelConfig(frame_step=args.frame_step or 1)
    if args.epochs < 1:
        raise SystemExit(f"--epochs is {args.epochs}; expected at least 1")
    record = train_world_model(
        args.data,
        args.out,
        epochs=args.epochs,
        seed=args.seed,
        resume=args.resume,
        threads=args.threads,
        model_config=model_config,
        train_config=train,
    )
    last = record["history"][-1]
    summary = {k: round(v, 5) if isinstance(v, float) else v for k, v in last.items()}
    print(json.dumps({"out": str(args.out), "train_seconds": record["train_seconds"], **summary}))
    return 0
