"""Work shared among processes: the pool that runs shares 1 .. n - 1 of a pass beside the caller's
share 0, and how a pass deals its items out among the shares.

Every share reads the whole log; a share scores only what is dealt to it, so the pooled figures are
one process's (each pass puts its shares' parts back in the order of one read).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from contextlib import ExitStack

from umad_common.dataflow.process.replica import one_blas_thread


def share_pool(stack: ExitStack, workers: int) -> ProcessPoolExecutor:
    """The processes of shares 1 .. workers - 1 (share 0 is the caller's), each with one BLAS thread:
    BLAS threads spinning beside the other shares' waste their CPU (docs/experiments.md)."""
    spawn = multiprocessing.get_context("spawn")
    return stack.enter_context(ProcessPoolExecutor(workers - 1, mp_context=spawn, initializer=one_blas_thread))


def dealt(position: int, share: tuple[int, int]) -> bool:
    """Whether the item at `position` of a sequence dealt out in turn falls to `share` (index, count)."""
    index, count = share
    return position % count == index
