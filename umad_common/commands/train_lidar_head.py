"""`umad train lidar-head DATA --world-model MODEL --out NEW`: give a trained world model a lidar head.

The world model's weights stay as they are (its images and every camera difference map stay bit for
bit the same); a lidar decoder learns to read the lidar view (the range of every pixel of the
camera's frustum) from the states the model filters and predicts on the normal drives of DATA,
never a label. NEW.safetensors + NEW.json then feed the `lidar` difference (`diff_lidar`). A world
model trained by `umad train world-model` has a lidar head already.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
from pathlib import Path

from umad_common.commands.checks import model_file, training_inputs
from umad_common.commands.common import (
    add_data_argument,
    add_device_argument,
    add_epochs_argument,
    add_out_argument,
    add_seed_argument,
    add_topics_argument,
    resolve_device_or_exit,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_data_argument(parser, help="drives: the normal drives the world model was trained on")
    add_topics_argument(parser)
    parser.add_argument(
        "--world-model", type=Path, required=True, help="a world model without a lidar head (MODEL.safetensors)"
    )
    add_out_argument(parser, help="output path without suffix (NEW.safetensors + .json)")
    add_epochs_argument(parser, 8, help="passes over the normal drives (default 8)")
    add_seed_argument(parser, 0, help="seed of the head's initialisation and the window order")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    add_device_argument(parser)


def command_line(args: argparse.Namespace) -> str:
    """The command as it was given, every option spelled out, for the model's record."""
    words = ["umad", "train", "lidar-head", str(args.data), "--world-model", str(args.world_model)]
    words += ["--out", str(args.out), "--epochs", str(args.epochs), "--seed", str(args.seed)]
    words += ["--threads", str(args.threads)] + (["--device", args.device] if args.device != "auto" else [])
    words += ["--topics", args.topics] if args.topics else []
    return shlex.join(words)


def run(args: argparse.Namespace) -> int:
    training_inputs(args.data, args.out, "", args.topics)
    model_file(args.world_model, "--world-model", "world model")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see `umad train world-model`
    from umad_common.training.fit_lidar_head import fit_lidar_head

    if args.epochs < 1:
        raise SystemExit(f"--epochs is {args.epochs}; expected at least 1")
    try:
        fit = fit_lidar_head(
            args.data,
            args.world_model,
            args.out,
            epochs=args.epochs,
            seed=args.seed,
            threads=args.threads,
            command=command_line(args),
            device=resolve_device_or_exit(args.device),
            topics=args.topics,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    print(json.dumps({"out": str(args.out), "train_seconds": fit["train_seconds"], **fit["history"][-1]}))
    return 0
