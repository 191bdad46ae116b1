"""Every message type survives encode -> decode unchanged; views, not copies."""

import numpy as np
import pytest
from conftest import make_chunk, make_png, sample_messages

from minority.protocol import (
    Chunk,
    Event,
    Frame,
    MessageKind,
    ProtocolError,
    Spec,
    Timing,
    decode_as,
    decode_message,
)
from minority.protocol.wire import ALIGN, PREFIX_SIZE, decode, encode


def assert_same(a, b):
    assert type(a) is type(b)
    if isinstance(a, Chunk):
        assert a.meta() == b.meta()
        assert list(a.fields) == list(b.fields)
        for name in a.fields:
            assert b.fields[name].dtype == a.fields[name].dtype
            np.testing.assert_array_equal(b.fields[name], a.fields[name])
    else:
        assert a.to_json() == b.to_json() if not isinstance(a, Frame) else a.meta() == b.meta()


@pytest.mark.parametrize("message", sample_messages(), ids=lambda m: type(m).__name__)
def test_round_trip(message):
    payload = message.encode()
    back = decode_message(bytes(payload))
    assert_same(message, back)
    assert back.sent_ns > 0  # stamped at encode
    assert decode_as(payload, type(message)).KIND == message.KIND


def test_frame_png_bytes_survive():
    png = make_png(7, 5)
    back = decode_as(Frame("r", "v", 1, 0.1, 7, 5, png).encode(), Frame)
    assert back.png == png


def test_chunk_arrays_are_aligned_views():
    chunk = make_chunk(n=1000)
    payload = bytes(chunk.encode())
    back = decode_as(payload, Chunk)
    base = np.frombuffer(payload, np.uint8).ctypes.data
    for array in back.fields.values():
        assert (array.ctypes.data - base) % ALIGN == 0
        assert not array.flags.owndata and not array.flags.writeable


@pytest.mark.parametrize("n", [0, 1])
def test_tiny_chunks(n):
    back = decode_as(make_chunk(n=n).encode(), Chunk)
    assert back.count == n and back.positions.shape == (n, 3)


def test_big_endian_and_float64_inputs_are_normalized():
    chunk = make_chunk(n=10)
    chunk.fields["positions"] = chunk.fields["positions"].astype(">f8")
    chunk.fields["temperature"] = np.arange(10, dtype=">f4")
    back = decode_as(chunk.encode(), Chunk)
    assert back.positions.dtype == np.float32
    assert back.fields["temperature"].dtype == np.dtype("<f4")
    np.testing.assert_array_equal(back.fields["temperature"], np.arange(10))


def test_kind_mismatch_is_named():
    with pytest.raises(ProtocolError, match="expected a frame message, got chunk"):
        decode_as(make_chunk().encode(), Frame)


@pytest.mark.parametrize("field,value,match", [
    ("positions", np.full((4, 3), np.nan, np.float32), "non-finite value at particle 0"),
    ("velocity_magnitude", np.array([0, 1, np.inf, 2], np.float32), "non-finite value at particle 2"),
    ("displacement", np.zeros((5, 3), np.float32), r"shape \[5, 3\]"),
])
def test_chunk_field_validation(field, value, match):
    chunk = make_chunk(n=4)
    chunk.fields[field] = value
    with pytest.raises(ProtocolError, match=match):
        decode_as(chunk.encode(), Chunk)


def test_unsupported_dtype_refused_at_encode():
    chunk = make_chunk(n=4)
    chunk.fields["name"] = np.array(["a", "b", "c", "d"])
    with pytest.raises(ProtocolError, match="dtype"):
        chunk.encode()


def test_envelope_layout():
    payload = encode(MessageKind.TIMING, {"a": 1}, {"x": np.arange(3, dtype=np.int32)}, sent_ns=7)
    assert payload[:4] == b"MNRT" and payload[4] == 1 and payload[5] == MessageKind.TIMING
    env = decode(payload)
    assert env.sent_ns == 7 and env.meta == {"a": 1}
    assert list(env.arrays["x"]) == [0, 1, 2]
    assert len(payload) == ALIGN * ((PREFIX_SIZE + len(b'{"meta":{"a":1},"arrays":'
                                                       b'[{"name":"x","dtype":"<i4","shape":[3]}]}')
                                     + ALIGN - 1) // ALIGN) + 12


def test_spec_and_event_types():
    spec = sample_messages()[1]
    assert isinstance(decode_message(spec.encode()), Spec)
    assert isinstance(decode_message(sample_messages()[3].encode()), Timing)
    assert isinstance(decode_message(sample_messages()[4].encode()), Event)


def test_finite_check_fast_path_has_no_false_verdicts():
    chunk = make_chunk(n=64)
    chunk.fields["flags"] = np.full(64, 0xFF, np.uint8)  # bytes that read as NaN in float32
    chunk.fields["huge"] = np.full(64, 3e38, np.float32)  # finite, but overflows a dot product
    chunk.fields["after"] = np.ones(64, np.float32)
    back = decode_as(chunk.encode(), Chunk)
    np.testing.assert_array_equal(back.fields["huge"], chunk.fields["huge"])
    chunk.fields["f64"] = np.ones(64)
    chunk.fields["f64"][17] = np.nan
    with pytest.raises(ProtocolError, match="'f64' has a non-finite value at particle 17"):
        decode_as(chunk.encode(), Chunk)
