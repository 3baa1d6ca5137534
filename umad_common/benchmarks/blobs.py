"""The bus benches' payloads: what their relay does to each blob, the same in UMAD's chain
(`bus.py`) and in dora-rs's (`dora_relay.py`)."""

from __future__ import annotations

import numpy as np


def checksum(data: np.ndarray) -> int:
    """A sum that reads every byte of `data`: its bytes as little-endian 64-bit words (wrapping),
    the last `nbytes % 8` one by one."""
    raw = data.reshape(-1).view(np.uint8)
    whole = raw.size - raw.size % 8
    return (int(raw[:whole].view("<u8").sum(dtype=np.uint64)) + int(raw[whole:].sum())) % (1 << 64)
