"""One view of the oracle spec: camera, image, colors, data needs and schedule.

A view's schedule is a list of windows of simulated time, each with its own cadence
(every n-th sim step, or every `every_s` seconds of simulated time) and its own regions of
interest. The JSON form is defined once, by the msgspec types here (Camera, InlineColormap,
WindowDocument, ViewDocument): they check what is read and give the JSON Schema stored in logs.
Errors start with the path of the bad field, e.g. ``views[1].schedule[0].every_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Annotated, Literal

import msgspec

from minority.protocol import check
from minority.protocol.check import RGB, Finite, Name, NonNegative, Vec3
from minority.protocol.errors import SpecError

MAX_IMAGE_SIDE = 8192  # px; 3840x2160 is the largest size the server is tested with
DEFAULT_EVERY_STEPS = 20
COLOR_SPACES = ("RGB", "HSV", "Lab", "Lab/CIEDE2000", "Diverging", "Step")
DEFAULT_COLOR_SPACE = "RGB"  # ParaView's, when a preset names none
# The ParaView presets the renderer has built in (render_server.colormap); any matplotlib
# colormap name ("viridis", "coolwarm", ...) is accepted too.
PARAVIEW_PRESETS = ("Cool to Warm", "Grayscale", "Viridis (matplotlib)", "Plasma (matplotlib)",
                    "Inferno (matplotlib)", "Magma (matplotlib)", "Turbo")
DEFAULT_COLORMAP = "Viridis (matplotlib)"

Side = Annotated[int, msgspec.Meta(ge=1, le=MAX_IMAGE_SIDE)]
Stride = Annotated[int, msgspec.Meta(ge=1)]
ColormapName = Annotated[str, msgspec.Meta(min_length=1, max_length=128)]


@cache
def matplotlib_colormaps() -> frozenset[str]:
    from matplotlib import colormaps  # only when a name is not a ParaView preset

    return frozenset(colormaps)


def check_colormap_name(name: str, where: str) -> str:
    """`name` when it is one of PARAVIEW_PRESETS or a matplotlib colormap; SpecError otherwise."""
    if name in PARAVIEW_PRESETS or name in matplotlib_colormaps():
        return name
    raise SpecError(f"{where}: {name!r:.60} is neither a built-in ParaView preset "
                    f"({', '.join(PARAVIEW_PRESETS)}) nor a matplotlib colormap name "
                    "(e.g. viridis, coolwarm); or give the preset inline {Name, RGBPoints, ...}")


class Camera(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """VTK camera model: positions in m, view angle in degrees (vertical), or parallel
    projection with parallel_scale = half the view height in m."""

    position: Vec3
    focal_point: Vec3
    view_up: Vec3 = (0.0, 0.0, 1.0)
    view_angle_deg: Annotated[float, msgspec.Meta(ge=0.1, le=179.0)] = 30.0
    parallel_projection: bool = False
    parallel_scale_m: Annotated[float, msgspec.Meta(ge=1e-9, le=check.FLOAT_MAX)] = 1.0

    @classmethod
    def from_dict(cls, obj, where: str) -> Camera:
        return check.convert(obj, cls, where, SpecError).checked(where)

    def checked(self, where: str) -> Camera:
        """self, when its frame is defined: SpecError naming `where` otherwise."""
        direction = [f - p for f, p in zip(self.focal_point, self.position, strict=True)]
        if math.hypot(*direction) == 0.0:
            raise SpecError(f"{where}: position and focal_point coincide")
        up = self.view_up
        cross = (direction[1] * up[2] - direction[2] * up[1],
                 direction[2] * up[0] - direction[0] * up[2],
                 direction[0] * up[1] - direction[1] * up[0])
        if math.hypot(*cross) <= 1e-12 * math.hypot(*direction) * max(math.hypot(*up), 1e-300):
            raise SpecError(f"{where}.view_up: parallel to the view direction (or zero)")
        return self

    def to_dict(self) -> dict:
        return check.to_json(self)


class InlineColormap(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A ParaView preset (the object ParaView's preset JSON holds): RGBPoints x0, r0, g0, b0,
    x1, ... (x in any units: the view's range rescales it; r, g, b in [0, 1])."""

    name: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] = msgspec.field(name="Name")
    rgb_points: Annotated[tuple[Finite, ...], msgspec.Meta(min_length=8)] = msgspec.field(
        name="RGBPoints")
    color_space: Literal[COLOR_SPACES] = msgspec.field(default=DEFAULT_COLOR_SPACE,
                                                       name="ColorSpace")
    nan_color: RGB = msgspec.field(default=(1.0, 1.0, 0.0), name="NanColor")

    @classmethod
    def from_dict(cls, obj, where: str) -> InlineColormap:
        """A spec's inline colormap: exactly these keys, Name and RGBPoints required."""
        return check.convert(obj, cls, where, SpecError).checked(where)

    @classmethod
    def from_preset(cls, obj, where: str, name: str = "Preset") -> InlineColormap:
        """One object of a ParaView preset file: keys other than these (Creator, Points, ...)
        are dropped, Name defaults to `name`."""
        if not isinstance(obj, dict):
            raise SpecError(f"{where}: expected a preset object, got {type(obj).__name__}")
        kept = {k: obj[k] for k in ("Name", "RGBPoints", "ColorSpace", "NanColor") if k in obj}
        return cls.from_dict({"Name": name, **kept}, where)

    def checked(self, where: str) -> InlineColormap:
        pts = self.rgb_points
        if len(pts) % 4:
            raise SpecError(f"{where}.RGBPoints: expected x, r, g, b quadruples (4k numbers, "
                            f"k >= 2), got {len(pts)}")
        xs = pts[0::4]
        for k in range(1, len(xs)):
            if xs[k] < xs[k - 1]:
                raise SpecError(f"{where}.RGBPoints[{4 * k}]: x {xs[k]} is below the previous "
                                f"x {xs[k - 1]} (x values must increase)")
        if not xs[-1] > xs[0]:
            raise SpecError(f"{where}.RGBPoints: x range [{xs[0]}, {xs[-1]}] is empty "
                            "(x values must increase)")
        for i, v in enumerate(pts):
            if i % 4 and not 0.0 <= v <= 1.0:
                raise SpecError(f"{where}.RGBPoints[{i}]: color component {v} is outside [0, 1]")
        return self

    def to_dict(self) -> dict:
        """The ParaView preset object."""
        return check.to_json(self)


# every_s instants: a time within this fraction of every_s before an instant has reached it
# (t_end_s - t_start_s is often a whole number of every_s only to rounding)
INSTANT_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Window:
    """A window of simulated time [t_start_s, t_end_s] (s) with its cadence and regions.

    Cadence: every `every_steps`-th sim step, or (when `every_s` is set) the first sim step
    at or after each instant t_start_s + k * every_s (this needs the previous step's time)."""

    t_start_s: float = 0.0
    t_end_s: float = math.inf
    every_steps: int = DEFAULT_EVERY_STEPS
    every_s: float | None = None
    regions: tuple[str, ...] = ()  # names of the spec's regions; () = every particle

    @classmethod
    def from_document(cls, w: WindowDocument, where: str) -> Window:
        if w.t_end_s is not None and w.t_end_s < w.t_start_s:
            raise SpecError(f"{where}.t_end_s: {w.t_end_s} is before t_start_s {w.t_start_s}")
        if w.every_s is not None and w.every_steps is not msgspec.UNSET:
            raise SpecError(f"{where}: give every_steps or every_s, not both")
        return cls(w.t_start_s, math.inf if w.t_end_s is None else w.t_end_s,
                   DEFAULT_EVERY_STEPS if w.every_steps is msgspec.UNSET else w.every_steps,
                   w.every_s, w.regions)

    def contains(self, time_s: float) -> bool:
        return self.t_start_s <= time_s <= self.t_end_s

    def instant(self, time_s: float) -> int:
        """With every_s: the index k of the last instant t_start_s + k * every_s at or before
        min(time_s, t_end_s) (-1 before the window starts)."""
        if time_s < self.t_start_s:
            return -1
        return math.floor((min(time_s, self.t_end_s) - self.t_start_s) / self.every_s
                          + INSTANT_TOLERANCE)

    def wants(self, step: int, time_s: float, prev_time_s: float | None = None) -> bool:
        """Whether sim step `step`, which went from `prev_time_s` to `time_s` (s), is due:
        with every_s, when an instant t_start_s + k * every_s of the window lies in
        (prev_time_s, time_s] (prev_time_s None: when time_s is one), so each instant falls
        to exactly one step, the window's last one too (its step may end after t_end_s)."""
        if self.every_s is None:
            return self.contains(time_s) and step % self.every_steps == 0
        if prev_time_s is None:
            now = (time_s - self.t_start_s) / self.every_s
            return self.contains(time_s) and now == math.floor(now)
        if time_s < self.t_start_s or prev_time_s >= self.t_end_s:
            return False
        return self.instant(time_s) > self.instant(prev_time_s)

    def planned_frames(self, duration_s: float, dt_s: float) -> int:
        """About how many steps of a run of `duration_s` with steps of `dt_s` (s) are due."""
        t1 = min(self.t_end_s, duration_s)
        if t1 < self.t_start_s:
            return 0
        if self.every_s is not None:
            return self.instant(t1) + 1
        return int((t1 - self.t_start_s) / dt_s / self.every_steps) + 1

    def to_dict(self) -> dict:
        d = {"t_start_s": self.t_start_s,
             "t_end_s": None if math.isinf(self.t_end_s) else self.t_end_s}
        if self.every_s is None:
            d["every_steps"] = self.every_steps
        else:
            d["every_s"] = self.every_s
        if self.regions:
            d["regions"] = list(self.regions)
        return d


class WindowDocument(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A Window as JSON: t_end_s null = open-ended; every_steps or every_s, not both."""

    t_start_s: NonNegative = 0.0
    t_end_s: NonNegative | None = None
    every_steps: Stride | msgspec.UnsetType = msgspec.UNSET
    every_s: Annotated[float, msgspec.Meta(ge=1e-12, le=check.FLOAT_MAX)] | None = None
    regions: tuple[Name, ...] = ()


class Annotations(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """What the render server draws over a view's particles: a colorbar (the field's name,
    unit and the view's range in its colormap), the simulated time and step, the domain's
    floor and channel walls as light lines behind the particles (`context`), and the
    domain's bounding box. In a spec: this object, or true (these defaults) or false (none)."""

    colorbar: bool = True
    time: bool = True
    context: bool = True
    bbox: bool = False

    def to_json(self) -> bool | dict:
        """The spec's form: true for the defaults, false for none, else the object."""
        if self == Annotations():
            return True
        return False if self == NO_ANNOTATIONS else check.to_json(self)


NO_ANNOTATIONS = Annotations(colorbar=False, time=False, context=False, bbox=False)


class ViewDocument(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A View as JSON (defaults as View's)."""

    name: Name
    camera: Camera
    width: Side = 1024
    height: Side = 768
    background: RGB = (1.0, 1.0, 1.0)
    field: Name = "displacement"
    colormap: ColormapName | InlineColormap = DEFAULT_COLORMAP
    range: tuple[Finite, Finite] = (0.0, 1.0)
    decimate: Stride = 1
    occlusion_cull: bool = False
    schedule: Annotated[tuple[WindowDocument, ...], msgspec.Meta(min_length=1)] = (
        WindowDocument(),)
    annotations: Annotations | bool = Annotations()


ONE_WINDOW_KEYS = ("t_start_s", "t_end_s", "every_steps", "every_s", "regions")


def one_window_shorthand(view, where: str):
    """The JSON view object `view` (at `where`) as version 2 writes it: when it gives its one
    window's keys (ONE_WINDOW_KEYS) on itself, as version 1 did, a copy with a schedule of
    that window; anything else as it is."""
    flat = [k for k in ONE_WINDOW_KEYS if isinstance(view, dict) and k in view]
    if not flat:
        return view
    if "schedule" in view:
        raise SpecError(f"{where}: give a schedule or the single-window keys "
                        f"({', '.join(flat)}), not both")
    return {**{k: v for k, v in view.items() if k not in flat},
            "schedule": [{k: view[k] for k in flat}]}


def shorthand_paths(exc: SpecError, views: list[str]) -> SpecError:
    """`exc` with the paths into the one window of the shorthand views at `views` (e.g.
    "views[2].schedule[0].every_s") named where the file has them ("views[2].every_s")."""
    text = str(exc)
    for where in views:
        text = text.replace(f"{where}.schedule[0]", where, 1)
    return SpecError(text)


@dataclass(frozen=True)
class View:
    """One rendered view: camera, image, colors, data needs, and when to render it."""

    name: str
    camera: Camera
    width: int = 1024  # px
    height: int = 768  # px
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # RGB in [0, 1]
    field: str = "displacement"  # colored by magnitude if vector-valued
    colormap: str | InlineColormap = DEFAULT_COLORMAP  # ParaView or matplotlib name, or inline
    range: tuple[float, float] = (0.0, 1.0)  # colormap range, units of the field
    decimate: int = 1  # render every n-th particle (by particle id); 1 = all
    schedule: tuple[Window, ...] = (Window(),)
    # send only particles this camera can see (hidden ones and those outside the image are
    # left out by the sim); the image is unchanged without shadows, which hidden ones cast
    occlusion_cull: bool = False
    annotations: Annotations = Annotations()  # drawn over the image (NO_ANNOTATIONS: none)

    @classmethod
    def from_dict(cls, obj, where: str) -> View:
        v2 = one_window_shorthand(obj, where)
        try:
            return cls.from_document(check.convert(v2, ViewDocument, where, SpecError), where)
        except SpecError as exc:
            raise shorthand_paths(exc, [where] if v2 is not obj else []) from None

    @classmethod
    def from_document(cls, v: ViewDocument, where: str) -> View:
        """The View of a checked document; SpecError for what its types cannot say."""
        if not v.range[0] < v.range[1]:
            raise SpecError(f"{where}.range: lower bound {v.range[0]} must be below upper "
                            f"{v.range[1]}")
        cmap = (check_colormap_name(v.colormap, f"{where}.colormap") if isinstance(v.colormap, str)
                else v.colormap.checked(f"{where}.colormap"))
        notes = v.annotations
        if isinstance(notes, bool):
            notes = Annotations() if notes else NO_ANNOTATIONS
        return cls(v.name, v.camera.checked(f"{where}.camera"), v.width, v.height, v.background,
                   v.field, cmap, v.range, v.decimate,
                   tuple(Window.from_document(w, f"{where}.schedule[{i}]")
                         for i, w in enumerate(v.schedule)), v.occlusion_cull, notes)

    @property
    def t_start_s(self) -> float:
        return min(w.t_start_s for w in self.schedule)

    @property
    def t_end_s(self) -> float:
        return max(w.t_end_s for w in self.schedule)

    @property
    def regions(self) -> tuple[str, ...]:
        """Every region name any window of the view uses."""
        return tuple(dict.fromkeys(r for w in self.schedule for r in w.regions))

    def window(self, step: int, time_s: float, prev_time_s: float | None = None) -> Window | None:
        """The first window that renders this step, or None."""
        return next((w for w in self.schedule if w.wants(step, time_s, prev_time_s)), None)

    def wants(self, step: int, time_s: float, prev_time_s: float | None = None) -> bool:
        """Whether this view renders sim step `step` at simulated time `time_s` (s), reached
        from `prev_time_s` (s; needed by windows with an every_s cadence)."""
        return self.window(step, time_s, prev_time_s) is not None

    def planned_frames(self, duration_s: float, dt_s: float) -> int:
        return sum(w.planned_frames(duration_s, dt_s) for w in self.schedule)

    def to_dict(self) -> dict:
        return {"name": self.name, "camera": self.camera.to_dict(), "width": self.width,
                "height": self.height, "background": list(self.background), "field": self.field,
                "colormap": (self.colormap if isinstance(self.colormap, str)
                             else self.colormap.to_dict()),
                "range": list(self.range), "decimate": self.decimate,
                **({"occlusion_cull": True} if self.occlusion_cull else {}),
                "schedule": [w.to_dict() for w in self.schedule],
                # the default is left out: a spec without the key encodes as before it existed
                **({} if self.annotations == Annotations()
                   else {"annotations": self.annotations.to_json()})}
