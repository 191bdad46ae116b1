"""The oracle spec: which views to render, when, with which colors, of which particles.

A versioned JSON model (SPEC_VERSION 2; version 1 files still read). Specs live as JSON
files, travel as SPEC messages (the JSON as the envelope meta) and validate with errors that
start with the path of the bad field, e.g. ``views[1].schedule[0].every_s``. The JSON form is
defined once, by msgspec types (SpecDocument and those it holds): they check what is read and
give the JSON Schema stored in logs (protocol.schemas); the rest of the checks (names unique,
regions that exist, ...) are the from_document methods'.

- views (protocol.view): camera, image, field, colormap (ParaView preset name or inline
  RGBPoints) and range, decimation, and a schedule of time windows, each with a cadence
  and the regions of interest it needs;
- regions: named axis-aligned boxes the windows refer to;
- events: what the oracle predicts and when (name, time, tolerance; an ensemble oracle adds
  the interval its members span, earliest_s..latest_s);
- budget: frames and bytes the schedule was planned within;
- provenance: free-form notes on where the spec came from (checkpoint, rollout, edits);
- deposit (optional): an ensemble oracle's predicted final deposit, per member and as a band;
- snapshots (optional): simulated times (s) at which every rank sends every particle
  (positions and displacement, no regions, decimation or culling), e.g. for the oracle that
  follows the run (minority oracle follow) to roll its GNS forward from the run's state.

`Spec.request(step, time_s, prev_time_s)` says what the simulation must send at a step: the union
of the fields and regions of the views due then, decimated by the views' common stride; at a
snapshot's step, every particle with displacement besides (merged with any view due then).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, ClassVar

import msgspec
import numpy as np

from minority.protocol import check
from minority.protocol.check import Name, NonNegative, Positive, Vec3
from minority.protocol.errors import SpecError
from minority.protocol.view import (
    Camera,
    InlineColormap,
    View,
    ViewDocument,
    Window,
    one_window_shorthand,
    shorthand_paths,
)
from minority.protocol.wire import MAX_HEADER_BYTES, Envelope, MessageKind, encode

SPEC_VERSION = 2
READS_VERSIONS = (1, 2)
ID_FIELD = "id"  # particle ids, sent when views due at one step decimate differently
# A spec travels as one message header of at most MAX_HEADER_BYTES of compact JSON; its file
# may be indented, so it may be a few times larger, never more.
MAX_SPEC_FILE_BYTES = 4 * MAX_HEADER_BYTES
MAX_INT_DIGITS = 19  # decimal digits of a JSON integer: int64 (budget.bytes is the largest)
SNAPSHOT_FIELD = "displacement"  # a snapshot's field besides positions: x - displacement = x0
MAX_SNAPSHOTS = 64  # snapshot times a spec may name

__all__ = ["Budget", "Camera", "DataRequest", "DepositSpread", "InlineColormap",
           "PredictedEvent", "Region", "Spec", "Spread", "View", "Window"]


class Region(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A named axis-aligned box of interest; a particle at x (m) is inside when
    lo_m <= x <= hi_m on every axis."""

    name: Name
    lo_m: Vec3
    hi_m: Vec3

    def checked(self, where: str) -> Region:
        if not all(a <= b for a, b in zip(self.lo_m, self.hi_m, strict=True)):
            raise SpecError(f"{where}: lo_m {list(self.lo_m)} exceeds hi_m {list(self.hi_m)} "
                            "on some axis")
        return self

    def to_dict(self) -> dict:
        return check.to_json(self)


def inside_mask(x: np.ndarray, regions: tuple[Region, ...]) -> np.ndarray:
    """[n] bool: whether each point x [n, 3] (m) lies inside any of the boxes (bounds
    included), compared in float64 whatever x's dtype; the one test the simulation (what it
    sends) and the server (what a view shows) share. Axis by axis on columns: 5x faster
    than comparing [n, 3] rows."""
    keep = np.zeros(x.shape[0], dtype=bool)
    for r in regions:
        box = np.ones(x.shape[0], dtype=bool)
        for axis in range(3):
            c = x[:, axis]
            box &= (c >= np.float64(r.lo_m[axis])) & (c <= np.float64(r.hi_m[axis]))
        keep |= box
    return keep


class PredictedEvent(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Something the oracle expects at `time_s` (s), give or take `tolerance_s`; an
    ensemble oracle adds the interval [earliest_s, latest_s] (s) its members' times span
    (widened as the oracle states in its provenance). Both bounds or neither; a spec
    without them encodes as before they existed."""

    name: Name
    time_s: NonNegative
    tolerance_s: NonNegative = 0.0
    earliest_s: NonNegative | None = None
    latest_s: NonNegative | None = None

    def checked(self, where: str) -> PredictedEvent:
        if (self.earliest_s is None) != (self.latest_s is None):
            raise SpecError(f"{where}: earliest_s and latest_s come together (got only "
                            f"{'earliest_s' if self.latest_s is None else 'latest_s'})")
        if self.earliest_s is not None and self.earliest_s > self.latest_s:
            raise SpecError(f"{where}: earliest_s {self.earliest_s} exceeds latest_s "
                            f"{self.latest_s}")
        return self

    @property
    def interval_s(self) -> tuple[float, float] | None:
        """(earliest, latest), s; None for an event without an interval."""
        return None if self.earliest_s is None else (self.earliest_s, self.latest_s)

    def to_dict(self) -> dict:
        d = check.to_json(self)
        if self.earliest_s is None:  # the interval is optional: old specs stay byte-identical
            del d["earliest_s"], d["latest_s"]
        return d


class Spread(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One measure of the predicted deposit over an ensemble: each member's value and the
    band [low, high] the oracle states (the members' range, widened as its provenance
    says)."""

    low: float
    high: float
    members: Annotated[tuple[float, ...], msgspec.Meta(min_length=1)]

    def checked(self, where: str) -> Spread:
        if not all(math.isfinite(v) for v in (self.low, self.high, *self.members)):
            raise SpecError(f"{where}: values must be finite")
        if self.low > self.high:
            raise SpecError(f"{where}: low {self.low} exceeds high {self.high}")
        return self


class DepositSpread(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The final deposit an ensemble oracle predicts, m (gns.metrics.deposit): the front
    (runout, from the back wall x = 0), the height (from the floor) and the largest
    displacement, each per member and as a band."""

    runout_m: Spread
    height_m: Spread
    displacement_max_m: Spread

    def checked(self, where: str) -> DepositSpread:
        counts = set()
        for name in ("runout_m", "height_m", "displacement_max_m"):
            counts.add(len(getattr(self, name).checked(f"{where}.{name}").members))
        if len(counts) != 1:
            raise SpecError(f"{where}: every measure needs one value per member (got "
                            f"{sorted(counts)} values)")
        return self

    def to_dict(self) -> dict:
        return check.to_json(self)


class Budget(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """What the schedule was planned within: rendered frames (all views) and chunk bytes
    sent by the simulation; None = no limit."""

    frames: Positive | None = None
    bytes: Positive | None = None

    def to_dict(self) -> dict:
        return check.to_json(self)


class SpecDocument(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A Spec as JSON (a file, or a SPEC message's meta)."""

    version: int
    run: Name
    views: Annotated[tuple[ViewDocument, ...], msgspec.Meta(min_length=1)]
    sphere_radius_m: Annotated[float, msgspec.Meta(ge=1e-9, le=check.FLOAT_MAX)] | None = None
    regions: tuple[Region, ...] = ()
    events: tuple[PredictedEvent, ...] = ()
    budget: Budget | None = None
    provenance: dict = {}
    deposit: DepositSpread | None = None
    snapshots: Annotated[tuple[NonNegative, ...], msgspec.Meta(max_length=MAX_SNAPSHOTS)] = ()


@dataclass(frozen=True)
class DataRequest:
    """What the simulation sends at one step: `fields` (besides positions) for every
    `decimate`-th particle (by id) inside any of `regions`, or anywhere when `regions` is
    None."""

    views: tuple[str, ...]  # the views due at the step
    fields: tuple[str, ...]  # in first-use order
    regions: tuple[Region, ...] | None
    decimate: int = 1
    # when every due view has occlusion_cull: each due view with the regions it shows (None:
    # every particle); send only particles visible in one of them among what it renders
    visible_in: tuple[tuple[View, tuple[Region, ...] | None], ...] = ()
    snapshot: bool = False  # a spec's snapshot: every particle, whatever the views need


@dataclass(frozen=True)
class Spec:
    """The oracle spec of one run."""

    KIND: ClassVar[MessageKind] = MessageKind.SPEC

    run: str
    views: tuple[View, ...]
    version: int = SPEC_VERSION
    sphere_radius_m: float | None = None  # render radius; None: half the particle spacing
    regions: tuple[Region, ...] = ()  # regions of interest the windows refer to by name
    events: tuple[PredictedEvent, ...] = ()
    budget: Budget = Budget()
    provenance: dict = field(default_factory=dict, compare=False)
    deposit: DepositSpread | None = None  # an ensemble oracle's predicted deposit spread
    snapshots: tuple[float, ...] = ()  # s: every rank sends every particle at these times
    sent_ns: int = field(default=0, compare=False)

    @property
    def fields(self) -> tuple[str, ...]:
        """Particle fields the sim must send besides positions, in first-use order."""
        return tuple(dict.fromkeys(v.field for v in self.views))

    def region(self, name: str) -> Region:
        return next(r for r in self.regions if r.name == name)

    def wants(self, step: int, time_s: float, prev_time_s: float | None = None) -> list[View]:
        """The views due at sim step `step`, time `time_s`, reached from `prev_time_s` (s)."""
        return [v for v in self.views if v.wants(step, time_s, prev_time_s)]

    def view_regions(self, view: View, step: int, time_s: float,
                     prev_time_s: float | None = None) -> tuple[Region, ...] | None:
        """The regions `view` shows at this step (None: every particle; the view must be due)."""
        names = view.window(step, time_s, prev_time_s).regions
        return tuple(self.region(n) for n in names) if names else None

    def snapshot_due(self, time_s: float, prev_time_s: float | None = None) -> bool:
        """Whether a snapshot time lies in (prev_time_s, time_s] (s), as an every_s instant
        falls to one step (prev_time_s None: when time_s is one)."""
        if prev_time_s is None:
            return time_s in self.snapshots
        return any(prev_time_s < t <= time_s for t in self.snapshots)

    def request(self, step: int, time_s: float, prev_time_s: float | None = None) -> DataRequest | None:
        """What the simulation must send at this step: None when no view is due and no
        snapshot; regions None when a due view needs every particle. A snapshot sends every
        particle, undecimated and unculled, with the due views' fields (or, when none is
        due, every view's) and the displacement."""
        views = self.wants(step, time_s, prev_time_s)
        snapshot = bool(self.snapshots) and self.snapshot_due(time_s, prev_time_s)
        if not views and not snapshot:
            return None
        fields = dict.fromkeys(v.field for v in (views or self.views))
        stride = math.gcd(*(v.decimate for v in views)) if views and not snapshot else 1
        if any(v.decimate != stride for v in views):
            fields[ID_FIELD] = None  # the server picks each view's particles by id
        if snapshot:
            fields[SNAPSHOT_FIELD] = None
            return DataRequest(tuple(v.name for v in views), tuple(fields), None, 1, (), True)
        boxes = [self.view_regions(v, step, time_s, prev_time_s) for v in views]
        regions = (None if any(b is None for b in boxes)
                   else tuple(dict.fromkeys(r for b in boxes for r in b)))
        visible_in = (tuple(zip(views, boxes, strict=True))
                      if all(v.occlusion_cull for v in views) else ())
        return DataRequest(tuple(v.name for v in views), tuple(fields), regions, stride,
                           visible_in)

    def active_regions(self, time_s: float) -> tuple[Region, ...] | None:
        """The union of the regions of every window open at `time_s` (cadence aside):
        None when an open window needs every particle, () when no window is open."""
        windows = [w for v in self.views for w in v.schedule if w.contains(time_s)]
        if any(not w.regions for w in windows):
            return None
        return tuple(self.region(n) for n in dict.fromkeys(r for w in windows for r in w.regions))

    def planned_frames(self, duration_s: float, dt_s: float) -> int:
        """About how many frames a run of `duration_s` with steps of `dt_s` (s) renders."""
        return sum(v.planned_frames(duration_s, dt_s) for v in self.views)

    def to_dict(self) -> dict:
        d = {"version": SPEC_VERSION, "run": self.run, "views": [v.to_dict() for v in self.views]}
        if self.sphere_radius_m is not None:
            d["sphere_radius_m"] = self.sphere_radius_m
        d["regions"] = [r.to_dict() for r in self.regions]
        d["events"] = [e.to_dict() for e in self.events]
        d["budget"] = self.budget.to_dict()
        if self.provenance:
            d["provenance"] = self.provenance
        if self.deposit is not None:  # optional: a spec without it encodes as before
            d["deposit"] = self.deposit.to_dict()
        if self.snapshots:  # optional, as deposit
            d["snapshots"] = list(self.snapshots)
        return d

    @classmethod
    def from_dict(cls, obj, sent_ns: int = 0) -> Spec:
        """The Spec of a decoded JSON object; SpecError "{path}: {problem}" otherwise."""
        if isinstance(obj, dict) and "version" in obj:
            version = check.convert(obj["version"], int, "version", SpecError)
            if version not in READS_VERSIONS:
                raise SpecError(f"version: spec version {version} is not supported "
                                f"(this build reads {', '.join(map(str, READS_VERSIONS))})")
        flat: list[str] = []  # the views given in the one-window shorthand
        if isinstance(obj, dict) and isinstance(obj.get("views"), list):
            views = []
            for i, view in enumerate(obj["views"]):
                views.append(one_window_shorthand(view, f"views[{i}]"))
                if views[-1] is not view:
                    flat.append(f"views[{i}]")
            obj = {**obj, "views": views}
        try:
            return cls.from_document(check.convert(obj, SpecDocument, "", SpecError, "spec"), sent_ns)
        except SpecError as exc:
            raise shorthand_paths(exc, flat) from None

    @classmethod
    def from_document(cls, s: SpecDocument, sent_ns: int = 0) -> Spec:
        views = tuple(View.from_document(v, f"views[{i}]") for i, v in enumerate(s.views))
        _unique([v.name for v in views], "views: view names")
        regions = tuple(r.checked(f"regions[{i}]") for i, r in enumerate(s.regions))
        region_names = [r.name for r in regions]
        _unique(region_names, "regions: region names")
        for i, v in enumerate(views):
            for k, w in enumerate(v.schedule):
                for j, name in enumerate(w.regions):
                    if name not in region_names:
                        raise SpecError(f"views[{i}].schedule[{k}].regions[{j}]: no region named "
                                        f"{name!r} (regions: {region_names})")
        _unique([e.name for e in s.events], "events: event names")
        events = tuple(e.checked(f"events[{i}]") for i, e in enumerate(s.events))
        deposit = s.deposit.checked("deposit") if s.deposit is not None else None
        if list(s.snapshots) != sorted(set(s.snapshots)):
            raise SpecError(f"snapshots: times must increase, got {list(s.snapshots)}")
        return cls(run=s.run, views=views, version=SPEC_VERSION,
                   sphere_radius_m=s.sphere_radius_m, regions=regions, events=events,
                   budget=s.budget or Budget(), provenance=s.provenance, deposit=deposit,
                   snapshots=tuple(s.snapshots), sent_ns=sent_ns)

    # wire and file forms
    def to_json(self) -> dict:
        return self.to_dict()

    from_json = from_dict

    def encode(self) -> bytearray:
        return encode(self.KIND, self.to_dict(), None, self.sent_ns or None)

    @classmethod
    def from_envelope(cls, env: Envelope) -> Spec:
        if env.arrays:
            raise SpecError("spec messages carry no arrays")
        return cls.from_dict(env.meta, env.sent_ns)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Spec:
        """Read a spec file; SpecError names the file and the problem (OSError when the file
        cannot be read)."""
        with open(path, "rb") as f:
            data = f.read(MAX_SPEC_FILE_BYTES + 1)
        if len(data) > MAX_SPEC_FILE_BYTES:
            raise SpecError(f"{path}: larger than {MAX_SPEC_FILE_BYTES} bytes "
                            "(MAX_SPEC_FILE_BYTES), not a spec")
        obj = loads_json(data, str(path))
        try:
            return cls.from_dict(obj)
        except SpecError as exc:
            raise SpecError(f"{path}: {exc}") from None


def render_radius_m(spec: Spec | None, spacing_m: float) -> float:
    """The sphere radius particles `spacing_m` apart (m) render with: the spec's
    sphere_radius_m, or half the spacing when it gives none (or there is no spec)."""
    return (spec.sphere_radius_m if spec is not None else None) or 0.5 * spacing_m


class _Refused(ValueError):
    """A JSON token that a spec file must not hold (raised by the json.loads hooks)."""


def _parse_int(token: str) -> int:
    digits = len(token.lstrip("-"))
    if digits > MAX_INT_DIGITS:  # before int(): its cost grows with the digits
        raise _Refused(f"holds a {digits}-digit integer (at most {MAX_INT_DIGITS} digits: "
                       "64-bit integers)")
    return int(token)


def _parse_float(token: str) -> float:
    value = float(token)
    if not math.isfinite(value):
        raise _Refused(f"holds the number {token[:40]}, beyond the range of a 64-bit float")
    return value


def _parse_constant(token: str):
    raise _Refused(f"holds {token} (JSON has no NaN or Infinity; the wire refuses them)")


def loads_json(data: bytes | str, where: str):
    """The JSON document in `data` as a spec file may hold it: UTF-8, 64-bit integers, finite
    numbers, nesting within what the parser allows (about a thousand levels); SpecError
    "{where}: ..." otherwise. What loads here encodes as a SPEC message."""
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise SpecError(f"{where}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset "
                            f"{exc.start})") from None
    try:
        return json.loads(data, parse_int=_parse_int, parse_float=_parse_float,
                          parse_constant=_parse_constant)
    except _Refused as exc:
        raise SpecError(f"{where}: {exc}") from None
    except json.JSONDecodeError as exc:
        raise SpecError(f"{where}: not valid JSON ({exc})") from None
    except RecursionError:  # the C scanner counts its depth: no stack is exhausted
        raise SpecError(f"{where}: JSON nested too deeply for the parser (about "
                        f"{sys.getrecursionlimit()} levels; a spec needs fewer than 10)") from None


def _unique(names: list[str], what: str) -> None:
    if len(set(names)) != len(names):
        raise SpecError(f"{what} must be unique, got {names}")
