"""Versioned binary envelope shared by every message type.

Layout (all little-endian), version 1::

    offset  size  field
    0       4     magic b"MNRT"
    4       1     format version (1)
    5       1     message kind (MessageKind)
    6       2     reserved, 0
    8       4     header length H, bytes
    12      4     reserved, 0
    16      8     total payload length, bytes
    24      8     sent time, ns since the Unix epoch (stamped at publish)
    32      H     header: UTF-8 JSON object {"meta": {...}, "arrays": [{"name", "dtype", "shape"}]}
                  (decoded and type-checked by msgspec against the message kind's meta type)
    ...           zero padding to a 64-byte boundary
    ...           each array, raw little-endian C order, starting on a 64-byte boundary

Array offsets are implied by the order and sizes in the header, so a decoder checks
that every array fits and that the declared total equals the bytes received before it
touches any array data. Arrays decode as read-only numpy views of the payload.
"""

from __future__ import annotations

import json
import math
import struct
import time
from dataclasses import dataclass
from enum import IntEnum
from typing import Annotated, Any, Generic, Literal, TypeVar

import msgspec
import numpy as np

from minority.protocol.errors import ProtocolError

MAGIC = b"MNRT"
FORMAT_VERSION = 1
PREFIX = struct.Struct("<4sBBHIIQq")  # magic, version, kind, reserved, H, reserved, total, sent_ns
PREFIX_SIZE = PREFIX.size  # 32 bytes
SENT_NS_OFFSET = 24
ALIGN = 64  # bytes; array starts are aligned for SIMD-friendly views
MAX_HEADER_BYTES = 1 << 20
MAX_ARRAYS = 64
MAX_NDIM = 4
MAX_PAYLOAD_BYTES = 1 << 36  # 64 GiB: anything larger is a corrupt length field

# Whitelist of array dtypes on the wire (numpy little-endian type strings).
DTYPES = {
    "<f4": np.dtype("<f4"),
    "<f8": np.dtype("<f8"),
    "<i4": np.dtype("<i4"),
    "<i8": np.dtype("<i8"),
    "<u4": np.dtype("<u4"),
    "<u8": np.dtype("<u8"),
    "<i2": np.dtype("<i2"),
    "<u2": np.dtype("<u2"),
    "|i1": np.dtype("i1"),
    "|u1": np.dtype("u1"),
}


class MessageKind(IntEnum):
    CHUNK = 1
    SPEC = 2
    FRAME = 3
    TIMING = 4
    EVENT = 5
    STATS = 6


_KINDS = {int(k): k for k in MessageKind}
_U1, _F4 = np.dtype("u1"), np.dtype("<f4")
WireDtype = Literal["<f4", "<f8", "<i4", "<i8", "<u4", "<u8", "<i2", "<u2", "|i1", "|u1"]
MetaT = TypeVar("MetaT")


class ArrayDesc(msgspec.Struct, forbid_unknown_fields=True):
    """One array of the payload: its name, wire dtype and shape."""

    name: Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
    dtype: WireDtype
    shape: Annotated[list[Annotated[int, msgspec.Meta(ge=0, lt=MAX_PAYLOAD_BYTES)]],
                     msgspec.Meta(max_length=MAX_NDIM)]


class Header(msgspec.Struct, Generic[MetaT], forbid_unknown_fields=True):
    """The JSON header: typed meta of the message kind, then the array descriptors."""

    meta: MetaT
    arrays: Annotated[list[ArrayDesc], msgspec.Meta(max_length=MAX_ARRAYS)]


_DECODERS: dict[Any, msgspec.json.Decoder] = {}


def _header_decoder(meta_type) -> msgspec.json.Decoder:
    """A cached typed decoder: types, ranges and unknown fields are checked in C."""
    if meta_type not in _DECODERS:
        _DECODERS[meta_type] = msgspec.json.Decoder(Header[meta_type])
    return _DECODERS[meta_type]


@dataclass(slots=True)
class Envelope:
    """A decoded envelope: kind, sender's time, header meta and array views."""

    kind: MessageKind
    sent_ns: int
    meta: dict
    arrays: dict[str, np.ndarray]
    payload: np.ndarray | None = None  # the whole payload as uint8 (a view, no copy)
    float_span: tuple[int, int] = (0, 0)  # byte range covering every float array

    def check_finite(self) -> None:
        """Raise unless every value of every float array is finite.

        Fast path: one dot product over the byte span of all float arrays, read as float32
        (padding is zero; a float64 NaN or inf is one as float32 too), propagates any NaN or
        inf in one BLAS pass. Only when it is not finite (bad values, huge finite values that
        overflow, or other bytes in the span that look like NaN) are arrays checked one by one.
        """
        lo, hi = self.float_span
        if hi <= lo:
            return
        span = self.payload[lo:hi].view(_F4)
        with np.errstate(over="ignore", invalid="ignore"):
            if math.isfinite(span.dot(span)):
                return
        for name, array in self.arrays.items():
            if array.dtype.kind == "f" and array.size:
                flat = array.reshape(-1)
                bad = np.flatnonzero(~np.isfinite(flat))
                if bad.size:
                    row = int(bad[0]) // (flat.size // array.shape[0])
                    raise ProtocolError(f"field {name!r} has a non-finite value at particle {row}")


def _aligned(offset: int) -> int:
    return (offset + ALIGN - 1) // ALIGN * ALIGN


def wire_dtype(array: np.ndarray) -> str:
    """The wire type string of `array`'s dtype, little-endian; raises if not allowed."""
    dt = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
    key = dt.str if dt.itemsize > 1 else "|" + dt.str[1:]
    if key not in DTYPES:
        raise ProtocolError(f"array dtype {array.dtype} is not one of {sorted(DTYPES)}")
    return key


def encode(kind: MessageKind, meta, arrays: dict[str, np.ndarray] | None = None,
           sent_ns: int | None = None) -> bytearray:
    """Encode one message; arrays are copied once, into the returned buffer."""
    arrays = arrays or {}
    if len(arrays) > MAX_ARRAYS:
        raise ProtocolError(f"{len(arrays)} arrays, at most {MAX_ARRAYS} allowed")
    descs, parts = [], []
    for name, array in arrays.items():
        a = np.asarray(array)
        dt = wire_dtype(a)
        descs.append({"name": name, "dtype": dt, "shape": list(a.shape)})
        parts.append(np.ascontiguousarray(a, dtype=DTYPES[dt]))
    try:  # the stdlib encoder refuses NaN and infinity (msgspec would write null)
        header = json.dumps({"meta": msgspec.to_builtins(meta), "arrays": descs},
                            allow_nan=False, separators=(",", ":")).encode()
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"header is not finite JSON: {exc}") from None
    if len(header) > MAX_HEADER_BYTES:
        raise ProtocolError(f"header is {len(header)} bytes, at most {MAX_HEADER_BYTES}")
    offsets, end = [], PREFIX_SIZE + len(header)
    for part in parts:
        start = _aligned(end)
        offsets.append(start)
        end = start + part.nbytes
    total = end
    out = bytearray(total)
    stamp = time.time_ns() if sent_ns is None else sent_ns
    PREFIX.pack_into(out, 0, MAGIC, FORMAT_VERSION, int(kind), 0, len(header), 0, total, stamp)
    out[PREFIX_SIZE:PREFIX_SIZE + len(header)] = header
    for start, part in zip(offsets, parts, strict=True):
        if part.nbytes:
            out[start:start + part.nbytes] = memoryview(part.reshape(-1)).cast("B")
    return out


def stamp_sent(payload: bytearray, sent_ns: int | None = None) -> None:
    """Overwrite the sent time of an encoded payload in place (at publish)."""
    struct.pack_into("<q", payload, SENT_NS_OFFSET, time.time_ns() if sent_ns is None else sent_ns)


def peek_kind(payload) -> MessageKind:
    """The message kind of a payload after checking only its prefix."""
    return _prefix(_bytes_view(payload))[0]


def _bytes_view(payload) -> np.ndarray:
    """The payload as a read-only uint8 array (no copy): one buffer acquisition, then every
    array is a slice of it (cheaper than one np.frombuffer per array)."""
    try:
        return np.frombuffer(payload, dtype=_U1)
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"payload is not a bytes-like object: {exc}") from None


def _prefix(view: np.ndarray) -> tuple[MessageKind, int, int, int]:
    if len(view) < PREFIX_SIZE:
        raise ProtocolError(f"payload is {len(view)} bytes, shorter than the {PREFIX_SIZE}-byte prefix")
    magic, version, kind, res1, hlen, res2, total, sent_ns = PREFIX.unpack_from(view, 0)
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version != FORMAT_VERSION:
        raise ProtocolError(f"format version {version} is not supported (this build reads {FORMAT_VERSION})")
    message_kind = _KINDS.get(kind)  # a dict lookup: IntEnum's constructor is a slow call
    if message_kind is None:
        raise ProtocolError(f"unknown message kind {kind}")
    if res1 or res2:
        raise ProtocolError("reserved prefix fields are not zero")
    if sent_ns < 0:
        raise ProtocolError(f"sent time {sent_ns} ns is negative")
    if total != len(view):
        raise ProtocolError(f"declared length {total} bytes but {len(view)} bytes received")
    if hlen > MAX_HEADER_BYTES or PREFIX_SIZE + hlen > len(view):
        raise ProtocolError(f"header length {hlen} does not fit in {len(view)} bytes")
    return message_kind, hlen, total, sent_ns


def decode(payload, meta_type: Any = dict, expect: MessageKind | None = None) -> Envelope:
    """Validate and decode an envelope. Arrays are views of `payload` (no copy).

    `meta_type` is the msgspec type of the header meta (a Struct per message kind, or dict);
    with `expect`, any other message kind is refused before the header is read.
    Raises ProtocolError naming the problem; nothing large is allocated before the declared
    sizes have been checked against the bytes received.
    """
    view = _bytes_view(payload)
    kind, hlen, total, sent_ns = _prefix(view)
    if expect is not None and kind != expect:
        raise ProtocolError(f"expected a {expect.name.lower()} message, got {kind.name.lower()}")
    try:
        header = _header_decoder(meta_type).decode(memoryview(view[PREFIX_SIZE:PREFIX_SIZE + hlen]))
    except msgspec.ValidationError as exc:
        raise ProtocolError(f"{kind.name.lower()} header: {exc}") from None
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ProtocolError(f"header is not valid JSON: {str(exc)[:80]}") from None
    arrays: dict[str, np.ndarray] = {}
    end = PREFIX_SIZE + hlen
    float_lo, float_hi = total, 0
    for desc in header.arrays:
        name, dt, shape = desc.name, DTYPES[desc.dtype], desc.shape
        if name in arrays:
            raise ProtocolError(f"array {name!r} appears twice")
        count = math.prod(shape)
        nbytes = count * dt.itemsize
        start = _aligned(end)
        if start + nbytes > total:
            raise ProtocolError(f"array {name!r} ({nbytes} bytes at {start}) runs past the "
                                f"end of the {total}-byte payload")
        if nbytes:
            a = view[start:start + nbytes].view(dt)
            arrays[name] = a if len(shape) == 1 else a.reshape(shape)
            if dt.kind == "f":
                float_lo, float_hi = min(float_lo, start), start + nbytes
        else:
            try:  # no elements, no bytes; numpy still refuses absurd other dimensions
                arrays[name] = np.empty(shape, dtype=dt)
            except ValueError as exc:
                raise ProtocolError(f"array {name!r}: shape {list(shape)} ({exc})") from None
        end = start + nbytes
    if end != total:
        raise ProtocolError(f"arrays end at byte {end} but the payload is {total} bytes")
    return Envelope(kind, sent_ns, header.meta, arrays, view, (float_lo, float_hi))
