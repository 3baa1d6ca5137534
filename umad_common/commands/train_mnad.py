"""`umad train mnad DATA --out FILE`: train the MNAD baseline on normal drives."""

from __future__ import annotations

import argparse
import logging

from umad_common.commands.checks import training_inputs
from umad_common.commands.common import (
    add_data_argument,
    add_device_argument,
    add_epochs_argument,
    add_frames_argument,
    add_out_argument,
    add_seed_argument,
    add_topics_argument,
    resolve_device_or_exit,
)

log = logging.getLogger("umad.train.mnad")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_data_argument(parser)
    add_topics_argument(parser)
    add_out_argument(parser)
    add_epochs_argument(parser, 3)
    parser.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="train for about this long instead (the epochs that fit, from a timed step; recorded in the JSON)",
    )
    add_seed_argument(parser)
    add_frames_argument(parser, 1200)
    parser.add_argument("--batch-size", type=int, default=8, help="frames per step (default 8)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    add_device_argument(parser)


def run(args: argparse.Namespace) -> int:
    training_inputs(args.data, args.out, ".safetensors", args.topics)
    import torch

    from umad_common.models.mnad import MnadConfig, save_mnad
    from umad_common.training.train_mnad import MnadTrainingConfig, load_normal_frames, train_mnad

    if args.epochs < 1 or args.frames < 2 or args.batch_size < 2 or (args.minutes is not None and args.minutes <= 0):
        raise SystemExit("--epochs must be >= 1, --minutes > 0, --frames and --batch-size >= 2")
    torch.set_num_threads(args.threads)
    device = resolve_device_or_exit(args.device)
    train_cfg = MnadTrainingConfig(
        epochs=args.epochs, seed=args.seed, batch_size=args.batch_size, max_frames=args.frames, minutes=args.minutes
    )
    model_cfg = MnadConfig()
    frames = load_normal_frames(args.data, model_cfg, train_cfg.max_frames, args.topics)
    model, record = train_mnad(frames, train_cfg, model_cfg, device=device)
    record["training"]["data"] = str(args.data)
    save_mnad(model, args.out, record)
    log.info("wrote %s (+ %s) after %s s", args.out, args.out.with_suffix(".json").name, record["training"]["seconds"])
    return 0
