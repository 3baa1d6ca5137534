"""Plane `inline`: no plane; every payload travels in its Zenoh message as it is. A graph's
`shared_payloads: false`, and a replica whose hub is on another host (`planes.on_this_host`)."""

from __future__ import annotations

import zenoh


class InlinePlane:
    """Plane `inline` (`planes.PayloadPlane`): putting and taking are the identity, nothing is
    declared, fetched or held."""

    name = "inline"

    @staticmethod
    def unfit_cpu(machine: str) -> None:
        return None  # any CPU

    def __init__(self, prefix: str = "", pool_mib: int | None = None, publishing: bool = True):
        pass

    def put(self, payload: bytes) -> bytes:
        return payload

    def declare(self, session: zenoh.Session) -> list:
        return []

    def take(self, raw: bytes) -> bytes | None:
        return raw

    def fetch(self, session: zenoh.Session, prefix: str, raw: bytes) -> bytes | None:
        return None

    def forget_gone(self) -> None:
        pass

    def close(self) -> None:
        pass
