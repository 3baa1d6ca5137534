"""One training in several processes: torch.distributed with DistributedDataParallel (DDP).

Each process (a rank) trains on its share of every optimizer step's windows; DDP averages the
gradients of all ranks after each backward pass, so every rank takes the same optimizer step and
holds the same weights. The backend is gloo on the CPU and NCCL on CUDA (one GPU per rank: its
local rank). Only rank 0 writes files and shows progress.

Two ways to start the ranks:

- `run_processes(n, target, kwargs)`: n processes on this machine (torch.multiprocessing), meeting
  on 127.0.0.1 at a free port; what `umad train world-model --nproc N` does;
- torchrun, for one or several machines: each process it starts reads RANK, WORLD_SIZE,
  LOCAL_RANK, LOCAL_WORLD_SIZE, MASTER_ADDR and MASTER_PORT from the environment torchrun sets
  (`started_by_torchrun`, `run_rank`).

A training with one process and no torchrun runs none of this: it is the plain loop, writing the
same files as before processes existed.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

TORCHRUN_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


@dataclass(frozen=True)
class Rank:
    """Where this process stands in a training."""

    index: int = 0  # this process's rank, 0 .. world - 1; rank 0 writes the files
    world: int = 1  # processes in the training, on every machine together
    local: int = 0  # rank among this machine's processes: its GPU under NCCL

    @property
    def distributed(self) -> bool:
        return self.world > 1 or torch.distributed.is_initialized()

    @property
    def writes(self) -> bool:
        """Whether this rank writes the files and shows the progress (rank 0)."""
        return self.index == 0

    def device(self, device: torch.device) -> torch.device:
        """This rank's device: its own GPU (cuda:local) when training on CUDA across processes."""
        if device.type == "cuda" and self.distributed:
            return torch.device("cuda", self.local)
        return device

    def share(self, items: list) -> list:
        """This rank's share of one step's items: every world-th one from its index on (as torch's
        DistributedSampler splits an epoch), so the ranks' shares together are the items, each once."""
        return items[self.index :: self.world]

    def mean(self, values: dict[str, float]) -> dict[str, float]:
        """Each value averaged over the ranks (float64 all-reduce); the values themselves in one process."""
        if not self.distributed:
            return values
        tensor = torch.tensor(list(values.values()), dtype=torch.float64)
        torch.distributed.all_reduce(tensor)
        return {key: float(value) / self.world for key, value in zip(values, tensor.tolist(), strict=True)}

    def from_rank_zero(self, value: Any) -> Any:
        """Rank 0's `value` on every rank (a picklable object, such as a checkpoint read by rank 0 only)."""
        if not self.distributed:
            return value
        box = [value if self.writes else None]
        torch.distributed.broadcast_object_list(box, src=0)
        return box[0]


def started_by_torchrun() -> bool:
    """Whether this process is one rank of a torchrun launch (its environment names rank and world)."""
    return all(name in os.environ for name in TORCHRUN_VARIABLES)


def processes_on_this_machine() -> int:
    """How many ranks share this machine: torchrun's LOCAL_WORLD_SIZE, else 1."""
    return int(os.environ.get("LOCAL_WORLD_SIZE", "1"))


def run_rank(target: Callable[..., Any], kwargs: dict[str, Any]) -> Any:
    """Join the process group that the environment describes (gloo, or NCCL when `kwargs["device"]`
    is CUDA), run `target(rank=..., **kwargs)` as this rank, and leave the group."""
    missing = [name for name in TORCHRUN_VARIABLES if name not in os.environ]
    if missing:
        raise RuntimeError(f"a training rank needs {', '.join(missing)} in its environment (torchrun sets them)")
    rank = Rank(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"]), int(os.environ["LOCAL_RANK"]))
    cuda = torch.device(kwargs.get("device", "cpu")).type == "cuda"
    if cuda:
        torch.cuda.set_device(rank.local)
    torch.distributed.init_process_group("nccl" if cuda else "gloo", rank=rank.index, world_size=rank.world)
    try:
        result = target(rank=rank, **kwargs)
        torch.distributed.barrier()  # rank 0 has written its last files before anyone leaves
        return result
    finally:
        torch.distributed.destroy_process_group()


def run_processes(processes: int, target: Callable[..., Any], kwargs: dict[str, Any]) -> None:
    """`target(rank=..., **kwargs)` in `processes` ranks on this machine, started with
    torch.multiprocessing and meeting on 127.0.0.1 at a free port; returns when all have finished.
    A rank that fails stops the others, and its error is raised here."""
    if processes < 1:
        raise ValueError(f"processes {processes}: expected at least 1")
    port = _free_port()
    torch.multiprocessing.spawn(_spawned_rank, args=(processes, port, target, kwargs), nprocs=processes, join=True)


def _spawned_rank(local: int, processes: int, port: int, target: Callable[..., Any], kwargs: dict[str, Any]) -> None:
    os.environ.update(
        RANK=str(local),
        WORLD_SIZE=str(processes),
        LOCAL_RANK=str(local),
        LOCAL_WORLD_SIZE=str(processes),
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
    )
    run_rank(target, kwargs)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]
