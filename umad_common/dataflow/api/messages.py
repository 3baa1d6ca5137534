"""The frame message every operator speaks: a msgpack map with a header and numpy arrays.

Wire format (version 1)::

    {v: 1, run: str, seq: int, stamp_ns: int, producer: str, meta: {...},
     arrays: {name: {dtype: "<f4", shape: [..], data: <raw little-endian bytes>}}}

Boolean arrays (`|b1`, e.g. a segmenter's (K, h, w) masks) travel bit-packed (`np.packbits`, C
order, ceil(n / 8) bytes): eight times less on the bus and in the log.

Decoding never trusts the sender: the version, every dtype (a whitelist), every shape and the byte
length are checked before a single array is built, and a size cap stops memory bombs.

A large payload (`IN_PLACE_FROM` bytes or more) is read in place: each array is a read-only numpy
view on the payload (which it keeps alive), not a copy, unless its bytes are bit-packed or not
aligned for its dtype. Walking the map in Python costs several times what msgpack's own decoder
takes, which copies each array, so only a large payload gains and a smaller one is decoded by
msgpack (docs/experiments.md). Encoding writes each array's bytes once, into the payload, or
(`encoded_parts`) into whatever buffer the transport hands out.
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
IN_PLACE_FROM = 512 << 10  # payloads this large are read in place (msgpack's copies cost more than the walk)
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
    return b"".join(encoded_parts(msg))


def encoded_parts(msg: Message) -> list[bytes | memoryview]:
    """The pieces whose concatenation is `encode(msg)`: small msgpack headers and each array's own
    bytes (a view, not a copy), for a transport that writes them straight into its buffer."""
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
    return parts


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


_UNPACK_LIMITS = dict(
    raw=False,
    strict_map_key=True,
    max_str_len=1 << 20,
    max_array_len=1 << 16,
    max_map_len=1 << 16,
    max_ext_len=0,
)


def decode(payload: bytes | bytearray | memoryview, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Parse and validate a payload; a large one's arrays are views on it (`_read_in_place`). Raises
    MessageError naming the first problem found."""
    size = len(payload)
    if size > max_bytes:
        raise MessageError(f"payload of {size} bytes exceeds the {max_bytes}-byte cap")
    obj = None
    if size >= IN_PLACE_FROM:
        try:
            obj = _read_in_place(memoryview(payload).cast("B"))
        except Exception:  # not a well-formed map: msgpack itself says below what is wrong with it
            obj = None
    if obj is None:
        obj = _unpack(payload, max_bytes)
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


def _unpack(payload: bytes | bytearray | memoryview, max_bytes: int) -> Any:
    """The whole payload by msgpack (every binary copied out), for a payload `_read_in_place` refused."""
    try:
        return msgpack.unpackb(payload, max_bin_len=max_bytes, **_UNPACK_LIMITS)
    except Exception as exc:  # msgpack raises many types for garbage input
        raise MessageError(f"payload is not valid msgpack ({type(exc).__name__}: {exc})") from None


def _read_in_place(view: memoryview) -> dict:
    """The message map with each array's `data` a view on `view`; msgpack decodes every other value.
    Raises (ValueError, IndexError, msgpack's own errors) for anything but a well-formed map."""
    count, at = _map_header(view, 0)
    obj = {}
    for _ in range(count):
        key, at = _key(view, at)
        if key == "arrays":
            value, at = _arrays_in_place(view, at)
        else:
            value, at = _small_value(view, at)
        obj[key] = value
    if at != len(view):
        raise ValueError(f"{len(view) - at} bytes after the message map")
    return obj


def _arrays_in_place(view: memoryview, at: int) -> tuple[dict, int]:
    count, at = _map_header(view, at)
    arrays = {}
    for _ in range(count):
        name, at = _key(view, at)
        fields, at = _map_header(view, at)
        spec = {}
        for _ in range(fields):
            field_name, at = _key(view, at)
            if field_name == "data" and view[at] in _BIN_LENGTH:
                length_bytes = _BIN_LENGTH[view[at]]
                length = int.from_bytes(view[at + 1 : at + 1 + length_bytes], "big")
                start = at + 1 + length_bytes
                if start + length > len(view):
                    raise ValueError("binary runs past the payload's end")
                spec[field_name], at = view[start : start + length], start + length
            else:
                spec[field_name], at = _small_value(view, at)
        arrays[name] = spec
    return arrays, at


def _map_header(view: memoryview, at: int) -> tuple[int, int]:
    """(entries, where the first key starts) of the msgpack map at `at`."""
    first = view[at]
    if 0x80 <= first <= 0x8F:
        return first & 0x0F, at + 1
    if first == 0xDE:
        return struct.unpack_from(">H", view, at + 1)[0], at + 3
    if first == 0xDF:
        return struct.unpack_from(">I", view, at + 1)[0], at + 5
    raise ValueError(f"expected a msgpack map at byte {at}")


def _key(view: memoryview, at: int) -> tuple[str, int]:
    key, end = _small_value(view, at)
    if not isinstance(key, str):
        raise ValueError(f"map key {key!r} at byte {at} is not a string")
    return key, end


def _small_value(view: memoryview, at: int) -> tuple[Any, int]:
    end = _end_of_value(view, at)
    return msgpack.unpackb(view[at:end], max_bin_len=MAX_MESSAGE_BYTES, **_UNPACK_LIMITS), end


_BIN_LENGTH = {0xC4: 1, 0xC5: 2, 0xC6: 4}  # bin 8/16/32: bytes of the length that follows the type byte
_STR_LENGTH = {0xD9: 1, 0xDA: 2, 0xDB: 4}
_FIXED_SIZE = {0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}
_FIXED_SIZE |= {0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8}
_CONTAINER = {
    0xDC: (2, 1),
    0xDD: (4, 1),
    0xDE: (2, 2),
    0xDF: (4, 2),
}  # array/map 16/32: (length bytes, values per entry)
MAX_NESTING = 64


def _end_of_value(view: memoryview, at: int, depth: int = 0) -> int:
    """Where the msgpack value starting at `at` ends (extension types are refused, as in decoding)."""
    if depth > MAX_NESTING:
        raise ValueError(f"values nested deeper than {MAX_NESTING}")
    first = view[at]
    if first <= 0x7F or first >= 0xE0:  # fixint
        return at + 1
    if 0xA0 <= first <= 0xBF:  # fixstr
        end = at + 1 + (first & 0x1F)
    elif first in _FIXED_SIZE:
        end = at + 1 + _FIXED_SIZE[first]
    elif first in _BIN_LENGTH or first in _STR_LENGTH:
        size = _BIN_LENGTH.get(first) or _STR_LENGTH[first]
        end = at + 1 + size + int.from_bytes(view[at + 1 : at + 1 + size], "big")
    else:
        if first <= 0x8F:  # fixmap
            entries, values, at = first & 0x0F, 2, at + 1
        elif first <= 0x9F:  # fixarray
            entries, values, at = first & 0x0F, 1, at + 1
        elif first in _CONTAINER:
            size, values = _CONTAINER[first]
            entries, at = int.from_bytes(view[at + 1 : at + 1 + size], "big"), at + 1 + size
        else:
            raise ValueError(f"msgpack type 0x{first:02x} at byte {at} is not used in messages")
        for _ in range(entries * values):
            at = _end_of_value(view, at, depth + 1)
        end = at
    if end > len(view):
        raise ValueError("value runs past the payload's end")
    return end


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
    if not isinstance(data, bytes | memoryview):
        raise MessageError(f"array '{name}': data must be bytes, got {type(data).__name__}")
    dt = np.dtype(dtype)
    count = math.prod(shape)
    expected = (count + 7) // 8 if dt == np.bool_ else count * dt.itemsize
    if expected != len(data):
        raise MessageError(f"array '{name}': shape {shape} of {dtype} needs {expected} bytes, got {len(data)}")
    if dt == np.bool_:
        bits = np.unpackbits(np.frombuffer(data, np.uint8), count=count)
        return bits.view(np.bool_).reshape(shape)
    array = np.frombuffer(data, dtype=dt).reshape(shape)
    return array if array.flags.aligned else array.copy()  # C code (torch, OpenCV) may expect alignment
