"""`umad train features DATA --out FILE`: train the label-free perceptual feature net on normal drives."""

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

log = logging.getLogger("umad.train.features")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_data_argument(parser)
    add_topics_argument(parser)
    add_out_argument(parser)
    add_epochs_argument(parser, 4)
    add_seed_argument(parser)
    add_frames_argument(parser, 1200)
    parser.add_argument("--batch-size", type=int, default=12, help="frames per step (default 12)")
    parser.add_argument(
        "--holdout", type=int, default=1, help="last N normal drives left out, as the world model (default 1)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    add_device_argument(parser)


def run(args: argparse.Namespace) -> int:
    training_inputs(args.data, args.out, ".safetensors", args.topics)
    import torch

    from umad_common import recorded_path
    from umad_common.models.feature_net import save_feature_net
    from umad_common.training.train_features import FeatureTrainingConfig, load_normal_rgb, train_feature_net

    if args.epochs < 1 or args.frames < 1 or args.batch_size < 2 or args.holdout < 0:
        raise SystemExit("--epochs and --frames must be >= 1, --batch-size >= 2, --holdout >= 0")
    torch.set_num_threads(args.threads)
    device = resolve_device_or_exit(args.device)
    cfg = FeatureTrainingConfig(
        epochs=args.epochs, seed=args.seed, max_frames=args.frames, batch_size=args.batch_size, holdout=args.holdout
    )
    frames, heldout = load_normal_rgb(args.data, cfg, args.topics)
    model, record = train_feature_net(frames, cfg, data_name=recorded_path(args.data), heldout=heldout, device=device)
    save_feature_net(model, args.out, record)
    log.info("wrote %s (+ %s), %s", args.out, args.out.with_suffix(".json").name, record["training"])
    return 0
