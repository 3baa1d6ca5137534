"""Payload planes: how a large payload travels from a publisher to the subscribers on its host.

A plane is one module here with one class that satisfies `PayloadPlane`, and one line in `PLANES`:

  - `inline`: no plane, the payload travels in the Zenoh message (`inline.py`);
  - `ring`: written once into a shared-memory ring of the publisher's, Zenoh carrying a reference
    to it (`ring.py`); x86 only;
  - `zenoh_shm`: written into a buffer of Zenoh's own shared memory, which Zenoh hands its
    subscribers on this host (`zenoh_shm.py`).

The graph's `shared_payloads` names the plane (true: the ring on x86 and Zenoh's shared memory on
any other CPU, false: inline); `payload_plane` makes that choice and `open_plane` gives a replica
(or the recorder) its one plane object. That object puts with the chosen plane and takes whatever
any plane put on the wire: a subscriber publishes with one plane, yet receives from publishers
that chose another (a worker on another host publishes inline and receives ring references; the
recorder publishes nothing).
"""

from __future__ import annotations

import importlib
import logging
import platform
import socket
from typing import Any, Literal, Protocol, runtime_checkable

import zenoh

INLINE_BELOW = 64 << 10  # smaller payloads travel inline: a copy through Zenoh is as cheap as a reference

# name -> `module:Class` of the plane, a module of this package; the graph's `shared_payloads` names one
PLANES: dict[str, str] = {
    "inline": "inline:InlinePlane",
    "ring": "ring:RingPlane",
    "zenoh_shm": "zenoh_shm:ZenohShmPlane",
}
DEFAULT_PLANE = "ring"  # `shared_payloads: true`, where the CPU allows it (else `FALLBACK_PLANE`)
FALLBACK_PLANE = "zenoh_shm"

PlaneName = Literal[tuple(PLANES)]  # type: ignore[valid-type]  # the names in `PLANES`
SharedPayloads = bool | PlaneName  # the graph's `shared_payloads`

log = logging.getLogger("umad.payloads")


@runtime_checkable
class PayloadPlane(Protocol):
    """One plane: its publishing side (`put`, `declare`) and its subscribing side (`take`, `fetch`,
    `forget_gone`), and `close`. A plane class is built as `Class(prefix, pool_mib, publishing)`:
    `prefix` is where its operator's replicas answer for their payloads (`Keys.payload`), `pool_mib`
    the graph's `shm_pool_mib` (None: the plane's default); `publishing=False` builds it for taking
    only, with no memory of its own to publish from (its `put` then returns the payload as it is)."""

    name: str

    @staticmethod
    def unfit_cpu(machine: str) -> str | None:
        """Why the plane cannot run on a CPU of this `platform.machine()`, or None where it can."""
        ...

    def put(self, payload: bytes) -> bytes | zenoh.ZBytes:
        """What goes on the wire for `payload`: the payload itself when it is smaller than
        `INLINE_BELOW` or the plane has no room, else the plane's description of it."""
        ...

    def declare(self, session: zenoh.Session) -> list[Any]:
        """What the publisher declares on `session` so that subscribers which cannot reach the
        plane's memory still get its payloads (undeclared with the session)."""
        ...

    def take(self, raw: bytes) -> bytes | None:
        """The payload `raw` (as received) stands for, copied out of the plane: `raw` itself when it
        is no description of this plane's; None when the payload cannot be read here (another
        host's memory, or overwritten): `fetch` may still get it."""
        ...

    def fetch(self, session: zenoh.Session, prefix: str, raw: bytes) -> bytes | None:
        """The payload of a `raw` that `take` could not read, asked of its publisher under `prefix`
        (its operator's `Keys.payload`); None when it is gone or `raw` is no description of this plane's."""
        ...

    def forget_gone(self) -> None:
        """Let go of what was mapped for publishers that are gone."""
        ...

    def close(self) -> None:
        """Release the plane's memory, the publisher's and what was mapped for taking."""
        ...


def plane_class(name: str) -> type:
    """The class registered as `name` in `PLANES`."""
    module, _, attr = PLANES[name].partition(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), attr)


class Planes:
    """A replica's one plane object (a `PayloadPlane`): puts with the plane chosen for it and takes
    what any registered plane put on the wire."""

    def __init__(self, name: str, prefix: str = "", pool_mib: int | None = None):
        self.name = name
        self.planes: dict[str, PayloadPlane] = {
            each: plane_class(each)(prefix, pool_mib, publishing=(each == name)) for each in PLANES
        }
        self.chosen = self.planes[name]

    def unfit_cpu(self, machine: str) -> str | None:
        return self.chosen.unfit_cpu(machine)

    def put(self, payload: bytes) -> bytes | zenoh.ZBytes:
        return self.chosen.put(payload)

    def declare(self, session: zenoh.Session) -> list[Any]:
        return self.chosen.declare(session)

    def take(self, raw: bytes) -> bytes | None:
        payload: bytes | None = raw
        for plane in self.planes.values():
            payload = plane.take(payload)
            if payload is None:
                return None
        return payload

    def fetch(self, session: zenoh.Session, prefix: str, raw: bytes) -> bytes | None:
        for plane in self.planes.values():
            payload = plane.fetch(session, prefix, raw)
            if payload is not None:
                return payload
        return None

    def forget_gone(self) -> None:
        for plane in self.planes.values():
            plane.forget_gone()

    def close(self) -> None:
        for plane in self.planes.values():
            plane.close()


def open_plane(name: str = "inline", prefix: str = "", pool_mib: int | None = None) -> Planes:
    """The plane object of a replica that publishes with plane `name` (`payload_plane`) under
    `prefix` (its operator's `Keys.payload`); the default, `inline`, for one that only takes."""
    return Planes(name, prefix, pool_mib)


def payload_plane(shared_payloads: SharedPayloads, machine: str | None = None) -> str:
    """Which plane a replica's large payloads take, by the graph's `shared_payloads` and this CPU
    (`machine`: `platform.machine()`); says in one line when this CPU rules the ring out."""
    if shared_payloads is False:
        return "inline"
    name = DEFAULT_PLANE if shared_payloads is True else shared_payloads
    machine = machine or platform.machine()
    unfit = plane_class(name).unfit_cpu(machine)
    if unfit:
        log.info("%s and this CPU is %s: large payloads go through Zenoh's shared memory", unfit, machine)
        return FALLBACK_PLANE
    return name


def on_this_host(endpoint: str) -> bool:
    """Whether a hub endpoint (`tcp/HOST:PORT`) is an address of this machine: a replica that reaches
    its hub elsewhere is a worker on another host, whose subscribers would all have to fetch its
    payloads one by one, so it sends them inline instead."""
    host = endpoint.partition("/")[2].rpartition(":")[0].strip("[]")
    try:
        for family, kind, proto, _, address in socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM):
            with socket.socket(family, kind, proto) as probe:
                probe.bind((address[0], 0))  # only an address of this host's interfaces can be bound
        return True
    except OSError:
        return False
