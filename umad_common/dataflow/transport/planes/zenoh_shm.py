"""Plane `zenoh_shm`: large payloads through Zenoh's own shared memory (`zenoh.shm`).

A publisher's `ZenohShmPayloads` owns a pool (a `ShmProvider`); `pack(payload)` writes a large
payload into a buffer of the pool and hands Zenoh that buffer. Subscribers on this host receive the
buffer itself (Zenoh passes its handle, not its bytes), subscribers on other hosts and the
recorder the bytes over the network, as for any payload: the bytes are the publisher's, so
recordings and replays are unchanged, and nobody needs to fetch. A buffer returns to the pool when
the last subscriber dropped its sample; a pool with no room left (subscribers holding every buffer)
sends that payload through the sockets instead of blocking the publisher. The pool is made at the
first large payload, so a replica that publishes with another plane (or only takes) makes none.

What the Python API of Zenoh 1.10 allows: a buffer is written from a `bytes` object and read into
one (`ZShmMut.__setitem__`, `ZBytes.to_bytes`), with no memoryview on either side. So a payload is
copied into the pool once and out of it once; `messages.decode` then reads the arrays in place, as
views on the bytes taken. Zenoh keeps each buffer's reference count with atomics, which is correct
on every CPU, so this plane is the ring's stand-in where the ring's overwrite check is not sound
(`planes.payload_plane`).
"""

from __future__ import annotations

import logging

import zenoh
from zenoh.shm import GarbageCollect, ShmProvider

from umad_common.dataflow.transport.planes import INLINE_BELOW
from umad_common.dataflow.transport.planes.inline import InlinePlane

DEFAULT_POOL_MIB = 64  # a source's window of 1 MiB frames several times over, per publishing replica
log = logging.getLogger("umad.payloads")


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


class ZenohShmPlane(InlinePlane):
    """Plane `zenoh_shm` (`planes.PayloadPlane`): puts into this replica's `ZenohShmPayloads`. Zenoh
    delivers the bytes themselves, so the subscribing side is the inline plane's: taking is the
    identity and nothing is ever fetched."""

    name = "zenoh_shm"

    def __init__(self, prefix: str = "", pool_mib: int | None = None, publishing: bool = True):
        self.payloads = ZenohShmPayloads(pool_mib or DEFAULT_POOL_MIB) if publishing else None

    def put(self, payload: bytes) -> zenoh.ZBytes | bytes:
        return payload if self.payloads is None else self.payloads.pack(payload)
