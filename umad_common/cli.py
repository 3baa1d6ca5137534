"""The `umad` command: one verb per step of a user's work.

Each verb lives in its own module under `umad_common.commands` with `add_arguments(parser)` and
`run(args) -> int`; this file only maps verbs to modules, importing a module when its verb runs.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import platform
import sys
from importlib import metadata

from umad_common.commands.checks import InputError
from umad_common.dataflow.api.exit_codes import EXIT_BAD_INPUT, EXIT_STOPPED
from umad_common.dataflow.process.allocator import keep_freed_memory

COMMANDS: dict[tuple[str, ...], tuple[str, str, str]] = {  # words -> (module, what it does, one example)
    ("launch",): (
        "umad_common.commands.launch",
        "start the graph: hub plus one process per operator replica",
        "umad launch graph.yaml --record run.mcap --max-frames 50",
    ),
    ("graph", "check"): ("umad_common.commands.graph_check", "validate a graph.yaml", "umad graph check my_graph.yaml"),
    ("certs",): (
        "umad_common.commands.certs",
        "a CA and certificates for a graph over mutual TLS",
        "umad certs graph.yaml --out certs --host HUB_HOST",
    ),
    ("op", "run"): (
        "umad_common.commands.op_run",
        "run one operator and join a running graph",
        "umad op run diff_ssim --graph graph.yaml --connect tcp/HUB:7447 --replica 1",
    ),
    ("op", "start"): (
        "umad_common.commands.op_control",
        "start an operator in a running graph",
        "umad op start diff_temporal",
    ),
    ("op", "stop"): ("umad_common.commands.op_control", "stop an operator in a running graph", "umad op stop mnad"),
    ("set",): (
        "umad_common.commands.set_param",
        "change an operator parameter at runtime",
        "umad set fusion.weights.ssim=0.5",
    ),
    ("replay",): (
        "umad_common.commands.replay",
        "republish a recorded MCAP log",
        "umad replay run.mcap --record run2.mcap",
    ),
    ("data", "info"): (
        "umad_common.commands.data_info",
        "what UMAD reads of a folder of drives: frames, rate, topics by role, what is missing",
        "umad data info drives/ --topics camera=/front/image_raw",
    ),
    ("generate", "synthetic"): (
        "umad_common.commands.generate",
        "write the built-in synthetic driving benchmark",
        "umad generate synthetic data/synth --normal 2 --anomalous 1 --frames 50",
    ),
    ("train", "world-model"): (
        "umad_common.commands.train_world_model",
        "train the world model on normal drives",
        "umad train world-model data/synth --out models/world_model",
    ),
    ("train", "lidar-head"): (
        "umad_common.commands.train_lidar_head",
        "give a trained world model a lidar head (its other weights unchanged)",
        "umad train lidar-head data/synth --world-model models/world_model.safetensors --out models/world_model",
    ),
    ("train", "features"): (
        "umad_common.commands.train_features",
        "train the label-free perceptual feature net",
        "umad train features data/synth --out models/feature_net.safetensors",
    ),
    ("train", "mnad"): (
        "umad_common.commands.train_mnad",
        "train the MNAD baseline",
        "umad train mnad data/synth --out models/mnad.safetensors",
    ),
    ("train", "segmenter"): (
        "umad_common.commands.train_segmenter",
        "train the label-free segment net",
        "umad train segmenter data/synth --out models/segment_net.safetensors",
    ),
    ("test", "world-model"): (
        "umad_common.commands.test_world_model",
        "held-out PSNR and anomaly/road error ratio",
        "umad test world-model models/world_model.safetensors data/synth",
    ),
    ("calibrate",): (
        "umad_common.commands.calibrate",
        "fit per-metric normalisation on normal frames",
        "umad calibrate data/synth --world-model models/world_model.safetensors --out calibration.json",
    ),
    ("eval",): (
        "umad_common.commands.evaluate",
        "run the full UMAD evaluation and write the report",
        "umad eval --out umad-eval",
    ),
    ("sweep",): (
        "umad_common.commands.sweep",
        "compute the ablation table from a recorded log",
        "umad sweep umad-eval/run.mcap --out resweep",
    ),
    ("compare",): (
        "umad_common.commands.compare",
        "two evaluation runs side by side, B's changes marked",
        "umad compare before after --out before-vs-after",
    ),
    ("bench",): ("umad_common.commands.bench", "side-by-side performance ratios", "umad bench bus --out bench.json"),
}
GROUPS = {  # first word of a two-word verb -> what its verbs do, one example
    "graph": ("check a graph file without starting anything", "umad graph check graph.yaml"),
    "op": ("run, start or stop one operator of a graph", "umad op stop diff_temporal"),
    "data": ("look at drives before using them", "umad data info drives/"),
    "generate": ("write a data set", "umad generate synthetic data/synth"),
    "train": (
        "train a model on normal drives (never reads a label)",
        "umad train mnad data/synth --out mnad.safetensors",
    ),
    "test": (
        "measure a trained model on drives it never saw",
        "umad test world-model world_model.safetensors data/synth",
    ),
}
EXAMPLE = "umad eval --out umad-eval   # the whole evaluation on the built-in benchmark with the shipped models"


class VersionAction(argparse.Action):
    """`umad --version`: UMAD's version and those of the libraries its results depend on most."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, help="print the versions of umad, torch and zenoh, then exit")

    def __call__(self, parser, namespace, values, option_string=None):
        umad, *libraries = (f"{name} {installed_version(dist)}" for name, dist in VERSIONED)
        print(f"{umad} ({', '.join(libraries)}, python {platform.python_version()})")
        parser.exit()


VERSIONED = (("umad", "umad"), ("torch", "torch"), ("zenoh", "eclipse-zenoh"))  # shown name, distribution


def installed_version(distribution: str) -> str:
    """A distribution's installed version, read from its metadata (torch is not imported)."""
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "(not installed)"


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of every verb. Given the command line, only the verb it names gets its arguments
    (the others are listed with what they do): a verb's `add_arguments` may import its module's
    dependencies (pydantic, for `--device`), and a wrong input must be answered fast."""
    named = [word for word in argv if not word.startswith("-")][:2] if argv is not None else None
    parser = argparse.ArgumentParser(
        prog="umad",
        description=__doc__.splitlines()[0],
        epilog=f"example: {EXAMPLE}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action=VersionAction)
    top = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    groups: dict[str, argparse._SubParsersAction] = {}
    for words, (module_name, help_text, example) in COMMANDS.items():
        description = f"{help_text}\n\nexample: {example}"
        raw = argparse.RawDescriptionHelpFormatter
        if len(words) == 1:
            sub = top.add_parser(words[0], help=help_text, description=description, formatter_class=raw)
        else:
            if words[0] not in groups:
                what, group_example = GROUPS[words[0]]
                group = top.add_parser(
                    words[0], help=what, description=f"{what}\n\nexample: {group_example}", formatter_class=raw
                )
                groups[words[0]] = group.add_subparsers(dest="subverb", required=True, metavar="WHAT")
            sub = groups[words[0]].add_parser(words[1], help=help_text, description=description, formatter_class=raw)
        sub.set_defaults(_module=module_name, _words=words)
        if named is None or list(words) == named[: len(words)]:
            importlib.import_module(module_name).add_arguments(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    keep_freed_memory()
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        code = int(importlib.import_module(args._module).run(args) or 0)
    except InputError as exc:  # checked before anything started: one line per problem, nothing written
        for line in str(exc).splitlines():
            print(f"umad {' '.join(args._words)}: {line}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (OSError, ValueError, LookupError) as exc:
        # Bad input (a missing or malformed file, a wrong shape, an unknown name): every such error
        # names what was wrong and what was expected, so the message is the answer. -v: traceback.
        if args.verbose:
            raise
        print(f"umad {' '.join(args._words)}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    if code == EXIT_STOPPED:  # all is closed (the log, the graph): skip the interpreter's teardown,
        logging.shutdown()  # which takes seconds with torch loaded on a busy machine
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
