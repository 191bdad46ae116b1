"""The oracle spec: which views to render, when, with which colors, of which particles.

A versioned JSON model (SPEC_VERSION 2; version 1 files still read). Specs live as JSON
files, travel as SPEC messages (the JSON as the envelope meta) and validate with errors that
start with the path of the bad field, e.g. ``views[1].schedule[0].every_s``.

- views (protocol.view): camera, image, field, colormap (ParaView preset name or inline
  RGBPoints) and range, decimation, and a schedule of time windows, each with a cadence
  and the regions of interest it needs;
- regions: named axis-aligned boxes the windows refer to;
- events: what the oracle predicts and when (name, time, tolerance);
- budget: frames and bytes the schedule was planned within;
- provenance: free-form notes on where the spec came from (checkpoint, rollout, edits).

`Spec.request(step, time_s, prev_time_s)` says what the simulation must send at a step: the union
of the fields and regions of the views due then, decimated by the views' common stride.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
from minority.protocol import check
from minority.protocol.errors import SpecError
from minority.protocol.view import Camera, InlineColormap, View, Window
from minority.protocol.wire import MAX_HEADER_BYTES, Envelope, MessageKind, encode

SPEC_VERSION = 2
READS_VERSIONS = (1, 2)
ID_FIELD = "id"  # particle ids, sent when views due at one step decimate differently
# A spec travels as one message header of at most MAX_HEADER_BYTES of compact JSON; its file
# may be indented, so it may be a few times larger, never more.
MAX_SPEC_FILE_BYTES = 4 * MAX_HEADER_BYTES
MAX_INT_DIGITS = 19  # decimal digits of a JSON integer: int64 (budget.bytes is the largest)

__all__ = ["Budget", "Camera", "DataRequest", "InlineColormap", "PredictedEvent", "Region",
           "Spec", "View", "Window"]


@dataclass(frozen=True)
class Region:
    """A named axis-aligned box of interest; a particle at x (m) is inside when
    lo_m <= x <= hi_m on every axis."""

    name: str
    lo_m: tuple[float, float, float]
    hi_m: tuple[float, float, float]

    @classmethod
    def from_dict(cls, obj, where: str) -> Region:
        r = check.keys(obj, where, {"name", "lo_m", "hi_m"}, error=SpecError)
        lo = check.vector(r["lo_m"], f"{where}.lo_m", error=SpecError)
        hi = check.vector(r["hi_m"], f"{where}.hi_m", error=SpecError)
        if not all(a <= b for a, b in zip(lo, hi, strict=True)):
            raise SpecError(f"{where}: lo_m {list(lo)} exceeds hi_m {list(hi)} on some axis")
        return cls(check.name(r["name"], f"{where}.name", SpecError), lo, hi)

    def to_dict(self) -> dict:
        return {"name": self.name, "lo_m": list(self.lo_m), "hi_m": list(self.hi_m)}


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


@dataclass(frozen=True)
class PredictedEvent:
    """Something the oracle expects at `time_s` (s), give or take `tolerance_s`."""

    name: str
    time_s: float
    tolerance_s: float = 0.0

    @classmethod
    def from_dict(cls, obj, where: str) -> PredictedEvent:
        e = check.keys(obj, where, {"name", "time_s"}, {"tolerance_s"}, error=SpecError)
        return cls(check.name(e["name"], f"{where}.name", SpecError),
                   check.number(e["time_s"], f"{where}.time_s", 0.0, None, SpecError),
                   check.number(e.get("tolerance_s", 0.0), f"{where}.tolerance_s", 0.0, None,
                                SpecError))

    def to_dict(self) -> dict:
        return {"name": self.name, "time_s": self.time_s, "tolerance_s": self.tolerance_s}


@dataclass(frozen=True)
class Budget:
    """What the schedule was planned within: rendered frames (all views) and chunk bytes
    sent by the simulation; None = no limit."""

    frames: int | None = None
    bytes: int | None = None

    @classmethod
    def from_dict(cls, obj, where: str) -> Budget:
        b = check.keys(obj, where, set(), {"frames", "bytes"}, error=SpecError)
        return cls(*(None if b.get(k) is None else check.integer(b[k], f"{where}.{k}", 1, None,
                                                                  SpecError)
                     for k in ("frames", "bytes")))

    def to_dict(self) -> dict:
        return {"frames": self.frames, "bytes": self.bytes}


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

    def request(self, step: int, time_s: float, prev_time_s: float | None = None) -> DataRequest | None:
        """What the simulation must send at this step: None when no view is due; regions None
        when a due view needs every particle."""
        views = self.wants(step, time_s, prev_time_s)
        if not views:
            return None
        fields = dict.fromkeys(v.field for v in views)
        stride = math.gcd(*(v.decimate for v in views))
        if any(v.decimate != stride for v in views):
            fields[ID_FIELD] = None  # the server picks each view's particles by id
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
        return d

    @classmethod
    def from_dict(cls, obj, sent_ns: int = 0) -> Spec:
        s = check.keys(obj, "spec", {"version", "run", "views"},
                       {"sphere_radius_m", "regions", "events", "budget", "provenance"},
                       error=SpecError)
        version = check.integer(s["version"], "version", error=SpecError)
        if version not in READS_VERSIONS:
            raise SpecError(f"version: spec version {version} is not supported "
                            f"(this build reads {', '.join(map(str, READS_VERSIONS))})")
        if not isinstance(s["views"], list) or not s["views"]:
            raise SpecError("views: expected a non-empty list")
        views = tuple(View.from_dict(v, f"views[{i}]") for i, v in enumerate(s["views"]))
        _unique([v.name for v in views], "views: view names")
        radius = s.get("sphere_radius_m")
        if radius is not None:
            radius = check.number(radius, "sphere_radius_m", 1e-9, None, SpecError)
        regions = tuple(Region.from_dict(r, f"regions[{i}]")
                        for i, r in enumerate(_list(s, "regions", "{name, lo_m, hi_m}")))
        region_names = [r.name for r in regions]
        _unique(region_names, "regions: region names")
        for i, v in enumerate(views):
            for k, w in enumerate(v.schedule):
                for j, name in enumerate(w.regions):
                    if name not in region_names:
                        where = (f"views[{i}].schedule[{k}]" if "schedule" in s["views"][i]
                                 else f"views[{i}]")
                        raise SpecError(f"{where}.regions[{j}]: no region named {name!r} "
                                        f"(regions: {region_names})")
        events = tuple(PredictedEvent.from_dict(e, f"events[{i}]")
                       for i, e in enumerate(_list(s, "events", "{name, time_s, tolerance_s}")))
        _unique([e.name for e in events], "events: event names")
        budget = Budget.from_dict(s["budget"], "budget") if s.get("budget") else Budget()
        provenance = s.get("provenance", {})
        if not isinstance(provenance, dict):
            raise SpecError("provenance: expected an object")
        return cls(run=check.name(s["run"], "run", SpecError), views=views, version=SPEC_VERSION,
                   sphere_radius_m=radius, regions=regions, events=events, budget=budget,
                   provenance=provenance, sent_ns=sent_ns)

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
        return cls.from_dict(loads_json(data, str(path)))


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


def _list(s: dict, key: str, shape: str) -> list:
    value = s.get(key, [])
    if not isinstance(value, list):
        raise SpecError(f"{key}: expected a list of {shape}")
    return value


def _unique(names: list[str], what: str) -> None:
    if len(set(names)) != len(names):
        raise SpecError(f"{what} must be unique, got {names}")
