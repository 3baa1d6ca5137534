"""The payload ring (plane `ring`): a large payload is written once into a shared-memory ring its publisher
owns, and Zenoh carries only a reference to it (a few dozen bytes) through the hub.

Why: a large message through Zenoh costs its publisher's put, the hub's routing and the
subscriber's take, each a copy of the whole payload (`umad bench bus` measures them); with the ring
a hop costs one copy in, one copy out and a small message.

A ring is a file under /dev/shm named after its publisher's pid:

    header (64 bytes): magic, capacity, `reserved` (the end of the newest write, in bytes ever written)
    data: `capacity` bytes, written round and round; a payload never wraps (it starts over at 0)

The publisher raises `reserved` before it writes a payload's bytes, so a reader that copied a
payload out and then finds `reserved <= start + capacity` knows nothing overwrote it meanwhile.
That check relies on x86's memory order (stores become visible in program order, loads are not
reordered with older loads), which Python cannot ask for with fences; on any other CPU
(`RING_CPUS`) no ring is made and large payloads go through Zenoh's shared memory instead
(`zenoh_shm.py`). Subscribers copy a payload out the moment it arrives; the ring holds at least
`SLACK_PAYLOADS` of the largest payload so far (it grows into a new file when a larger one comes),
far more than the frames a source keeps in flight.

What a reference cannot reach, the publisher still serves: a subscriber on another host (or one
that copied too late) asks the publisher's queryable for the payload, answered from the last
payloads the publisher keeps (`fetch`). The bytes a subscriber ends up with are the bytes the
publisher wrote, so recorded logs and replays are unchanged.

`RingPlane` is the plane (`planes.PayloadPlane`): a publisher's `PayloadRing`, a subscriber's
`PayloadReader` and `fetch`.
"""

from __future__ import annotations

import mmap
import os
import platform
import re
import secrets
import struct
import threading
from collections import OrderedDict
from collections.abc import Collection
from pathlib import Path

import zenoh

from umad_common.dataflow.transport.planes import INLINE_BELOW

RING_DIR = Path(os.environ.get("UMAD_RING_DIR", "/dev/shm"))  # e.g. a container whose /dev/shm is small
SWEPT_BY_LAUNCHER = "UMAD_RINGS_SWEPT_BY_LAUNCHER"  # set in a replica's environment by the launcher, which
#   then removes the replica's ring some time after it exited (`remove_stale_rings`), not the replica
#   itself: the launcher's recorder may still have references to it in its queue
REFERENCE_TAG = b"\xc1umad-ref"  # 0xc1 is never valid msgpack: a reference is never taken for a message
SLACK_PAYLOADS = 32  # the ring holds at least this many of its largest payload
MIN_CAPACITY = 8 << 20
MAX_CAPACITY = 1 << 30
KEPT_FOR_FETCH = 64  # payloads a publisher can still serve to a subscriber that cannot map its ring
FETCH_TIMEOUT_S = 5.0

_MAGIC = b"umadring"
_HEADER = 64
_RESERVED_AT = 16
_ALIGN = 64
_REFERENCE = struct.Struct("<QQ")  # start (in bytes ever written), length; then the ring's file name
_RING_NAME = re.compile(r"^umad-(\d+)-([0-9a-f]+)-(\d+)\.ring$")
# what `platform.machine()` says on a CPU with x86's memory order
RING_CPUS = frozenset({"x86_64", "amd64", "i386", "i686", "x86"})


def ring_is_correct_here(machine: str | None = None) -> bool:
    """Whether this CPU (`machine`: `platform.machine()`) keeps the store and load order the
    reader's overwrite check relies on."""
    return (machine or platform.machine()).lower() in RING_CPUS


def is_reference(payload: bytes) -> bool:
    return payload[: len(REFERENCE_TAG)] == REFERENCE_TAG


def _parse(reference: bytes) -> tuple[str, int, int]:
    """(ring file name, start, length) of a reference; ValueError for anything else."""
    body = reference[len(REFERENCE_TAG) :]
    if len(body) <= _REFERENCE.size:
        raise ValueError("truncated payload reference")
    start, length = _REFERENCE.unpack_from(body)
    name = body[_REFERENCE.size :].decode("ascii", errors="replace")
    if not _RING_NAME.match(name):
        raise ValueError(f"payload reference names {name!r}, which is no payload ring")
    return name, start, length


def fetch_key(prefix: str, reference: bytes) -> str:
    """Where the publisher of `reference` answers for its payloads: `<prefix>/<pid>-<id>`, the prefix
    being its operator's (`Keys.payload`), so access control can let only that operator answer."""
    match = _RING_NAME.match(_parse(reference)[0])
    assert match is not None
    return f"{prefix}/{match[1]}-{match[2]}"


class PayloadRing:
    """A publisher's side: `pack(payload)` writes a large payload into the ring and returns its
    reference (a small payload comes back unchanged). Not thread-safe: one publishing thread."""

    def __init__(self, prefix: str, directory: Path = RING_DIR):
        self.directory = directory
        self.ident = f"{os.getpid()}-{secrets.token_hex(4)}"
        self.fetch_key = f"{prefix}/{self.ident}"
        self.generation = 0
        self.capacity = 0
        self.name = ""
        self.previous_name = ""  # the ring this one grew from, kept until the next growth (see `_grow`)
        self._map: mmap.mmap | None = None
        self._view: memoryview | None = None  # writes through a memoryview copy: faster than mmap's own
        self._head = 0
        self._kept: OrderedDict[tuple[str, int], bytes] = OrderedDict()
        self.disabled_because: str | None = None
        if not ring_is_correct_here():
            self.disabled_because = (
                f"payload rings need x86's memory order and this CPU is {platform.machine()}; "
                "large payloads go through Zenoh's shared memory"
            )

    def pack(self, payload: bytes) -> bytes:
        size = len(payload)
        if size < INLINE_BELOW or self.disabled_because or size * SLACK_PAYLOADS > MAX_CAPACITY:
            return payload
        if size * SLACK_PAYLOADS > self.capacity and not self._grow(size * SLACK_PAYLOADS):
            return payload
        assert self._map is not None and self._view is not None
        start = self._head
        offset = start % self.capacity
        if offset + size > self.capacity:  # never wrap a payload: start over at the ring's beginning
            start += self.capacity - offset
            offset = 0
        struct.pack_into("<Q", self._map, _RESERVED_AT, start + size)  # announce, then overwrite
        self._view[_HEADER + offset : _HEADER + offset + size] = payload
        self._head = -(-(start + size) // _ALIGN) * _ALIGN
        self._kept[(self.name, start)] = payload
        if len(self._kept) > KEPT_FOR_FETCH:
            self._kept.popitem(last=False)
        return REFERENCE_TAG + _REFERENCE.pack(start, size) + self.name.encode("ascii")

    def _grow(self, wanted: int) -> bool:
        """Move to a new, larger ring file. The old file stays until the next growth: a subscriber
        that had not mapped it yet still reads the payloads referenced just before the move (a
        source's first frame, whose next output is larger). Readers keep mappings until they forget them."""
        capacity = max(MIN_CAPACITY, 1 << (wanted - 1).bit_length())
        name = f"umad-{self.ident}-{self.generation + 1}.ring"
        path = self.directory / name
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError as exc:
            self.disabled_because = f"cannot create {path}: {exc.strerror}"
            return False
        try:
            os.posix_fallocate(fd, 0, _HEADER + capacity)  # fail now, not with SIGBUS on a full /dev/shm
            new = mmap.mmap(fd, _HEADER + capacity)
        except OSError as exc:
            os.close(fd)
            path.unlink(missing_ok=True)
            self.disabled_because = f"no room for a {capacity >> 20} MiB ring in {self.directory}: {exc.strerror}"
            return False
        os.close(fd)
        new[: len(_MAGIC)] = _MAGIC
        struct.pack_into("<QQ", new, len(_MAGIC), capacity, 0)
        if self.previous_name:
            (self.directory / self.previous_name).unlink(missing_ok=True)
        self._unmap()
        self.previous_name = self.name
        self._map, self._view, self.name, self.capacity, self._head = new, memoryview(new), name, capacity, 0
        self.generation += 1
        return True

    def serve(self, query: zenoh.Query) -> None:
        """The queryable's callback: answer a fetch with the payload, if still kept."""
        try:
            name, start, _ = _parse(query.payload.to_bytes() if query.payload else b"")
            payload = self._kept.get((name, start))
            if payload is not None:
                query.reply(query.key_expr, payload)
        except ValueError:
            pass
        finally:
            query.drop()

    def close(self, unlink: bool = True) -> None:
        """Unmap the ring and unlink its files, this one and the one it grew from (mappings others
        hold stay readable until they drop them); `unlink=False` leaves them to the launcher's sweep."""
        self._unmap()
        if unlink:
            for name in (self.name, self.previous_name):
                if name:
                    (self.directory / name).unlink(missing_ok=True)

    def _unmap(self) -> None:
        if self._map is not None:
            assert self._view is not None
            self._view.release()
            self._map.close()
            self._map = self._view = None


class PayloadReader:
    """A subscriber's side: `take(payload)` returns the payload a reference points to, copied out of
    the ring, or the payload itself when it travelled inline; None when the ring is not reachable
    from here (another host) or was overwritten while it was copied: `fetch` then asks the
    publisher. Thread-safe: Zenoh's callbacks take, another thread may forget."""

    def __init__(self, directory: Path = RING_DIR):
        self.directory = directory
        self._maps: dict[str, mmap.mmap | None] = {}
        self._lock = threading.Lock()

    def take(self, payload: bytes) -> bytes | None:
        if not is_reference(payload):
            return payload
        try:
            name, start, length = _parse(payload)
        except ValueError:
            return payload  # not ours to judge: decoding says what is wrong with it
        with self._lock:
            ring = self._maps[name] if name in self._maps else self._open(name)
            if ring is None:
                return None
            capacity = len(ring) - _HEADER
            offset = start % capacity
            if length > capacity - offset:
                return None
            with memoryview(ring) as whole:
                copied = bytes(whole[_HEADER + offset : _HEADER + offset + length])
            (reserved,) = struct.unpack_from("<Q", ring, _RESERVED_AT)
            return copied if start + length <= reserved <= start + capacity else None

    def _open(self, name: str) -> mmap.mmap | None:
        try:
            fd = os.open(self.directory / name, os.O_RDONLY)
        except OSError:
            self._maps[name] = None  # another host's ring, or gone: fetch from now on
            return None
        try:
            ring = mmap.mmap(fd, 0, prot=mmap.PROT_READ)
        except (OSError, ValueError):
            ring = None
        finally:
            os.close(fd)
        if ring is not None and ring[: len(_MAGIC)] != _MAGIC:
            ring.close()
            ring = None
        self._maps[name] = ring
        return ring

    def forget_gone(self) -> None:
        """Drop the mappings of rings whose file is gone (a publisher that moved on or exited)."""
        with self._lock:
            for name, ring in list(self._maps.items()):
                if not (self.directory / name).exists():
                    if ring is not None:
                        ring.close()
                    del self._maps[name]

    def close(self) -> None:
        with self._lock:
            for ring in self._maps.values():
                if ring is not None:
                    ring.close()
            self._maps.clear()


def fetch(session: zenoh.Session, prefix: str, reference: bytes) -> bytes | None:
    """Ask the publisher of `reference` for its payload under `prefix` (its operator's
    `Keys.payload`); None if it no longer has it (or is gone)."""
    try:
        key = fetch_key(prefix, reference)
    except ValueError:
        return None
    try:
        for reply in session.get(key, payload=reference, timeout=FETCH_TIMEOUT_S):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
    except zenoh.ZError:  # the session closed meanwhile (the launcher stopping)
        pass
    return None


def remove_stale_rings(directory: Path = RING_DIR, spare_pids: Collection[int] = ()) -> list[str]:
    """Unlink ring files whose publisher process is gone (a replica killed before it could, or one
    the launcher sweeps after), except those of `spare_pids`."""
    removed = []
    for path in directory.glob("umad-*.ring") if directory.is_dir() else []:
        match = _RING_NAME.match(path.name)
        if match and int(match[1]) not in spare_pids and not Path(f"/proc/{match[1]}").exists():
            path.unlink(missing_ok=True)
            removed.append(path.name)
    return removed


class RingPlane:
    """Plane `ring` (`planes.PayloadPlane`): puts into this replica's `PayloadRing`, takes through a
    `PayloadReader`; its queryable serves the payloads a subscriber could not map (`fetch`)."""

    name = "ring"

    @staticmethod
    def unfit_cpu(machine: str) -> str | None:
        return None if ring_is_correct_here(machine) else "payload rings need x86's memory order"

    def __init__(
        self,
        prefix: str = "",
        pool_mib: int | None = None,
        publishing: bool = True,
        *,
        directory: Path | None = None,
    ):
        directory = RING_DIR if directory is None else directory
        self.ring = PayloadRing(prefix, directory) if publishing else None
        self.reader = PayloadReader(directory)

    def put(self, payload: bytes) -> bytes:
        return payload if self.ring is None else self.ring.pack(payload)

    def declare(self, session: zenoh.Session) -> list[zenoh.Queryable]:
        return [] if self.ring is None else [session.declare_queryable(self.ring.fetch_key, self.ring.serve)]

    def take(self, raw: bytes) -> bytes | None:
        return self.reader.take(raw)

    def fetch(self, session: zenoh.Session, prefix: str, raw: bytes) -> bytes | None:
        return fetch(session, prefix, raw) if is_reference(raw) else None

    def forget_gone(self) -> None:
        self.reader.forget_gone()

    def close(self) -> None:
        """A replica the launcher started leaves its ring's files to the launcher's sweep
        (`SWEPT_BY_LAUNCHER`): the recorder may still copy payloads out of them."""
        self.reader.close()
        if self.ring is not None:
            self.ring.close(unlink=SWEPT_BY_LAUNCHER not in os.environ)
