"""Large payloads through Zenoh's own shared memory (`zenoh.shm`), and which same-host data plane a
replica uses.

A publisher's `ZenohShmPayloads` owns a pool (a `ShmProvider`); `pack(payload)` writes a large
payload into a buffer of the pool and hands Zenoh that buffer. Subscribers on this host receive the
buffer itself (Zenoh passes its handle, not its bytes), subscribers on other hosts and the
recorder the bytes over the network, as for any payload: the bytes are the publisher's, so
recordings and replays are unchanged, and nobody needs to fetch. A buffer returns to the pool when
the last subscriber dropped its sample; a pool with no room left (subscribers holding every buffer)
sends that payload through the sockets instead of blocking the publisher.

What the Python API of Zenoh 1.10 allows: a buffer is written from a `bytes` object and read into
one (`ZShmMut.__setitem__`, `ZBytes.to_bytes`), with no memoryview on either side. So a payload is
copied into the pool once and out of it once; `messages.decode` then reads the arrays in place, as
views on the bytes taken. Zenoh keeps each buffer's reference count with atomics, which is correct
on every CPU.

The choice (`payload_plane`): the graph's `shared_payloads` true takes the project's payload ring
(`payload_ring.py`) on x86, where it measures faster (docs/benchmarks.md: the payload planes), and
Zenoh's shared memory on any other CPU, where the ring's overwrite check is not sound;
`zenoh_shm` takes Zenoh's shared memory on every CPU; false sends every payload through Zenoh as
it is.
"""

from __future__ import annotations

import logging
import platform
from typing import Literal

import zenoh
from zenoh.shm import GarbageCollect, ShmProvider

from umad_common.dataflow.transport.payload_ring import INLINE_BELOW, ring_is_correct_here

DEFAULT_POOL_MIB = 64  # a source's window of 1 MiB frames several times over, per publishing replica
log = logging.getLogger("umad.payloads")

SharedPayloads = bool | Literal["zenoh_shm"]  # the graph's `shared_payloads`


class ZenohShmPayloads:
    """A publisher's pool in Zenoh's shared memory; `pack` turns a large payload into a buffer of it."""

    def __init__(self, pool_mib: int = DEFAULT_POOL_MIB):
        self.through_sockets = 0  # payloads that found the pool full
        self.disabled_because: str | None = None
        try:
            self.provider: ShmProvider | None = ShmProvider.default_backend(pool_mib << 20)
        except zenoh.ZError as exc:  # e.g. a container's /dev/shm smaller than the pool
            self.provider = None
            self.disabled_because = f"no {pool_mib} MiB pool in Zenoh's shared memory ({exc}); payloads go as they are"
            log.warning("%s", self.disabled_because)

    def pack(self, payload: bytes) -> zenoh.ZBytes | bytes:
        """`payload` in a shared-memory buffer, or as it is when small, when the pool is full or
        when there is no pool."""
        size = len(payload)
        if size < INLINE_BELOW or self.provider is None:
            return payload
        try:
            buffer = self.provider.alloc(size, GarbageCollect())
        except zenoh.ZError:
            self.through_sockets += 1
            return payload
        buffer[0:size] = payload
        return zenoh.ZBytes(buffer)


def payload_plane(shared_payloads: SharedPayloads, machine: str | None = None) -> Literal["ring", "zenoh_shm"] | None:
    """Which same-host data plane a replica's large payloads take (None: as they are, through
    Zenoh); says in one line when this CPU rules the ring out."""
    if shared_payloads is False:
        return None
    if shared_payloads == "zenoh_shm":
        return "zenoh_shm"
    if ring_is_correct_here(machine):
        return "ring"
    log.info(
        "payload rings need x86's memory order and this CPU is %s: large payloads go through Zenoh's shared memory",
        machine or platform.machine(),
    )
    return "zenoh_shm"
