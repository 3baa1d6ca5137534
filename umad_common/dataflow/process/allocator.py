"""How a UMAD process asks the C allocator to keep the memory it frees for its next frame.

By default glibc serves a request of 128 KiB or more (the bytes of a 1 MiB frame message, a numpy
temporary the size of a camera image) with a fresh `mmap` and unmaps it when it is freed (the
threshold only rises to the size of buffers freed so far), and gives the top of its heap back to
the kernel once twice that lies free there. A process that handles a stream of frames then pays a
page fault for every 4 KiB of every such buffer, frame after frame: encoding a 1 MiB frame message
then costs many times one copy of its bytes (docs/experiments.md). With large buffers served from
the heap and the heap kept, the memory a frame freed is there for the next one.
`keep_freed_memory` says so once at process start: every `umad` command and every operator
replica call it. A process keeps at most `TRIM_THRESHOLD_BYTES` of freed memory.
"""

from __future__ import annotations

import ctypes
import logging

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's largest allowed value: smaller requests come from the heap
TRIM_THRESHOLD_BYTES = 64 << 20  # free memory the heap keeps at its top before returning it (per process:
#   a graph of 15 replicas may hold up to 1 GiB more than it uses)

log = logging.getLogger("umad.allocator")


def keep_freed_memory() -> bool:
    """Raise this process's glibc mmap and trim thresholds; False where the C library is not glibc
    (musl, macOS): nothing changes there."""
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library this process already runs on
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    done = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    if not done:
        log.debug("mallopt refused the thresholds; the allocator keeps its defaults")
    return done
