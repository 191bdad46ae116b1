"""Message types on the wire: Chunk, Frame, Timing, Event, Stats (Spec: protocol.spec).

Each type encodes to the envelope of `protocol.wire` and decodes with full validation;
every failure is a `ProtocolError` naming the problem.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated, ClassVar, Literal

import msgspec
import numpy as np
from minority.protocol import check
from minority.protocol.errors import ProtocolError
from minority.protocol.spec import Spec
from minority.protocol.wire import Envelope, MessageKind, decode, encode, peek_kind

MAX_RANKS = 1 << 20
MAX_IMAGE_SIDE = 8192  # px
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
POSITIONS = "positions"
MAX_ABS_COORD_M = 1e12  # larger (or non-finite) header numbers are corrupt

# Typed header metas of the hot-path messages, checked in C by msgspec on decode.
Name = Annotated[str, msgspec.Meta(pattern=check.NAME_RE.pattern)]
Count = Annotated[int, msgspec.Meta(ge=0, le=1 << 40)]
Seconds = Annotated[float, msgspec.Meta(ge=0.0, le=1e12)]
Coord = Annotated[float, msgspec.Meta(ge=-MAX_ABS_COORD_M, le=MAX_ABS_COORD_M)]
Vec3 = tuple[Coord, Coord, Coord]
Side = Annotated[int, msgspec.Meta(ge=1, le=MAX_IMAGE_SIDE)]


class ChunkMeta(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    run: Name
    step: Count
    time_s: Seconds
    rank: Annotated[int, msgspec.Meta(ge=0, lt=MAX_RANKS)]
    ranks: Annotated[int, msgspec.Meta(ge=1, le=MAX_RANKS)]
    count: Count
    spacing_m: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_ABS_COORD_M)]
    bounds_m: tuple[Vec3, Vec3]
    prev_time_s: Seconds | None = None  # the previous step's time (every_s cadences use it)


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

    @property
    def count(self) -> int:
        return int(self.fields[POSITIONS].shape[0])

    @property
    def positions(self) -> np.ndarray:
        return self.fields[POSITIONS]

    def meta(self) -> ChunkMeta:
        return ChunkMeta(self.run, self.step, self.time_s, self.rank, self.ranks, self.count,
                         self.spacing_m, (tuple(self.bounds_m[0]), tuple(self.bounds_m[1])),
                         self.prev_time_s)

    def encode(self) -> bytearray:
        pos = self.fields.get(POSITIONS)
        if pos is None or pos.ndim != 2 or pos.shape[1] != 3:
            raise ProtocolError("chunk needs a 'positions' field of shape [n, 3]")
        fields = {POSITIONS: np.asarray(pos, dtype=np.float32)}
        fields.update((k, v) for k, v in self.fields.items() if k != POSITIONS)
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
        for name, array in env.arrays.items():
            if array.ndim not in (1, 2) or array.shape[0] != count:
                raise ProtocolError(f"field {name!r} has shape {list(array.shape)}; "
                                    f"expected [{count}] or [{count}, k]")
        env.check_finite()
        return cls(m.run, m.step, m.time_s, m.rank, m.ranks, m.spacing_m, (lo, hi),
                   dict(env.arrays), env.sent_ns, m.prev_time_s)


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
        return {"timestamp": {"sec": sec, "nsec": nsec}, "frame_id": self.view,
                "format": "png", "data": base64.b64encode(self.png).decode("ascii"),
                "run": self.run, "view": self.view, "step": self.step, "time_s": self.time_s,
                "width": self.width, "height": self.height}

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
    """A message whose whole content is its header meta (no arrays)."""

    KIND: ClassVar[MessageKind]
    sent_ns: int

    def to_json(self) -> dict:
        raise NotImplementedError

    def encode(self) -> bytearray:
        return encode(self.KIND, self.to_json(), None, self.sent_ns or None)

    @classmethod
    def from_json(cls, obj: dict, sent_ns: int = 0):
        raise NotImplementedError

    @classmethod
    def from_envelope(cls, env: Envelope):
        if env.arrays:
            raise ProtocolError(f"{cls.__name__.lower()} must not carry arrays")
        return cls.from_json(env.meta, env.sent_ns)


TIMING_NUMBERS = ("time_s", "receive_s", "setup_s", "render_s")
TIMING_COUNTS = ("bytes", "particles", "ranks_expected", "ranks_received")


@dataclass
class Timing(_JsonMessage):
    """Per step and view: receive (first chunk to assembled), setup (repartition +
    acceleration structures) and render wall times, s."""

    KIND: ClassVar[MessageKind] = MessageKind.TIMING

    run: str
    step: int
    view: str
    time_s: float = 0.0  # simulated time, s
    receive_s: float = 0.0
    setup_s: float = 0.0
    render_s: float = 0.0
    bytes: int = 0  # chunk bytes received for the step
    particles: int = 0
    ranks_expected: int = 0
    ranks_received: int = 0
    incomplete: bool = False
    sent_ns: int = 0

    def to_json(self) -> dict:
        return {"run": self.run, "step": self.step, "view": self.view,
                **{k: getattr(self, k) for k in TIMING_NUMBERS + TIMING_COUNTS},
                "incomplete": self.incomplete}

    @classmethod
    def from_json(cls, obj: dict, sent_ns: int = 0) -> Timing:
        m = check.keys(obj, "timing", {"run", "step", "view", "incomplete",
                                       *TIMING_NUMBERS, *TIMING_COUNTS})
        return cls(run=check.name(m["run"], "timing.run"),
                   step=check.integer(m["step"], "timing.step", 0),
                   view=check.name(m["view"], "timing.view"),
                   **{k: check.number(m[k], f"timing.{k}", 0.0) for k in TIMING_NUMBERS},
                   **{k: check.integer(m[k], f"timing.{k}", 0) for k in TIMING_COUNTS},
                   incomplete=check.boolean(m["incomplete"], "timing.incomplete"),
                   sent_ns=sent_ns)


class EventKind(StrEnum):
    RUN_START = "run_start"
    RANK_DONE = "rank_done"
    RUN_END = "run_end"
    ERROR = "error"


@dataclass
class Event(_JsonMessage):
    """Lifecycle: run start, rank done, run end, error. rank is -1 for the server."""

    KIND: ClassVar[MessageKind] = MessageKind.EVENT

    run: str
    kind: EventKind
    rank: int = -1
    message: str = ""
    detail: dict = field(default_factory=dict)
    sent_ns: int = 0

    def to_json(self) -> dict:
        return {"run": self.run, "event": str(self.kind), "rank": self.rank,
                "message": self.message, "detail": self.detail}

    @classmethod
    def from_json(cls, obj: dict, sent_ns: int = 0) -> Event:
        m = check.keys(obj, "event", {"run", "event", "rank", "message", "detail"})
        try:
            kind = EventKind(m["event"])
        except ValueError:
            raise ProtocolError(f"event.event: {m['event']!r:.40} is not one of "
                                f"{[str(k) for k in EventKind]}") from None
        if not isinstance(m["detail"], dict):
            raise ProtocolError("event.detail: expected an object")
        return cls(run=check.name(m["run"], "event.run"), kind=kind,
                   rank=check.integer(m["rank"], "event.rank", -1, MAX_RANKS),
                   message=check.text(m["message"], "event.message"), detail=m["detail"],
                   sent_ns=sent_ns)


# Speed histogram of Stats: bin 0 counts speeds below SPEED_EDGES_M_S[0], bin i (1..50) speeds
# in [edge[i-1], edge[i]), the last bin speeds from edge[-1] up; 10 bins per decade.
SPEED_EDGES_M_S = tuple(float(10.0 ** (k / 10.0 - 4.0)) for k in range(51))  # 1e-4 .. 10 m/s
SPEED_BINS = len(SPEED_EDGES_M_S) + 1


def speed_histogram(speed_m_s: np.ndarray) -> list[int]:
    """Counts of speeds [n] (m/s) in the SPEED_BINS bins of Stats."""
    idx = np.searchsorted(np.asarray(SPEED_EDGES_M_S), speed_m_s, side="right")
    return np.bincount(idx, minlength=SPEED_BINS).tolist()


@dataclass
class Stats(_JsonMessage):
    """One rank's flow statistics at one step, published on a fixed cadence of simulated time
    whether or not a view is due, so the oracle's predictions can be scored against the full
    run without sending particles. `in_regions` counts particles inside the regions of the
    windows open at time_s (all of them when an open window needs every particle, none when
    no window is open: then windows_open is false)."""

    KIND: ClassVar[MessageKind] = MessageKind.STATS

    run: str
    rank: int
    step: int
    time_s: float  # simulated time, s
    count: int  # particles on the rank
    speed_sq_sum_m2_s2: float  # sum of |v|^2 over the rank's particles
    max_speed_m_s: float
    max_displacement_m: float  # max |x - x0|
    windows_open: bool
    hist_in_regions: list[int]  # [SPEED_BINS] speeds of particles in the open regions
    hist_elsewhere: list[int]  # [SPEED_BINS] the others
    sent_ns: int = 0

    def to_json(self) -> dict:  # numpy scalars become plain JSON numbers
        d = {k: getattr(self, k) for k in _STATS_KEYS}
        for k in ("time_s", "speed_sq_sum_m2_s2", "max_speed_m_s", "max_displacement_m"):
            d[k] = float(d[k])
        for k in ("rank", "step", "count"):
            d[k] = int(d[k])
        d["windows_open"] = bool(d["windows_open"])
        d["hist_in_regions"] = [int(c) for c in d["hist_in_regions"]]
        d["hist_elsewhere"] = [int(c) for c in d["hist_elsewhere"]]
        return d

    @classmethod
    def from_json(cls, obj: dict, sent_ns: int = 0) -> Stats:
        m = check.keys(obj, "stats", set(_STATS_KEYS))
        hists = {}
        for k in ("hist_in_regions", "hist_elsewhere"):
            h = m[k]
            if not isinstance(h, list) or len(h) != SPEED_BINS:
                raise ProtocolError(f"stats.{k}: expected a list of {SPEED_BINS} counts")
            hists[k] = [check.integer(c, f"stats.{k}[{i}]", 0) for i, c in enumerate(h)]
        if sum(hists["hist_in_regions"]) + sum(hists["hist_elsewhere"]) != m["count"]:
            raise ProtocolError("stats: histogram counts do not add up to stats.count")
        return cls(run=check.name(m["run"], "stats.run"),
                   rank=check.integer(m["rank"], "stats.rank", 0, MAX_RANKS),
                   step=check.integer(m["step"], "stats.step", 0),
                   time_s=check.number(m["time_s"], "stats.time_s", 0.0),
                   count=check.integer(m["count"], "stats.count", 0),
                   **{k: check.number(m[k], f"stats.{k}", 0.0)
                      for k in ("speed_sq_sum_m2_s2", "max_speed_m_s", "max_displacement_m")},
                   windows_open=check.boolean(m["windows_open"], "stats.windows_open"),
                   **hists, sent_ns=sent_ns)


_STATS_KEYS = ("run", "rank", "step", "time_s", "count", "speed_sq_sum_m2_s2", "max_speed_m_s",
               "max_displacement_m", "windows_open", "hist_in_regions", "hist_elsewhere")

META_TYPES = {MessageKind.CHUNK: ChunkMeta, MessageKind.FRAME: FrameMeta}
_CLASSES = {MessageKind.CHUNK: Chunk, MessageKind.FRAME: Frame, MessageKind.TIMING: Timing,
            MessageKind.EVENT: Event, MessageKind.SPEC: Spec, MessageKind.STATS: Stats}


def decode_message(payload):
    """Decode any message type; raises ProtocolError on malformed input."""
    kind = peek_kind(payload)
    return _CLASSES[kind].from_envelope(decode(payload, META_TYPES.get(kind, dict)))


def decode_as(payload, cls):
    """Decode and require a given message type."""
    return cls.from_envelope(decode(payload, META_TYPES.get(cls.KIND, dict), expect=cls.KIND))
