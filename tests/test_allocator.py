import json
import subprocess
import sys

import pytest

PROBE = """
import json, sys
from umad_common.dataflow.process.allocator import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else None
block = bytes(8 << 20)
heap = [line.split()[0] for line in open("/proc/self/maps") if line.rstrip().endswith("[heap]")]
low, high = (int(x, 16) for x in heap[0].split("-"))
print(json.dumps({"kept": kept, "in_heap": low <= id(block) < high}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and /proc/self/maps")
def test_keep_freed_memory_serves_large_buffers_from_the_heap():
    """By default glibc maps an 8 MiB buffer on its own (and unmaps it when freed); once a process
    keeps freed memory, the buffer comes from the heap, which keeps what is freed."""

    def probe(mode: str) -> dict:
        out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
        return json.loads(out.stdout)

    assert probe("default") == {"kept": None, "in_heap": False}
    assert probe("keep") == {"kept": True, "in_heap": True}
