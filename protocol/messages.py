"""Message types on the wire: Chunk, Frame, Timing, Event, Stats (Spec: protocol.spec).

Each type encodes to the envelope of `protocol.wire` and decodes with full validation;
every failure is a `ProtocolError` naming the problem.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated, ClassVar, Literal

import msgspec
import numpy as np

from minority.protocol import check
from minority.protocol.check import Base64, Count, Name, NonNegative
from minority.protocol.errors import ProtocolError
from minority.protocol.spec import Spec
from minority.protocol.view import Side
from minority.protocol.wire import Envelope, MessageKind, decode, encode, peek_kind

MAX_RANKS = 1 << 20
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
POSITIONS = "positions"
CONTEXT_ID = "context_id"  # [context] int64: ids of a chunk's context rows (not a field)
EVICT_ID = "evict_id"  # [evicted] int64: ids the server's cache drops (not a field)
MAX_ABS_COORD_M = 1e12  # larger (or non-finite) header numbers are corrupt

# Typed header metas, checked in C by msgspec on decode; the JSON Schemas stored in logs are
# derived from them (protocol.schemas).
Seconds = Annotated[float, msgspec.Meta(ge=0.0, le=1e12)]
Coord = Annotated[float, msgspec.Meta(ge=-MAX_ABS_COORD_M, le=MAX_ABS_COORD_M)]
Corner = tuple[Coord, Coord, Coord]  # of a box, m


class ChunkMeta(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    run: Name
    step: Count
    time_s: Seconds
    rank: Annotated[int, msgspec.Meta(ge=0, lt=MAX_RANKS)]
    ranks: Annotated[int, msgspec.Meta(ge=1, le=MAX_RANKS)]
    count: Count
    spacing_m: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_ABS_COORD_M)]
    bounds_m: tuple[Corner, Corner]
    prev_time_s: Seconds | None = None  # the previous step's time (every_s cadences use it)
    # the rank keeps the server's particle cache (render_server.particles): the last
    # `context` rows are context rows, `evicted` ids leave the cache, a reset first drops
    # every cached row the rank sent (None: it does not; every row is fresh)
    context: Count | None = None
    evicted: Count = 0
    context_reset: bool = False


class FrameMeta(msgspec.Struct, forbid_unknown_fields=True):
    run: Name
    view: Name
    step: Count
    time_s: Seconds
    width: Side
    height: Side
    format: Literal["png"]


@dataclass
class Chunk:
    """One rank's particles at one step.

    fields: name -> array with first dimension n; `positions` [n, 3] float32 (m) is required,
    other fields are [n] or [n, k] (e.g. `displacement` [n, 3] float32 m).

    Context (a rank that keeps the render server's particle cache; None otherwise): the last
    len(context_ids) rows are particles outside the step's regions, sent once so the server
    draws them until they change; `context_ids` [k] int64 are their ids, `evict_ids` [e]
    int64 the cached particles the server must forget (they entered the regions or left
    the rank), and `context_reset` drops every cached row of this rank before the rest.
    """

    KIND: ClassVar[MessageKind] = MessageKind.CHUNK

    run: str
    step: int
    time_s: float  # simulated time, s
    rank: int
    ranks: int
    spacing_m: float  # particle spacing; the render sphere radius is half of it by default
    bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]]  # domain (lo, hi)
    fields: dict[str, np.ndarray]
    sent_ns: int = 0
    prev_time_s: float | None = None  # simulated time of the step before, s (None: not known)
    context_ids: np.ndarray | None = None  # [k] int64, the last k rows (None: no context)
    evict_ids: np.ndarray | None = None  # [e] int64
    context_reset: bool = False

    @property
    def count(self) -> int:
        return int(self.fields[POSITIONS].shape[0])

    @property
    def fresh(self) -> int:
        """Rows sent because the step needs them now (the rest are context rows)."""
        return self.count - (0 if self.context_ids is None else len(self.context_ids))

    @property
    def positions(self) -> np.ndarray:
        return self.fields[POSITIONS]

    def meta(self) -> ChunkMeta:
        tracked = self.context_ids is not None
        return ChunkMeta(self.run, self.step, self.time_s, self.rank, self.ranks, self.count,
                         self.spacing_m, (tuple(self.bounds_m[0]), tuple(self.bounds_m[1])),
                         self.prev_time_s, len(self.context_ids) if tracked else None,
                         len(self.evict_ids) if tracked and self.evict_ids is not None else 0,
                         self.context_reset and tracked)

    def encode(self) -> bytearray:
        pos = self.fields.get(POSITIONS)
        if pos is None or pos.ndim != 2 or pos.shape[1] != 3:
            raise ProtocolError("chunk needs a 'positions' field of shape [n, 3]")
        fields = {POSITIONS: np.asarray(pos, dtype=np.float32)}
        fields.update((k, v) for k, v in self.fields.items() if k != POSITIONS)
        if self.context_ids is not None:
            if len(self.context_ids) > len(pos):
                raise ProtocolError(f"chunk has {len(self.context_ids)} context ids for "
                                    f"{len(pos)} rows")
            fields[CONTEXT_ID] = np.asarray(self.context_ids, dtype="<i8")
            if self.evict_ids is not None and len(self.evict_ids):
                fields[EVICT_ID] = np.asarray(self.evict_ids, dtype="<i8")
        return encode(self.KIND, self.meta(), fields, self.sent_ns or None)

    @classmethod
    def from_envelope(cls, env: Envelope) -> Chunk:
        m: ChunkMeta = env.meta
        if m.rank >= m.ranks:
            raise ProtocolError(f"chunk.rank {m.rank} is not below chunk.ranks {m.ranks}")
        lo, hi = m.bounds_m
        if lo[0] > hi[0] or lo[1] > hi[1] or lo[2] > hi[2]:
            raise ProtocolError(f"chunk.bounds_m: lower corner {lo} exceeds upper corner {hi}")
        count = m.count
        pos = env.arrays.get(POSITIONS)
        if pos is None:
            raise ProtocolError("chunk has no 'positions' array")
        if pos.dtype != np.float32 or pos.shape != (count, 3):
            raise ProtocolError(f"chunk positions must be [{count}, 3] float32, "
                                f"got {list(pos.shape)} {pos.dtype}")
        arrays = dict(env.arrays)
        context_ids, evict_ids = _context_arrays(m, arrays)
        for name, array in arrays.items():
            if array.ndim not in (1, 2) or array.shape[0] != count:
                raise ProtocolError(f"field {name!r} has shape {list(array.shape)}; "
                                    f"expected [{count}] or [{count}, k]")
        env.check_finite()
        return cls(m.run, m.step, m.time_s, m.rank, m.ranks, m.spacing_m, (lo, hi),
                   arrays, env.sent_ns, m.prev_time_s, context_ids, evict_ids,
                   m.context_reset)


def _context_arrays(m: ChunkMeta, arrays: dict[str, np.ndarray]
                    ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Take a chunk's context and eviction ids out of `arrays`, checked against its header."""
    ids = arrays.pop(CONTEXT_ID, None)
    evict = arrays.pop(EVICT_ID, None)
    if m.context is None:
        if ids is not None or evict is not None or m.evicted or m.context_reset:
            raise ProtocolError("chunk has context ids, evictions or a reset but no "
                                "chunk.context count")
        return None, None
    if m.context > m.count:
        raise ProtocolError(f"chunk.context {m.context} exceeds chunk.count {m.count}")
    for name, array, n in ((CONTEXT_ID, ids, m.context), (EVICT_ID, evict, m.evicted)):
        if n and array is None:
            raise ProtocolError(f"chunk header counts {n} {name} but the array is missing")
        if array is not None and (array.dtype != np.dtype("<i8") or array.shape != (n,)):
            raise ProtocolError(f"chunk {name} must be [{n}] int64, got "
                                f"{list(array.shape)} {array.dtype}")
    empty = np.zeros(0, dtype="<i8")
    return (ids if ids is not None else empty), (evict if evict is not None else empty)


class _Stamp(msgspec.Struct, forbid_unknown_fields=True):
    sec: Count
    nsec: Count


class CompressedImage(msgspec.Struct, forbid_unknown_fields=True):
    """A Frame as logged: the fields of Foxglove's CompressedImage (so viewers show frames),
    then the frame's own."""

    timestamp: _Stamp
    frame_id: str
    format: str
    data: Base64
    run: Name
    view: Name
    step: Count
    time_s: NonNegative
    width: Count
    height: Count


@dataclass
class Frame:
    """A rendered image of one view at one step, PNG-encoded."""

    KIND: ClassVar[MessageKind] = MessageKind.FRAME

    run: str
    view: str
    step: int
    time_s: float  # simulated time, s
    width: int  # px
    height: int  # px
    png: bytes
    sent_ns: int = 0

    def meta(self) -> FrameMeta:
        return FrameMeta(self.run, self.view, self.step, self.time_s, self.width, self.height, "png")

    def encode(self) -> bytearray:
        _check_png(self.png, self.width, self.height)
        image = np.frombuffer(self.png, dtype=np.uint8)
        return encode(self.KIND, self.meta(), {"png": image}, self.sent_ns or None)

    @classmethod
    def from_envelope(cls, env: Envelope) -> Frame:
        m: FrameMeta = env.meta
        image = env.arrays.get("png")
        if image is None or len(env.arrays) != 1 or image.dtype != np.uint8 or image.ndim != 1:
            raise ProtocolError("frame must carry exactly one uint8 array 'png'")
        frame = cls(m.run, m.view, m.step, m.time_s, m.width, m.height, image.tobytes(),
                    env.sent_ns)
        _check_png(frame.png, frame.width, frame.height)
        return frame

    def to_json(self) -> dict:
        """foxglove.CompressedImage fields (so MCAP viewers show it) plus our metadata."""
        sec, nsec = divmod(self.sent_ns, 1_000_000_000)
        return check.to_json(CompressedImage(
            _Stamp(sec, nsec), self.view, "png", base64.b64encode(self.png).decode("ascii"),
            self.run, self.view, self.step, self.time_s, self.width, self.height))

    @classmethod
    def from_json(cls, obj: dict, sent_ns: int = 0) -> Frame:
        try:
            png = base64.b64decode(obj["data"], validate=True)
        except (KeyError, TypeError, ValueError) as exc:
            raise ProtocolError(f"frame.data: not base64 PNG bytes ({exc})") from None
        fields = {k: obj.get(k) for k in ("run", "view", "step", "time_s", "width", "height")}
        try:
            meta = msgspec.convert({**fields, "format": obj.get("format")}, FrameMeta)
        except msgspec.ValidationError as exc:
            raise ProtocolError(f"frame: {exc}") from None
        env = Envelope(MessageKind.FRAME, sent_ns, meta, {"png": np.frombuffer(png, np.uint8)})
        return cls.from_envelope(env)


def _check_png(png: bytes, width: int, height: int) -> None:
    if len(png) < 24 or png[:8] != PNG_SIGNATURE or png[12:16] != b"IHDR":
        raise ProtocolError("frame.png: not a PNG image (bad signature or IHDR)")
    w, h = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    if (w, h) != (width, height):
        raise ProtocolError(f"frame.png is {w}x{h} px but the header says {width}x{height}")


class _JsonMessage:
    """A message whose whole content is its header meta (no arrays): a subclass of its META
    Struct (the JSON fields) with sent_ns added."""

    __slots__ = ()
    KIND: ClassVar[MessageKind]
    META: ClassVar[type[msgspec.Struct]]

    def to_json(self) -> dict:
        d = check.to_json(self)
        del d["sent_ns"]
        return d

    def encode(self) -> bytearray:
        return encode(self.KIND, self.to_json(), None, self.sent_ns or None)

    @classmethod
    def from_meta(cls, meta, sent_ns: int = 0):
        """The message of a checked META; ProtocolError for what its types cannot say."""
        return cls(*msgspec.structs.astuple(meta), sent_ns=sent_ns)

    @classmethod
    def from_json(cls, obj: dict, sent_ns: int = 0):
        return cls.from_meta(check.convert(obj, cls.META, cls.__name__.lower()), sent_ns)

    @classmethod
    def from_envelope(cls, env: Envelope):
        if env.arrays:
            raise ProtocolError(f"{cls.__name__.lower()} must not carry arrays")
        return cls.from_meta(env.meta, env.sent_ns)


Rank = Annotated[int, msgspec.Meta(ge=0, lt=MAX_RANKS)]


class TimingMeta(msgspec.Struct, forbid_unknown_fields=True):
    run: Name
    step: Count
    view: Name
    time_s: NonNegative = 0.0  # simulated time, s
    receive_s: NonNegative = 0.0
    setup_s: NonNegative = 0.0
    render_s: NonNegative = 0.0
    bytes: Count = 0  # chunk bytes received for the step
    particles: Count = 0
    ranks_expected: Count = 0
    ranks_received: Count = 0
    incomplete: bool = False
    # of `particles`: drawn from the server's cache (sent at an earlier step, outside the
    # regions), and the age of the oldest of them, s of simulated time and steps
    cached: Count = 0
    cache_age_s: NonNegative = 0.0
    cache_age_steps: Count = 0


class Timing(TimingMeta, _JsonMessage):
    """Per step and view: receive (first chunk to assembled), setup (repartition +
    acceleration structures) and render wall times, s."""

    KIND: ClassVar[MessageKind] = MessageKind.TIMING
    META: ClassVar[type] = TimingMeta

    sent_ns: int = 0


class EventKind(StrEnum):
    RUN_START = "run_start"
    RANK_DONE = "rank_done"
    RUN_END = "run_end"
    ERROR = "error"


class EventMeta(msgspec.Struct, forbid_unknown_fields=True):
    run: Name
    kind: EventKind = msgspec.field(name="event")
    rank: Annotated[int, msgspec.Meta(ge=-1, lt=MAX_RANKS)] = -1  # -1: the server
    message: Annotated[str, msgspec.Meta(max_length=4096)] = ""
    detail: dict = {}


class Event(EventMeta, _JsonMessage):
    """Lifecycle: run start, rank done, run end, error. rank is -1 for the server."""

    KIND: ClassVar[MessageKind] = MessageKind.EVENT
    META: ClassVar[type] = EventMeta

    sent_ns: int = 0


# Speed histogram of Stats: bin 0 counts speeds below SPEED_EDGES_M_S[0], bin i (1..50) speeds
# in [edge[i-1], edge[i]), the last bin speeds from edge[-1] up; 10 bins per decade.
SPEED_EDGES_M_S = tuple(float(10.0 ** (k / 10.0 - 4.0)) for k in range(51))  # 1e-4 .. 10 m/s
SPEED_BINS = len(SPEED_EDGES_M_S) + 1
Histogram = Annotated[list[Count], msgspec.Meta(min_length=SPEED_BINS, max_length=SPEED_BINS)]


def speed_histogram(speed_m_s: np.ndarray) -> list[int]:
    """Counts of speeds [n] (m/s) in the SPEED_BINS bins of Stats."""
    idx = np.searchsorted(np.asarray(SPEED_EDGES_M_S), speed_m_s, side="right")
    return np.bincount(idx, minlength=SPEED_BINS).tolist()


class StatsMeta(msgspec.Struct, forbid_unknown_fields=True):
    run: Name
    rank: Rank
    step: Count
    time_s: NonNegative  # simulated time, s
    count: Count  # particles on the rank
    speed_sq_sum_m2_s2: NonNegative  # sum of |v|^2 over the rank's particles
    max_speed_m_s: NonNegative
    max_displacement_m: NonNegative  # max |x - x0|
    windows_open: bool
    hist_in_regions: Histogram  # speeds of particles in the open regions
    hist_elsewhere: Histogram  # the others


class Stats(StatsMeta, _JsonMessage):
    """One rank's flow statistics at one step, published on a fixed cadence of simulated time
    whether or not a view is due, so the oracle's predictions can be scored against the full
    run without sending particles. `in_regions` counts particles inside the regions of the
    windows open at time_s (all of them when an open window needs every particle, none when
    no window is open: then windows_open is false)."""

    KIND: ClassVar[MessageKind] = MessageKind.STATS
    META: ClassVar[type] = StatsMeta

    sent_ns: int = 0

    def __post_init__(self) -> None:  # numpy scalars become plain JSON numbers
        for k in ("rank", "step", "count"):
            setattr(self, k, int(getattr(self, k)))
        for k in ("time_s", "speed_sq_sum_m2_s2", "max_speed_m_s", "max_displacement_m"):
            setattr(self, k, float(getattr(self, k)))
        self.windows_open = bool(self.windows_open)
        self.hist_in_regions = [int(c) for c in self.hist_in_regions]
        self.hist_elsewhere = [int(c) for c in self.hist_elsewhere]

    @classmethod
    def from_meta(cls, meta: StatsMeta, sent_ns: int = 0) -> Stats:
        if sum(meta.hist_in_regions) + sum(meta.hist_elsewhere) != meta.count:
            raise ProtocolError("stats: histogram counts do not add up to stats.count")
        return super().from_meta(meta, sent_ns)


META_TYPES = {MessageKind.CHUNK: ChunkMeta, MessageKind.FRAME: FrameMeta,
              MessageKind.TIMING: TimingMeta, MessageKind.EVENT: EventMeta,
              MessageKind.STATS: StatsMeta}
_CLASSES = {MessageKind.CHUNK: Chunk, MessageKind.FRAME: Frame, MessageKind.TIMING: Timing,
            MessageKind.EVENT: Event, MessageKind.SPEC: Spec, MessageKind.STATS: Stats}


def decode_message(payload):
    """Decode any message type; raises ProtocolError on malformed input."""
    kind = peek_kind(payload)
    return _CLASSES[kind].from_envelope(decode(payload, META_TYPES.get(kind, dict)))


def decode_as(payload, cls):
    """Decode and require a given message type."""
    return cls.from_envelope(decode(payload, META_TYPES.get(cls.KIND, dict), expect=cls.KIND))
