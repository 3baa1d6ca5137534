"""The frame message every operator speaks: a msgpack map with a header and numpy arrays.

Wire format (version 1)::

    {v: 1, run: str, seq: int, stamp_ns: int, producer: str, meta: {...},
     arrays: {name: {dtype: "<f4", shape: [..], data: <raw little-endian bytes>}}}

Boolean arrays (`|b1`, e.g. a segmenter's (K, h, w) masks) travel bit-packed (`np.packbits`, C
order, ceil(n / 8) bytes): eight times less on the bus and in the log.

Decoding never trusts the sender: the version, every dtype (a whitelist), every shape and the byte
length are checked before a single array is built, and a size cap stops memory bombs.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

VERSION = 1
MAX_MESSAGE_BYTES = 256 * 1024 * 1024
MAX_ARRAYS = 64
MAX_NDIM = 6
ALLOWED_DTYPES = frozenset(["|u1", "|i1", "|b1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"])


class MessageError(ValueError):
    """A payload that is not a valid UMAD frame message (says what was wrong and what was expected)."""


@dataclass
class Message:
    """One frame's worth of one output: header fields, free-form metadata and named arrays."""

    run: str
    seq: int
    stamp_ns: int = 0
    producer: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def frame_id(self) -> str:
        return f"{self.run}#{self.seq}"


def _wire_dtype(arr: np.ndarray) -> np.dtype:
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    if dt.str not in ALLOWED_DTYPES:
        raise MessageError(f"array dtype {arr.dtype} cannot be sent; expected one of {sorted(ALLOWED_DTYPES)}")
    return dt


def encode(msg: Message) -> bytes:
    """Serialise a message; arrays travel as raw little-endian C-order bytes.

    The bytes are exactly what `msgpack.packb` writes for the map above, assembled so that each
    array's data is copied once, into the payload: `packb` of the map would copy it three times
    (`tobytes`, its own buffer, the result)."""
    packer = msgpack.Packer(use_bin_type=True, default=_to_builtin)
    header = {
        "v": VERSION,
        "run": msg.run,
        "seq": int(msg.seq),
        "stamp_ns": int(msg.stamp_ns),
        "producer": msg.producer,
        "meta": msg.meta,
    }
    parts: list[bytes | memoryview] = [packer.pack_map_header(len(header) + 1)]
    for key, value in header.items():
        parts += [packer.pack(key), packer.pack(value)]
    parts += [packer.pack("arrays"), packer.pack_map_header(len(msg.arrays))]
    for name, arr in msg.arrays.items():
        arr = np.asarray(arr)
        dt = _wire_dtype(arr)
        data = np.ascontiguousarray(arr, dtype=dt)
        raw = (np.packbits(data, axis=None) if dt == np.bool_ else data).reshape(-1).view(np.uint8)
        parts += [
            packer.pack(name),
            packer.pack_map_header(3),
            packer.pack("dtype"),
            packer.pack(dt.str),
            packer.pack("shape"),
            packer.pack(list(arr.shape)),
            packer.pack("data"),
            _bin_header(raw.nbytes),
            memoryview(raw),
        ]
    return b"".join(parts)


def _bin_header(size: int) -> bytes:
    """The msgpack header of a `size`-byte binary, in the smallest form, as msgpack writes it."""
    if size < 1 << 8:
        return struct.pack(">BB", 0xC4, size)
    if size < 1 << 16:
        return struct.pack(">BH", 0xC5, size)
    return struct.pack(">BI", 0xC6, size)


def _to_builtin(obj: Any) -> Any:
    """Let numpy scalars and small arrays appear in `meta`."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"meta value of type {type(obj).__name__} cannot be sent; use plain numbers, strings, lists, dicts")


def decode(payload: bytes | bytearray | memoryview, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Parse and validate a payload. Raises MessageError naming the first problem found."""
    size = len(payload)
    if size > max_bytes:
        raise MessageError(f"payload of {size} bytes exceeds the {max_bytes}-byte cap")
    try:
        obj = msgpack.unpackb(
            payload,  # read in place; every binary comes out as new bytes
            raw=False,
            strict_map_key=True,
            max_bin_len=max_bytes,
            max_str_len=1 << 20,
            max_array_len=1 << 16,
            max_map_len=1 << 16,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises many types for garbage input
        raise MessageError(f"payload is not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise MessageError(f"expected a msgpack map at the top level, got {type(obj).__name__}")
    if obj.get("v") != VERSION:
        raise MessageError(f"message version {obj.get('v')!r} is not supported; expected {VERSION}")
    run, seq, stamp, producer = obj.get("run"), obj.get("seq"), obj.get("stamp_ns", 0), obj.get("producer", "")
    if not isinstance(run, str):
        raise MessageError(f"field 'run' must be a string, got {type(run).__name__}")
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
        raise MessageError(f"field 'seq' must be a non-negative integer, got {seq!r}")
    if not isinstance(stamp, int) or isinstance(stamp, bool):
        raise MessageError(f"field 'stamp_ns' must be an integer, got {type(stamp).__name__}")
    if not isinstance(producer, str):
        raise MessageError(f"field 'producer' must be a string, got {type(producer).__name__}")
    meta = obj.get("meta", {})
    if not isinstance(meta, dict):
        raise MessageError(f"field 'meta' must be a map, got {type(meta).__name__}")
    raw_arrays = obj.get("arrays", {})
    if not isinstance(raw_arrays, dict) or len(raw_arrays) > MAX_ARRAYS:
        raise MessageError(f"field 'arrays' must be a map of at most {MAX_ARRAYS} entries")
    arrays = {name: _decode_array(name, spec) for name, spec in raw_arrays.items()}
    return Message(run=run, seq=seq, stamp_ns=stamp, producer=producer, meta=meta, arrays=arrays)


def _decode_array(name: Any, spec: Any) -> np.ndarray:
    if not isinstance(name, str):
        raise MessageError(f"array names must be strings, got {type(name).__name__}")
    if not isinstance(spec, dict):
        raise MessageError(f"array '{name}': expected a map with dtype, shape, data")
    dtype, shape, data = spec.get("dtype"), spec.get("shape"), spec.get("data")
    if dtype not in ALLOWED_DTYPES:
        raise MessageError(f"array '{name}': dtype {dtype!r} is not allowed; expected one of {sorted(ALLOWED_DTYPES)}")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**31 for d in shape)
    ):
        raise MessageError(
            f"array '{name}': shape must be a list of at most {MAX_NDIM} non-negative ints, got {shape!r}"
        )
    if not isinstance(data, bytes):
        raise MessageError(f"array '{name}': data must be bytes, got {type(data).__name__}")
    dt = np.dtype(dtype)
    count = math.prod(shape)
    expected = (count + 7) // 8 if dt == np.bool_ else count * dt.itemsize
    if expected != len(data):
        raise MessageError(f"array '{name}': shape {shape} of {dtype} needs {expected} bytes, got {len(data)}")
    if dt == np.bool_:
        bits = np.unpackbits(np.frombuffer(data, np.uint8), count=count)
        return bits.view(np.bool_).reshape(shape)
    return np.frombuffer(data, dtype=dt).reshape(shape)
