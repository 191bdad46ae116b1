"""The oracle spec: which views to render, when, with which colors, of which particles.

A minimal versioned model (SPEC_VERSION 1); the oracle issue completes it. Specs live as
JSON files, travel as SPEC messages (the JSON as the envelope meta) and validate with
errors that start with the path of the bad field, e.g. ``views[1].camera.view_up``.

Regions of interest (optional, still version 1): the spec may name axis-aligned boxes
(`regions`), and a view may list the regions whose particles it needs (`views[i].regions`).
A view without regions needs every particle. `Spec.request(step, time_s)` says what the
simulation must send at a step: the union of the fields and of the regions of the views
scheduled then. A spec without regions reads and writes exactly as before.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

from protocol import check
from protocol.errors import SpecError
from protocol.wire import Envelope, MessageKind, encode

SPEC_VERSION = 1
MAX_IMAGE_SIDE = 8192  # px; 3840x2160 is the largest size the server is tested with


@dataclass(frozen=True)
class Camera:
    """VTK camera model: positions in m, view angle in degrees (vertical), or parallel
    projection with parallel_scale = half the view height in m."""

    position: tuple[float, float, float]
    focal_point: tuple[float, float, float]
    view_up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    view_angle_deg: float = 30.0
    parallel_projection: bool = False
    parallel_scale_m: float = 1.0

    @classmethod
    def from_dict(cls, obj, where: str) -> Camera:
        c = check.keys(obj, where, {"position", "focal_point"},
                       {"view_up", "view_angle_deg", "parallel_projection", "parallel_scale_m"},
                       error=SpecError)
        cam = cls(position=check.vector(c["position"], f"{where}.position", error=SpecError),
                  focal_point=check.vector(c["focal_point"], f"{where}.focal_point", error=SpecError),
                  view_up=check.vector(c.get("view_up", cls.view_up), f"{where}.view_up",
                                       error=SpecError),
                  view_angle_deg=check.number(c.get("view_angle_deg", cls.view_angle_deg),
                                              f"{where}.view_angle_deg", 0.1, 179.0, SpecError),
                  parallel_projection=check.boolean(c.get("parallel_projection", False),
                                                    f"{where}.parallel_projection", SpecError),
                  parallel_scale_m=check.number(c.get("parallel_scale_m", cls.parallel_scale_m),
                                                f"{where}.parallel_scale_m", 1e-9, None, SpecError))
        direction = [f - p for f, p in zip(cam.focal_point, cam.position, strict=True)]
        if math.hypot(*direction) == 0.0:
            raise SpecError(f"{where}: position and focal_point coincide")
        cross = (direction[1] * cam.view_up[2] - direction[2] * cam.view_up[1],
                 direction[2] * cam.view_up[0] - direction[0] * cam.view_up[2],
                 direction[0] * cam.view_up[1] - direction[1] * cam.view_up[0])
        if math.hypot(*cross) <= 1e-12 * math.hypot(*direction) * max(math.hypot(*cam.view_up), 1e-300):
            raise SpecError(f"{where}.view_up: parallel to the view direction (or zero)")
        return cam


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


@dataclass(frozen=True)
class DataRequest:
    """What the simulation sends at one step: `fields` (besides positions) for the particles
    inside any of `regions`, or for every particle when `regions` is None."""

    views: tuple[str, ...]  # the views scheduled at the step
    fields: tuple[str, ...]  # in first-use order
    regions: tuple[Region, ...] | None


@dataclass(frozen=True)
class View:
    """One rendered view: camera, image, colors, and when to render it."""

    name: str
    camera: Camera
    width: int = 1024  # px
    height: int = 768  # px
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # RGB in [0, 1]
    field: str = "displacement"  # colored by magnitude if vector-valued
    colormap: str = "Viridis (matplotlib)"  # ParaView preset name
    range: tuple[float, float] = (0.0, 1.0)  # colormap range, units of the field
    t_start_s: float = 0.0  # simulated time window, s
    t_end_s: float = math.inf
    every_steps: int = 20  # cadence: render every n-th sim step inside the window
    regions: tuple[str, ...] = ()  # names of the spec's regions it shows; () = everything

    @classmethod
    def from_dict(cls, obj, where: str) -> View:
        v = check.keys(obj, where, {"name", "camera"},
                       {"width", "height", "background", "field", "colormap", "range",
                        "t_start_s", "t_end_s", "every_steps", "regions"}, error=SpecError)
        regions = v.get("regions", [])
        if not isinstance(regions, list):
            raise SpecError(f"{where}.regions: expected a list of region names")
        rng = check.vector(v.get("range", cls.range), f"{where}.range", 2, SpecError)
        if not rng[0] < rng[1]:
            raise SpecError(f"{where}.range: lower bound {rng[0]} must be below upper {rng[1]}")
        t0 = check.number(v.get("t_start_s", 0.0), f"{where}.t_start_s", 0.0, None, SpecError)
        t1 = v.get("t_end_s")
        t1 = math.inf if t1 is None else check.number(t1, f"{where}.t_end_s", t0, None, SpecError)
        background = check.vector(v.get("background", cls.background), f"{where}.background",
                                  3, SpecError)
        if not all(0.0 <= b <= 1.0 for b in background):
            raise SpecError(f"{where}.background: RGB components must lie in [0, 1]")
        return cls(name=check.name(v["name"], f"{where}.name", SpecError),
                   camera=Camera.from_dict(v["camera"], f"{where}.camera"),
                   width=check.integer(v.get("width", cls.width), f"{where}.width", 1,
                                       MAX_IMAGE_SIDE, SpecError),
                   height=check.integer(v.get("height", cls.height), f"{where}.height", 1,
                                        MAX_IMAGE_SIDE, SpecError),
                   background=background,
                   field=check.name(v.get("field", cls.field), f"{where}.field", SpecError),
                   colormap=check.text(v.get("colormap", cls.colormap), f"{where}.colormap", 128,
                                       SpecError),
                   range=rng, t_start_s=t0, t_end_s=t1,
                   every_steps=check.integer(v.get("every_steps", cls.every_steps),
                                             f"{where}.every_steps", 1, None, SpecError),
                   regions=tuple(check.name(r, f"{where}.regions[{i}]", SpecError)
                                 for i, r in enumerate(regions)))

    def wants(self, step: int, time_s: float) -> bool:
        """Whether this view renders sim step `step` at simulated time `time_s` (s)."""
        return self.t_start_s <= time_s <= self.t_end_s and step % self.every_steps == 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["t_end_s"] = None if math.isinf(self.t_end_s) else self.t_end_s
        if self.regions:
            d["regions"] = list(self.regions)
        else:
            del d["regions"]  # a spec without regions writes as before
        return d


@dataclass(frozen=True)
class Spec:
    """The oracle spec of one run."""

    KIND: ClassVar[MessageKind] = MessageKind.SPEC

    run: str
    views: tuple[View, ...]
    version: int = SPEC_VERSION
    sphere_radius_m: float | None = None  # render radius; None: half the particle spacing
    regions: tuple[Region, ...] = ()  # regions of interest the views refer to by name
    sent_ns: int = field(default=0, compare=False)

    @property
    def fields(self) -> tuple[str, ...]:
        """Particle fields the sim must send besides positions, in first-use order."""
        return tuple(dict.fromkeys(v.field for v in self.views))

    def wants(self, step: int, time_s: float) -> list[View]:
        return [v for v in self.views if v.wants(step, time_s)]

    def request(self, step: int, time_s: float) -> DataRequest | None:
        """What the simulation must send at sim step `step`, simulated time `time_s` (s):
        None when no view is scheduled; regions None when a scheduled view needs every
        particle."""
        views = self.wants(step, time_s)
        if not views:
            return None
        fields = tuple(dict.fromkeys(v.field for v in views))
        if any(not v.regions for v in views):
            return DataRequest(tuple(v.name for v in views), fields, None)
        by_name = {r.name: r for r in self.regions}
        names = dict.fromkeys(name for v in views for name in v.regions)
        return DataRequest(tuple(v.name for v in views), fields,
                           tuple(by_name[n] for n in names))

    def to_dict(self) -> dict:
        d = {"version": self.version, "run": self.run, "views": [v.to_dict() for v in self.views]}
        if self.sphere_radius_m is not None:
            d["sphere_radius_m"] = self.sphere_radius_m
        if self.regions:
            d["regions"] = [r.to_dict() for r in self.regions]
        return d

    @classmethod
    def from_dict(cls, obj, sent_ns: int = 0) -> Spec:
        s = check.keys(obj, "spec", {"version", "run", "views"}, {"sphere_radius_m", "regions"},
                       error=SpecError)
        version = check.integer(s["version"], "version", error=SpecError)
        if version != SPEC_VERSION:
            raise SpecError(f"version: spec version {version} is not supported "
                            f"(this build reads {SPEC_VERSION})")
        if not isinstance(s["views"], list) or not s["views"]:
            raise SpecError("views: expected a non-empty list")
        views = tuple(View.from_dict(v, f"views[{i}]") for i, v in enumerate(s["views"]))
        names = [v.name for v in views]
        if len(set(names)) != len(names):
            raise SpecError(f"views: view names must be unique, got {names}")
        radius = s.get("sphere_radius_m")
        if radius is not None:
            radius = check.number(radius, "sphere_radius_m", 1e-9, None, SpecError)
        raw_regions = s.get("regions", [])
        if not isinstance(raw_regions, list):
            raise SpecError("regions: expected a list of {name, lo_m, hi_m}")
        regions = tuple(Region.from_dict(r, f"regions[{i}]") for i, r in enumerate(raw_regions))
        region_names = [r.name for r in regions]
        if len(set(region_names)) != len(region_names):
            raise SpecError(f"regions: region names must be unique, got {region_names}")
        for i, v in enumerate(views):
            for j, name in enumerate(v.regions):
                if name not in region_names:
                    raise SpecError(f"views[{i}].regions[{j}]: no region named {name!r} "
                                    f"(regions: {region_names})")
        return cls(run=check.name(s["run"], "run", SpecError), views=views, version=version,
                   sphere_radius_m=radius, regions=regions, sent_ns=sent_ns)

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
        try:
            obj = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise SpecError(f"{path}: not valid JSON ({exc})") from None
        return cls.from_dict(obj)
