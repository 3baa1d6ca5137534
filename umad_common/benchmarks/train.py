"""`umad bench train [--nproc N] [--data DIR]`: world-model training samples/s in one process and in N.

Both trainings run in this bench, one after the other, on the same normal drives with the same
model, seed, epochs and steps: one process with all `threads`, then N processes
(`umad_common.training.distributed`, gloo or NCCL) sharing them. Each step trains the same
`batch_size` windows either way, so the figure is the training's own `samples_per_second`
(windows per second of its steps, without loading the drives or starting the processes) and the
ratio of N processes to one. Without `--data`, four short normal drives of the built-in world are
generated on the validation seed (2), three of them trained on (the last is held out as always).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

BENCH_SEED = 2  # neither the training seed (0) nor the evaluation seed (1)
BUILTIN_DRIVES, BUILTIN_FRAMES = 4, 64


def bench_train(processes: int = 2, data: Path | None = None, epochs: int = 2, threads: int = 2) -> dict:
    if processes < 2:
        raise ValueError(f"--nproc {processes}: the bench compares one process with more; expected at least 2")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `umad train` runs: no spinning on a shared machine
    with tempfile.TemporaryDirectory(prefix="umad-bench-train-") as folder:
        return _one_and_many(Path(folder), processes, data, epochs, threads)


def _one_and_many(work: Path, processes: int, data: Path | None, epochs: int, threads: int) -> dict:
    from umad_common.models.device import resolve_device
    from umad_common.models.weights import weight_paths
    from umad_common.training.distributed import run_processes
    from umad_common.training.train_world_model import train_world_model

    if data is None:
        from umad_common.datasets.synthetic.generator import generate_benchmark

        data = work / "drives"
        generate_benchmark(data, BUILTIN_DRIVES, 0, BUILTIN_FRAMES, BENCH_SEED, (384, 256), workers=os.cpu_count() or 1)
        print(f"generated {BUILTIN_DRIVES} normal drives of {BUILTIN_FRAMES} frames, seed {BENCH_SEED}", flush=True)
    device = str(resolve_device("auto"))
    training = dict(data=data, epochs=epochs, seed=0, device=device)
    train_world_model(out=work / "one", threads=threads, **training)
    run_processes(
        processes, train_world_model, dict(out=work / "many", threads=max(1, threads // processes), **training)
    )
    one, many = (json.loads(weight_paths(work / name)[1].read_text()) for name in ("one", "many"))
    return {
        "device": device,
        "processes": [1, processes],
        "threads_per_process": [one["threads"], many["threads"]],
        "windows_per_step": one["train_config"]["batch_size"],
        "epochs": epochs,
        "samples_per_second": [one["samples_per_second"], many["samples_per_second"]],
        "ratio": round(many["samples_per_second"] / one["samples_per_second"], 3),
        "final_loss": [round(one["history"][-1]["loss"], 5), round(many["history"][-1]["loss"], 5)],
    }
