"""The `umad` command: one verb per step of a user's work.

Each verb lives in its own module under `umad_common.commands` with `add_arguments(parser)` and
`run(args) -> int`; this file only maps verbs to modules, importing a module when its verb runs.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from umad_common.commands.checks import InputError
from umad_common.dataflow.allocator import keep_freed_memory
from umad_common.dataflow.exit_codes import EXIT_BAD_INPUT, EXIT_STOPPED

COMMANDS: dict[tuple[str, ...], tuple[str, str]] = {
    ("launch",): ("umad_common.commands.launch", "start the graph: hub plus one process per operator replica"),
    ("graph", "check"): ("umad_common.commands.graph_check", "validate a graph.yaml"),
    ("op", "run"): ("umad_common.commands.op_run", "run one operator and join a running graph"),
    ("op", "start"): ("umad_common.commands.op_control", "start an operator in a running graph"),
    ("op", "stop"): ("umad_common.commands.op_control", "stop an operator in a running graph"),
    ("set",): ("umad_common.commands.set_param", "change an operator parameter at runtime"),
    ("replay",): ("umad_common.commands.replay", "republish a recorded MCAP log"),
    ("generate", "synthetic"): ("umad_common.commands.generate", "write the built-in synthetic driving benchmark"),
    ("train", "world-model"): ("umad_common.commands.train_world_model", "train the world model on normal drives"),
    ("train", "features"): ("umad_common.commands.train_features", "train the label-free perceptual feature net"),
    ("train", "mnad"): ("umad_common.commands.train_mnad", "train the MNAD baseline"),
    ("train", "segmenter"): ("umad_common.commands.train_segmenter", "train the label-free segment net"),
    ("test", "world-model"): ("umad_common.commands.test_world_model", "held-out PSNR and anomaly/road error ratio"),
    ("calibrate",): ("umad_common.commands.calibrate", "fit per-metric normalisation on normal frames"),
    ("eval",): ("umad_common.commands.evaluate", "run the full UMAD evaluation and write the report"),
    ("sweep",): ("umad_common.commands.sweep", "compute the ablation table from a recorded log"),
    ("compare",): ("umad_common.commands.compare", "two evaluation runs side by side, B's changes marked"),
    ("bench",): ("umad_common.commands.bench", "side-by-side performance ratios"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="umad", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    top = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    groups: dict[str, argparse._SubParsersAction] = {}
    for words, (module_name, help_text) in COMMANDS.items():
        if len(words) == 1:
            sub = top.add_parser(words[0], help=help_text, description=help_text)
        else:
            if words[0] not in groups:
                group = top.add_parser(words[0], help=f"{words[0]} ...")
                groups[words[0]] = group.add_subparsers(dest="subverb", required=True, metavar="WHAT")
            sub = groups[words[0]].add_parser(words[1], help=help_text, description=help_text)
        sub.set_defaults(_module=module_name, _words=words)
        importlib.import_module(module_name).add_arguments(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    keep_freed_memory()
    parser = build_parser()
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
