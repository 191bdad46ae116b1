"""Hostile input: random and mutated payloads raise only ProtocolError (seeded, fast)."""

import json
import random
import struct

import pytest
from conftest import sample_messages

from minority.protocol import Chunk, Event, Frame, ProtocolError, Spec, Timing, decode_as, decode_message
from minority.protocol.wire import ALIGN, PREFIX, PREFIX_SIZE

CASES_PER_DECODER = 10_000
HOSTILE_VALUES = [None, True, -1, 0, 2**63, -(2**70), 1e308, "x" * 300, "", [], [1, 2],
                  {"a": 1}, [[0, 0, 0], [1, 1]], "NaN", 0.5, [2**40, 3], [-1, 3], ["a", "b", "c"]]


def _aligned(offset: int) -> int:
    return (offset + ALIGN - 1) // ALIGN * ALIGN


def _rebuild(header, arrays: bytes, kind: int, rng: random.Random) -> bytes:
    """Re-encode a (mutated) header before the original array bytes, laid out as the encoder
    would (so the mutation reaches field validation), with the length sometimes wrong."""
    h = json.dumps(header).encode()
    payload = bytearray(PREFIX_SIZE) + h
    payload += bytes(_aligned(len(payload)) - len(payload)) + arrays if arrays else b""
    total = len(payload) if rng.random() < 0.9 else rng.randrange(0, 2**40)
    kind = kind if rng.random() < 0.8 else rng.choice([1, 2, 3, 4, 5])
    PREFIX.pack_into(payload, 0, b"MNRT", 1, kind, 0, len(h), 0, total, 0)
    return bytes(payload)


def _mutate_header(payload: bytes, rng: random.Random) -> bytes:
    hlen = struct.unpack_from("<I", payload, 8)[0]
    header = json.loads(payload[PREFIX_SIZE:PREFIX_SIZE + hlen])
    arrays = payload[_aligned(PREFIX_SIZE + hlen):]
    for _ in range(rng.choice([1, 1, 1, 2, 3])):
        target = rng.choice(["meta", "meta", "meta", "arrays", "root"])
        if target == "meta" and isinstance(header, dict) and isinstance(header.get("meta"), dict):
            meta = header["meta"]
            views = meta.get("views")
            if isinstance(views, list) and views and rng.random() < 0.5:  # into a spec's views
                meta = rng.choice(views)
                if isinstance(meta, dict) and isinstance(meta.get("camera"), dict) and rng.random() < 0.5:
                    meta = meta["camera"]
            if not isinstance(meta, dict) or not meta:
                continue
            key = rng.choice(list(meta))
            if rng.random() < 0.15:
                del meta[key]
            else:
                meta[key] = rng.choice(HOSTILE_VALUES)
        elif target == "arrays" and isinstance(header, dict) and isinstance(header.get("arrays"), list) \
                and header["arrays"]:
            desc = rng.choice(header["arrays"])
            if not isinstance(desc, dict):
                continue
            key = rng.choice(["name", "dtype", "shape", "extra"])
            desc[key] = rng.choice(HOSTILE_VALUES + ["<f4", "<f8", ">f4", "|u1", "O", "<U4"])
        elif target == "root":
            header = rng.choice(HOSTILE_VALUES + [{"meta": {}, "arrays": []}, {"meta": 1}])
    return _rebuild(header, arrays, payload[5], rng)


def _mutate(payload: bytes, rng: random.Random) -> bytes:
    op = rng.randrange(9)
    if op == 0:
        return bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 200)))
    if op == 1:
        return payload[:rng.randrange(0, len(payload))]
    if op == 2:
        return payload + bytes(rng.getrandbits(8) for _ in range(rng.randrange(1, 70)))
    if op == 3:
        b = bytearray(payload)
        for _ in range(rng.randrange(1, 9)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        return bytes(b)
    if op == 4:
        b = bytearray(payload)
        field = rng.choice([(4, "<B"), (5, "<B"), (6, "<H"), (8, "<I"), (12, "<I"), (16, "<Q")])
        hi = 2 ** (8 * struct.calcsize(field[1])) - 1
        struct.pack_into(field[1], b, field[0], rng.choice([0, 1, 2, 6, 255, hi, rng.randrange(hi)]))
        return bytes(b)
    return _mutate_header(payload, rng)  # ops 5-8: a third of the cases reach field checks


DECODERS = {
    "chunk": lambda p: decode_as(p, Chunk),
    "frame": lambda p: decode_as(p, Frame),
    "timing": lambda p: decode_as(p, Timing),
    "event": lambda p: decode_as(p, Event),
    "spec": lambda p: decode_as(p, Spec),
    "any": decode_message,
}


@pytest.mark.parametrize("name", list(DECODERS))
def test_fuzz_decoder_raises_only_protocol_error(name):
    rng = random.Random(f"minority-fuzz-{name}")
    seeds = [bytes(m.encode()) for m in sample_messages()]
    decoder = DECODERS[name]
    rejected = 0
    for i in range(CASES_PER_DECODER):
        payload = _mutate(rng.choice(seeds), rng)
        try:
            decoder(payload)
        except ProtocolError:
            rejected += 1
        except Exception as exc:  # noqa: BLE001 - the point of the test
            pytest.fail(f"case {i}: {type(exc).__name__}: {exc} for payload {payload[:96]!r}")
    assert rejected > CASES_PER_DECODER // 2  # the mutations really are hostile


def test_an_empty_array_with_absurd_dimensions_is_a_protocol_error():
    """Zero elements pass the size checks, but numpy refuses the shape: still ProtocolError."""
    import numpy as np

    from minority.protocol.wire import MessageKind, decode, encode

    payload = bytes(encode(MessageKind.CHUNK, {"a": 1},
                           {"x": np.empty((0, 2**35, 10**7), np.float32)}))
    shape = b"[0,34359738368,10000000]"
    assert shape in payload  # the same header length with a larger last dimension:
    bad = payload.replace(shape, b"[0,34359738368,99999999]")
    with pytest.raises(ProtocolError, match="array 'x': shape"):
        decode(bad)


@pytest.mark.parametrize("message", sample_messages(), ids=lambda m: type(m).__name__)
def test_a_negative_sent_time_is_refused(message):
    """MCAP stores times as u64: a negative stamp must never get past the decoder."""
    payload = bytearray(message.encode())
    struct.pack_into("<q", payload, 24, -1)
    with pytest.raises(ProtocolError, match="negative"):
        decode_message(bytes(payload))


@pytest.mark.parametrize("name", [".", "..", "a\n", "-x", ".hidden", "a/b", "", "x" * 65])
def test_names_that_are_not_one_safe_path_component_are_refused(name):
    from minority.protocol import check, keys

    with pytest.raises(ProtocolError):
        check.name(name, "run")
    assert keys.parse(f"minority/{name}/event") is None
    event = Event("r", "error").to_json() | {"run": name}
    with pytest.raises(ProtocolError):
        Event.from_json(event)
    chunk = next(m for m in sample_messages() if isinstance(m, Chunk))
    payload = chunk.encode()
    hlen = struct.unpack_from("<I", payload, 8)[0]
    header = json.loads(payload[PREFIX_SIZE:PREFIX_SIZE + hlen])
    header["meta"]["run"] = name
    with pytest.raises(ProtocolError):
        decode_as(_rebuild(header, bytes(payload[_aligned(PREFIX_SIZE + hlen):]), 1,
                           random.Random(0)), Chunk)
