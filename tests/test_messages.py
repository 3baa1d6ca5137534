import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from umad_common.dataflow.api.messages import ALLOWED_DTYPES, IN_PLACE_FROM, Message, MessageError, decode, encode

dtypes = st.sampled_from(sorted(ALLOWED_DTYPES)).map(np.dtype)
arrays = dtypes.flatmap(lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=4, max_side=5)))


@settings(max_examples=200, deadline=None)
@given(
    run=st.text(max_size=20),
    seq=st.integers(0, 2**40),
    stamp=st.integers(-(2**62), 2**62),
    meta=st.dictionaries(st.text(max_size=8), st.one_of(st.integers(-100, 100), st.text(max_size=8), st.booleans())),
    arrs=st.dictionaries(st.text(min_size=1, max_size=8), arrays, max_size=4),
)
def test_round_trip(run, seq, stamp, meta, arrs):
    msg = Message(run, seq, stamp, "producer", meta, arrs)
    payload = encode(msg)
    assert msgpack.packb(msgpack.unpackb(payload), use_bin_type=True) == payload  # plain msgpack, smallest forms
    back = decode(payload)
    assert (back.run, back.seq, back.stamp_ns, back.producer, back.meta) == (run, seq, stamp, "producer", meta)
    assert set(back.arrays) == set(arrs)
    for name, arr in arrs.items():
        assert back.arrays[name].dtype == arr.dtype and back.arrays[name].shape == arr.shape
        np.testing.assert_array_equal(back.arrays[name], arr)


def test_big_endian_arrays_travel_as_little_endian():
    arr = np.arange(6, dtype=">f4").reshape(2, 3)
    back = decode(encode(Message("r", 0, arrays={"a": arr})))
    assert back.arrays["a"].dtype == np.dtype("<f4")
    np.testing.assert_array_equal(back.arrays["a"], arr)


def test_boolean_masks_travel_bit_packed():
    masks = np.zeros((3, 128, 192), bool)
    masks[1, 10:20, 30:90] = True
    payload = encode(Message("r", 0, arrays={"masks": masks}))
    assert len(payload) < masks.size // 8 + 200  # one bit per pixel plus the header
    np.testing.assert_array_equal(decode(payload).arrays["masks"], masks)
    lying = msgpack.unpackb(payload)
    lying["arrays"]["masks"]["shape"] = [3, 128, 193]
    with pytest.raises(MessageError, match="needs 9264 bytes, got 9216"):
        decode(msgpack.packb(lying, use_bin_type=True))


def test_unsupported_dtype_is_refused_when_encoding():
    with pytest.raises(MessageError, match="cannot be sent"):
        encode(Message("r", 0, arrays={"a": np.array(["x"])}))


def _raw(**overrides):
    obj = {
        "v": 1,
        "run": "r",
        "seq": 1,
        "stamp_ns": 0,
        "producer": "p",
        "meta": {},
        "arrays": {"a": {"dtype": "<f4", "shape": [2, 2], "data": b"\0" * 16}},
    }
    obj.update(overrides)
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(
    "payload, match",
    [
        (b"\xc1garbage", "not valid msgpack"),
        (msgpack.packb([1, 2, 3]), "map at the top level"),
        (_raw(v=2), "version 2"),
        (_raw(seq=-1), "'seq'"),
        (_raw(run=5), "'run'"),
        (_raw(meta=[1]), "'meta'"),
        (_raw(arrays={"a": {"dtype": "|O", "shape": [1], "data": b"\0" * 8}}), "dtype '\\|O' is not allowed"),
        (_raw(arrays={"a": {"dtype": "<f4", "shape": [3, 3], "data": b"\0" * 16}}), "needs 36 bytes, got 16"),
        (_raw(arrays={"a": {"dtype": "<f4", "shape": [2**30, 2**30], "data": b""}}), "needs"),
        (_raw(arrays={"a": {"dtype": "<f4", "shape": [-1], "data": b""}}), "shape"),
        (_raw(arrays={"a": {"dtype": "<f4", "shape": [1] * 9, "data": b"\0" * 4}}), "shape"),
    ],
)
def test_malformed_payloads_raise_one_clear_error(payload, match):
    with pytest.raises(MessageError, match=match):
        decode(payload)


def test_size_cap_stops_memory_bombs_before_parsing():
    with pytest.raises(MessageError, match="exceeds"):
        decode(b"\0" * 1001, max_bytes=1000)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_never_escape_as_other_errors(data):
    try:
        decode(data)
    except MessageError:
        pass


def test_a_large_payloads_arrays_are_read_in_place_as_views_that_keep_the_payload_alive():
    image = np.arange(1024 * 768, dtype=np.uint8).reshape(1024, 768)
    payload = bytearray(encode(Message("r", 3, arrays={"image": image})))
    back = decode(payload)
    assert np.shares_memory(back.arrays["image"], np.frombuffer(payload, np.uint8))
    del payload  # the view holds the buffer, not a dangling pointer
    np.testing.assert_array_equal(back.arrays["image"], image)


def test_a_small_payloads_arrays_are_decoded_by_msgpack_as_copies():
    image = np.arange(64 * 48, dtype=np.uint8).reshape(64, 48)
    payload = bytearray(encode(Message("r", 3, arrays={"image": image})))
    back = decode(payload)
    assert not np.shares_memory(back.arrays["image"], np.frombuffer(payload, np.uint8))
    np.testing.assert_array_equal(back.arrays["image"], image)


def test_an_array_misaligned_in_the_payload_is_copied_to_an_aligned_one():
    values = np.arange(IN_PLACE_FROM, dtype="<f8")
    payload = encode(Message("r", 0, arrays={"v": values}))
    shifted = memoryview(bytearray(b"\0" + payload))[1:]  # every array now starts one byte off its alignment
    back = decode(shifted)
    assert back.arrays["v"].flags.aligned
    np.testing.assert_array_equal(back.arrays["v"], values)


def test_reading_in_place_gives_what_plain_msgpack_gives():
    masks = np.zeros((2, 8, 9), bool)
    masks[1, 2:5] = True
    arrays = {"m": masks, "f": np.ones((3, 2), "<f4"), "big": np.arange(IN_PLACE_FROM, dtype="<u2")}
    msg = Message("run", 7, 11, "p", {"nested": {"a": [1, 2.5, None]}}, arrays)
    payload = encode(msg)
    by_msgpack = msgpack.unpackb(payload)
    back = decode(payload)
    assert back.meta == by_msgpack["meta"]
    for name, spec in by_msgpack["arrays"].items():
        assert bytes(encode(Message("run", 7, 11, "p", arrays={name: back.arrays[name]}))).endswith(spec["data"])


def test_a_large_payload_corrupted_anywhere_in_its_header_raises_only_message_errors():
    payload = encode(Message("run", 1, 2, "p", {"k": [1, "v"]}, {"a": np.ones(IN_PLACE_FROM, np.uint8)}))
    header_end = payload.index(b"\xc6")  # the big binary's type byte: everything before is msgpack structure
    rng = np.random.default_rng(0)
    for at in range(header_end + 5):
        for value in rng.integers(0, 256, 6):
            corrupted = bytearray(payload)
            corrupted[at] = value
            try:
                decode(corrupted)
            except MessageError:
                pass
    with pytest.raises(MessageError, match="not valid msgpack"):
        decode(payload[:-1])
