"""One view of the oracle spec: camera, image, colors, data needs and schedule.

A view's schedule is a list of windows of simulated time, each with its own cadence
(every n-th sim step, or every `every_s` seconds of simulated time) and its own regions of
interest. Errors start with the path of the bad field, e.g. ``views[1].schedule[0].every_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from minority.protocol import check
from minority.protocol.errors import SpecError

MAX_IMAGE_SIDE = 8192  # px; 3840x2160 is the largest size the server is tested with
DEFAULT_EVERY_STEPS = 20
COLOR_SPACES = ("RGB", "HSV", "Lab", "Lab/CIEDE2000", "Diverging", "Step")


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

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """The camera's orthonormal frame in world coordinates, VTK's convention: position
        [3] (m), right [3] (image +x), up [3] (the view up orthogonalized, image +y), forward
        [3] (toward the focal point), and the distance to the focal point (m)."""
        position = np.asarray(self.position, dtype=np.float64)
        forward = np.asarray(self.focal_point, dtype=np.float64) - position
        distance = float(np.linalg.norm(forward))
        forward /= distance
        right = np.cross(forward, np.asarray(self.view_up, dtype=np.float64))
        right /= np.linalg.norm(right)
        return position, right, np.cross(right, forward), forward, distance

    def to_dict(self) -> dict:
        return {"position": list(self.position), "focal_point": list(self.focal_point),
                "view_up": list(self.view_up), "view_angle_deg": self.view_angle_deg,
                "parallel_projection": self.parallel_projection,
                "parallel_scale_m": self.parallel_scale_m}


@dataclass(frozen=True)
class InlineColormap:
    """A ParaView preset written into the spec: RGBPoints x0, r0, g0, b0, x1, ... (x in any
    units: the view's range rescales it; r, g, b in [0, 1])."""

    name: str
    color_space: str
    rgb_points: tuple[float, ...]
    nan_color: tuple[float, float, float] = (1.0, 1.0, 0.0)

    @classmethod
    def from_dict(cls, obj, where: str) -> InlineColormap:
        c = check.keys(obj, where, {"Name", "RGBPoints"}, {"ColorSpace", "NanColor"},
                       error=SpecError)
        space = c.get("ColorSpace", "RGB")
        if space not in COLOR_SPACES:
            raise SpecError(f"{where}.ColorSpace: {space!r:.40} is not one of {list(COLOR_SPACES)}")
        pts = c["RGBPoints"]
        if not isinstance(pts, list) or len(pts) < 8 or len(pts) % 4:
            raise SpecError(f"{where}.RGBPoints: expected x, r, g, b quadruples (at least two)")
        values = tuple(check.number(v, f"{where}.RGBPoints[{i}]", error=SpecError)
                       for i, v in enumerate(pts))
        xs = values[0::4]
        if any(b < a for a, b in zip(xs[:-1], xs[1:], strict=True)) or xs[-1] <= xs[0]:
            raise SpecError(f"{where}.RGBPoints: x values must increase")
        if any(not 0.0 <= v <= 1.0 for i, v in enumerate(values) if i % 4):
            raise SpecError(f"{where}.RGBPoints: r, g, b must lie in [0, 1]")
        nan = check.vector(c.get("NanColor", list(cls.nan_color)), f"{where}.NanColor",
                           error=SpecError)
        return cls(check.text(c["Name"], f"{where}.Name", 128, SpecError), space, values, nan)

    def to_dict(self) -> dict:
        """The ParaView preset object (what ParaView's preset JSON holds)."""
        return {"Name": self.name, "ColorSpace": self.color_space,
                "RGBPoints": list(self.rgb_points), "NanColor": list(self.nan_color)}


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
    def from_dict(cls, obj, where: str) -> Window:
        w = check.keys(obj, where, set(), {"t_start_s", "t_end_s", "every_steps", "every_s",
                                           "regions"}, error=SpecError)
        t0 = check.number(w.get("t_start_s", 0.0), f"{where}.t_start_s", 0.0, None, SpecError)
        t1 = w.get("t_end_s")
        t1 = math.inf if t1 is None else check.number(t1, f"{where}.t_end_s", t0, None, SpecError)
        every_s = w.get("every_s")
        if every_s is not None:
            every_s = check.number(every_s, f"{where}.every_s", 1e-12, None, SpecError)
            if "every_steps" in w:
                raise SpecError(f"{where}: give every_steps or every_s, not both")
        regions = w.get("regions", [])
        if not isinstance(regions, list):
            raise SpecError(f"{where}.regions: expected a list of region names")
        return cls(t0, t1, check.integer(w.get("every_steps", DEFAULT_EVERY_STEPS),
                                         f"{where}.every_steps", 1, None, SpecError),
                   every_s, tuple(check.name(r, f"{where}.regions[{i}]", SpecError)
                                  for i, r in enumerate(regions)))

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


_FLAT = ("t_start_s", "t_end_s", "every_steps", "every_s", "regions")  # version 1 shorthand


@dataclass(frozen=True)
class View:
    """One rendered view: camera, image, colors, data needs, and when to render it."""

    name: str
    camera: Camera
    width: int = 1024  # px
    height: int = 768  # px
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # RGB in [0, 1]
    field: str = "displacement"  # colored by magnitude if vector-valued
    colormap: str | InlineColormap = "Viridis (matplotlib)"  # ParaView preset name or inline
    range: tuple[float, float] = (0.0, 1.0)  # colormap range, units of the field
    decimate: int = 1  # render every n-th particle (by particle id); 1 = all
    schedule: tuple[Window, ...] = (Window(),)
    # send only particles this camera can see (hidden ones and those outside the image are
    # left out by the sim); the image is unchanged without shadows, which hidden ones cast
    occlusion_cull: bool = False

    @classmethod
    def from_dict(cls, obj, where: str) -> View:
        v = check.keys(obj, where, {"name", "camera"},
                       {"width", "height", "background", "field", "colormap", "range", "decimate",
                        "occlusion_cull", "schedule", *_FLAT}, error=SpecError)
        rng = check.vector(v.get("range", cls.range), f"{where}.range", 2, SpecError)
        if not rng[0] < rng[1]:
            raise SpecError(f"{where}.range: lower bound {rng[0]} must be below upper {rng[1]}")
        background = check.vector(v.get("background", cls.background), f"{where}.background",
                                  3, SpecError)
        if not all(0.0 <= b <= 1.0 for b in background):
            raise SpecError(f"{where}.background: RGB components must lie in [0, 1]")
        cmap = v.get("colormap", cls.colormap)
        cmap = (InlineColormap.from_dict(cmap, f"{where}.colormap") if isinstance(cmap, dict)
                else check.text(cmap, f"{where}.colormap", 128, SpecError))
        flat = [k for k in _FLAT if k in v]
        if "schedule" in v:
            if flat:
                raise SpecError(f"{where}: give a schedule or the single-window keys "
                                f"({', '.join(flat)}), not both")
            if not isinstance(v["schedule"], list) or not v["schedule"]:
                raise SpecError(f"{where}.schedule: expected a non-empty list of windows")
            schedule = tuple(Window.from_dict(w, f"{where}.schedule[{i}]")
                             for i, w in enumerate(v["schedule"]))
        else:
            schedule = (Window.from_dict({k: v[k] for k in flat}, where),)
        return cls(name=check.name(v["name"], f"{where}.name", SpecError),
                   camera=Camera.from_dict(v["camera"], f"{where}.camera"),
                   width=check.integer(v.get("width", cls.width), f"{where}.width", 1,
                                       MAX_IMAGE_SIDE, SpecError),
                   height=check.integer(v.get("height", cls.height), f"{where}.height", 1,
                                        MAX_IMAGE_SIDE, SpecError),
                   background=background,
                   field=check.name(v.get("field", cls.field), f"{where}.field", SpecError),
                   colormap=cmap, range=rng,
                   decimate=check.integer(v.get("decimate", 1), f"{where}.decimate", 1, None,
                                          SpecError),
                   schedule=schedule,
                   occlusion_cull=check.boolean(v.get("occlusion_cull", False),
                                                f"{where}.occlusion_cull", SpecError))

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
                "schedule": [w.to_dict() for w in self.schedule]}
