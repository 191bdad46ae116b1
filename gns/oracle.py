"""The oracle: a render spec derived from a predicted run (a GNS rollout).

From the trajectory [frames, n, 3] (m) it finds the events (failure onset, fastest motion,
end of runout), splits the run into an initiation window (onset to the fastest motion)
and a runout window (fast phase to rest), and plans three views as the reference paper
chose them: a side view across the flow framing the column during initiation, and a
top and an aerial view framing the deposit during runout. Each view's window is cut into
segments (one before and one after the predicted fast phase, the others splitting it); each
segment gets frames in proportion to how fast the material moves then
(within the frame budget) and a region of interest: the padded extent of the particles
that move in it, so the simulation leaves static material out, and (occlusion_cull) the
simulation sends only what each camera can see. The colormap range is the
predicted displacement magnitude with a margin. Axes: x is the flow direction, z is up.

An ensemble oracle (gns.ensemble: the nominal rollout and perturbed members) plans over
all members at once: each event carries the interval the members' times span (widened by
OracleOptions.interval_widen), the windows are the union of the members' windows and cover
those intervals, the cadence follows the largest speed any member has at each frame, the
regions hold every member's moving particles, the cameras frame every member's extent, and
the spec carries the spread of the final deposit.

A prediction with no flow (no particle travels `standing_travel` particle spacings: the
column stands, settling elastically) is no reason to spend the budget: its spec renders each
view at the run's start and end, sends every particle there (the region is the domain: where
motion would come from is unknown) and leaves the rest of the frame budget unplanned, a
reserve that the closed loop (`minority oracle follow`) spends if the run flows after all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from minority.gns.ensemble import deposit_spread, event_intervals
from minority.gns.events import (
    EVENT_NAMES,
    MOVING_SPEED_FRACTION,
    Events,
    displacement_range,
    event_times,
    extent,
    fast_start_s,
    fast_windows,
    find_events,
    moving_points,
)
from minority.protocol.projection import orthonormal_frame, view_tangent
from minority.protocol.spec import SPEC_VERSION, Camera, Spec

ORACLE_VERSION = "minority-oracle/1"
VIEW_ANGLE_DEG = 30.0
AERIAL_DIRECTION = (-0.55, 0.75, -0.45)  # camera looking back, across and down at the deposit


# (name, phase, view direction, view up): the reference paper's side view of the failing
# column and top and aerial views of the runout
VIEWS = (("side", "initiation", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
         ("top", "runout", (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
         ("aerial", "runout", AERIAL_DIRECTION, (0.0, 0.0, 1.0)))


@dataclass(frozen=True)
class OracleOptions:
    run: str = "run"
    frames: int = 120  # frame budget, all views together
    width: int = 1024  # px
    height: int = 768  # px
    segments: int = 4  # per view window: cadence and ROI change between segments
    margin: float = 0.1  # framing and colormap margin, fraction of the extent / range
    roi_pad_m: float = 0.02  # padding of each region of interest beyond the moving extent, m
    roi_front_pad: float = 0.25  # extra padding ahead of the flow front, fraction of the travel
    roi_slabs: int = 4  # boxes per region of interest, slabs along the flow
    roi_time_margin: float = 0.1  # regions cover their window widened by this share of t
    speed_power: float = 4.0  # frames per segment in proportion to the integral of speed^p
    colormap: str = "Viridis (matplotlib)"
    occlusion_cull: bool = True  # the sim sends only particles a view's camera can see
    # an ensemble's intervals: the members' range [min, max] widened on each side by this
    # fraction of the range plus interval_pad_frames frame intervals (gns.ensemble; 1.0 is
    # what bench/oracle_calibration.py measured to cover the held-out runs)
    interval_widen: float = 1.0
    interval_pad_frames: float = 1.0
    # no flow predicted when the farthest any particle travels is under this many particle
    # spacings: the spec renders each view at the start and the end and keeps the budget
    standing_travel: float = 1.0

    def __post_init__(self) -> None:
        if self.frames < 2 * len(VIEWS):
            raise ValueError(f"a frame budget of {self.frames} is too small: each of the "
                             f"{len(VIEWS)} views needs at least 2 frames (its window's ends)")


def fit_camera(lo: np.ndarray, hi: np.ndarray, direction, view_up, aspect: float,
               view_angle_deg: float = VIEW_ANGLE_DEG) -> Camera:
    """The VTK perspective camera looking along `direction` [3] that frames the box [lo, hi]
    ([3] each, m) in an image of width/height `aspect`: the nearest distance at which every
    corner lies inside the view frustum (protocol.projection.in_view), one of them on its
    edge. Its view up is `view_up` [3] orthogonalized."""
    right, up, d = orthonormal_frame(direction, view_up)
    center = 0.5 * (lo + hi)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - center
    tan = view_tangent(view_angle_deg)
    depth = corners @ d
    need = np.maximum(np.abs(corners @ right) / (tan * aspect), np.abs(corners @ up) / tan) - depth
    distance = float(need.max())
    return Camera(position=tuple((center - distance * d).tolist()),
                  focal_point=tuple(center.tolist()), view_up=tuple(up.tolist()),
                  view_angle_deg=view_angle_deg)


def _segments(t0: float, t1: float, k: int, fast: tuple[float, float] | None = None,
              min_s: float = 0.0) -> list[tuple[float, float]]:
    """k segments of [t0, t1]: one before and one after the fast phase `fast` (when the
    window reaches more than `min_s` beyond it), the rest splitting the fast phase evenly;
    k even splits without a fast phase inside the window."""
    lo, hi = (max(t0, fast[0]), min(t1, fast[1])) if fast else (t0, t0)
    if hi - lo <= min_s:
        edges = np.linspace(t0, t1, k + 1).tolist()
    else:
        before, after = lo - t0 > min_s, t1 - hi > min_s
        inner = np.linspace(lo if before else t0, hi if after else t1,
                            max(k - before - after, 1) + 1).tolist()
        edges = ([t0] if before else []) + inner + ([t1] if after else [])
    return list(zip(edges[:-1], edges[1:], strict=True))


def _allocate(weights: np.ndarray, frames: int) -> np.ndarray:
    """Split `frames` over segments in proportion to `weights`, at least one each."""
    w = np.maximum(np.asarray(weights, float), 1e-12)
    share = np.maximum(1, np.floor(frames * w / w.sum())).astype(int)
    while share.sum() > frames and share.max() > 1:
        share[np.argmax(share)] -= 1
    while share.sum() < frames:
        share[np.argmax(w / share)] += 1
    return share


class Oracle:
    """The analysis of one rollout and the spec it implies."""

    def __init__(self, positions: np.ndarray, frame_interval_s: float, bounds_m: np.ndarray,
                 spacing_m: float, options: OracleOptions | None = None,
                 members: Sequence[np.ndarray] = ()):
        """positions [frames, n, 3] (m): the prediction (an ensemble's nominal member);
        members: the ensemble's other members, each [frames, n, 3] (m) like positions
        (none: a single-rollout oracle, as before ensembles)."""
        self.positions = np.asarray(positions, dtype=np.float64)
        self.dt = float(frame_interval_s)
        self.bounds = np.asarray(bounds_m, dtype=np.float64).reshape(3, 2)
        self.spacing = float(spacing_m)
        self.o = options or OracleOptions()
        self.events: Events = find_events(self.positions, self.dt)
        self.time = np.arange(len(self.positions)) * self.dt
        self.scale = self.events.speed_scale_m_s  # [frames] m/s, at the frames' times
        self.threshold = MOVING_SPEED_FRACTION * self.events.peak_speed_m_s
        self.displacement = displacement_range(self.positions)
        for k, m in enumerate(members):
            if np.shape(m) != self.positions.shape:
                raise ValueError(f"ensemble member {k + 1} is {list(np.shape(m))}, the "
                                 f"prediction {list(self.positions.shape)}: members must have "
                                 "the prediction's frames and particles")
        # the ensemble: this oracle first, then one per member (each its own analysis)
        self.each = [self] + [Oracle(m, frame_interval_s, bounds_m, spacing_m, self.o)
                              for m in members]
        self.intervals = (event_intervals(
            [event_times(o.events, self.dt) for o in self.each], self.o.interval_widen,
            self.o.interval_pad_frames * self.dt, self.events.duration_s)
            if members else {})
        # the largest speed scale any member has at each frame, m/s: where frames go
        self.envelope = np.max([o.scale for o in self.each], axis=0)
        self.travel_m = max(o.displacement[1] for o in self.each)  # the farthest any moves

    # --- windows --------------------------------------------------------------------
    def windows(self) -> dict[str, tuple[float, float]]:
        """Initiation: onset to the fastest motion (the column failing), padded by a frame;
        runout: from the start of the fast phase to rest padded by a frame (within the
        rollout). An
        ensemble's: the union over its members, widened to cover the events' intervals
        (the initiation's from the onset's earliest to the peak's latest, the runout's from
        the runout start's earliest to the runout end's latest)."""
        if len(self.each) == 1:
            return self._own_windows()
        out = {}
        for phase, (first, last) in {"initiation": ("failure_onset", "peak_motion"),
                                     "runout": ("runout_start", "runout_end")}.items():
            w = [o._own_windows()[phase] for o in self.each]
            lo = min(min(a for a, _ in w), self.intervals[first][0] - self.dt)
            hi = max(max(b for _, b in w), self.intervals[last][1] + self.dt)
            out[phase] = (max(0.0, lo), min(hi, self.events.duration_s))
        return out

    def _own_windows(self) -> dict[str, tuple[float, float]]:
        """This trajectory's windows alone (windows() of a single rollout)."""
        e = self.events
        fast_start = fast_start_s(e, self.dt)
        end = max(e.runout_end_s, fast_start + self.dt)
        pad = self.dt
        failing = max(e.peak_s, e.onset_s + self.dt)  # an early kinetic-energy spike aside
        return {"initiation": (max(0.0, e.onset_s - pad), min(failing + pad, e.duration_s)),
                # from the fast phase's first frame: a frame before it is outside the
                # critical window unless the run is early, when it is one of many inside
                "runout": (fast_start, min(end + pad, e.duration_s))}

    def region(self, t0: float, t1: float) -> list[np.ndarray]:
        """[3, 2] boxes (m) holding the particles moving in [t0, t1]: one per slab along the
        flow (x), hugging the moving material so that the static base stays out; padded, the
        front one ahead by a share of the travel, within the domain; the whole domain if
        nothing moves. An ensemble's hold every member's moving particles (each member's
        own moving threshold), ahead of the farthest travel."""
        found = [moving_points(o.positions, self.dt, t0, t1, o.threshold) for o in self.each]
        found = [p for p in found if p is not None]
        if not found:
            return [self.bounds.copy()]
        pts = np.concatenate(found)
        pad = self.o.roi_pad_m + self.spacing
        edges = np.linspace(pts[:, 0].min(), pts[:, 0].max(), self.o.roi_slabs + 1)
        slab = np.clip(np.searchsorted(edges, pts[:, 0], side="right") - 1, 0,
                       self.o.roi_slabs - 1)
        boxes = []
        for j in range(self.o.roi_slabs):
            p = pts[slab == j]
            if len(p):
                boxes.append(np.stack([p.min(axis=0) - pad, p.max(axis=0) + pad], axis=1))
        travel = self.travel_m
        boxes[-1][0, 1] += self.o.roi_front_pad * travel  # x: the flow direction
        boxes[-1][2, 1] += self.o.roi_front_pad * travel * 0.5  # z: heaving ahead of the front
        return [np.clip(b, self.bounds[:, :1], self.bounds[:, 1:]) for b in boxes]

    def fast_phase(self) -> tuple[float, float] | None:
        """The predicted fast phase (speed scale >= half its peak; the longest if several),
        s; an ensemble's spans its members' (earliest start to latest end)."""
        phases = [p for p in (o._own_fast_phase() for o in self.each) if p is not None]
        if not phases:
            return None
        return min(a for a, _ in phases), max(b for _, b in phases)

    def _own_fast_phase(self) -> tuple[float, float] | None:
        fast = fast_windows(self.time, self.scale)
        return max(fast, key=lambda w: w[1] - w[0]) if fast else None

    def framed(self, phase: str) -> np.ndarray:
        """[3, 2] box (m) a view of the phase frames: the column over the initiation; the
        predicted final deposit (the last frame at the end of the runout) for the runout;
        an ensemble's frames every member's."""
        if phase == "initiation":
            t0, t1 = self.windows()["initiation"]
            boxes = [extent(o.positions, self.dt, t0, t1) for o in self.each]
        else:
            boxes = [extent(o.positions, self.dt, o.events.runout_end_s, o.events.runout_end_s)
                     for o in self.each]
        return np.stack([np.min([b[:, 0] for b in boxes], axis=0),
                         np.max([b[:, 1] for b in boxes], axis=0)], axis=1)

    def weight(self, t0: float, t1: float) -> float:
        """How fast the material moves in [t0, t1]: the integral of the speed scale raised to
        `speed_power` (2 would follow the kinetic energy; 4, the default, spends the frames
        more sharply where motion is fastest: on the showcase 111 of 117 frames fall inside
        the predicted fast phase against 105 with 2, each segment keeping at least one). An
        ensemble's follows the largest speed scale of any member at each frame."""
        inside = (self.time >= t0) & (self.time <= t1)
        return float((self.envelope[inside] ** self.o.speed_power).sum() * self.dt) \
            if inside.any() else 0.0

    def standing(self) -> bool:
        """No flow predicted: no member's particles travel standing_travel spacings."""
        return self.travel_m < self.o.standing_travel * self.spacing

    # --- the spec ---------------------------------------------------------------------
    def spec(self, provenance: dict | None = None) -> Spec:
        if self.standing():
            return self._spec(self._standing_views(), [{
                "name": "domain", "lo_m": self.bounds[:, 0].tolist(),
                "hi_m": self.bounds[:, 1].tolist()}], provenance)
        o = self.o
        windows = self.windows()
        regions, schedules, boxes = [], {}, {}
        for phase, (t0, t1) in windows.items():
            # a part outside the fast phase gets its own segment if it is 10 % of the window
            segs = _segments(t0, t1, o.segments, self.fast_phase(),
                             max(self.dt, 0.1 * (t1 - t0)))
            for k, (a, b) in enumerate(segs):
                # the region covers the segment widened by the oracle's timing tolerance: a
                # run that is early or late by that much still has its movers inside
                wa = max(0.0, a - max(o.roi_time_margin * a, self.dt))
                wb = min(self.events.duration_s, b + max(o.roi_time_margin * b, self.dt))
                for j, box in enumerate(self.region(wa, wb)):
                    name = f"{phase}_{k}_{j}"
                    regions.append({"name": name, "lo_m": box[:, 0].tolist(),
                                    "hi_m": box[:, 1].tolist()})
                    boxes.setdefault(f"{phase}_{k}", []).append((name, box))
            schedules[phase] = segs
        per_view = _allocate(np.ones(len(VIEWS)), o.frames)
        out_views = []
        for (name, phase, direction, up), budget in zip(VIEWS, per_view, strict=True):
            # segment k renders f_k + 1 instants, its last one shared with segment k + 1: at
            # most budget - 1 segments (neighbours merged, their regions together)
            groups = np.array_split(np.arange(len(schedules[phase])), budget - 1)
            segs = [(schedules[phase][g[0]][0], schedules[phase][g[-1]][1])
                    for g in groups if len(g)]
            windows_boxes = [[b for k in g for b in boxes[f"{phase}_{k}"]]
                             for g in groups if len(g)]
            share = _allocate([self.weight(a, b) for a, b in segs], budget - 1)
            out_views.append({
                **self._view(name, phase, direction, up),
                "schedule": [{"t_start_s": a, "t_end_s": b, "every_s": (b - a) / int(f),
                              "regions": [n for n, _ in wb]}
                             for (a, b), f, wb in zip(segs, share, windows_boxes, strict=True)]})
        return self._spec(out_views, regions, provenance)

    def _view(self, name: str, phase: str, direction, up) -> dict:
        """A view of the phase (framing, field, colormap), without its schedule."""
        o = self.o
        lo, hi = self.framed(phase).T
        pad = o.margin * (hi - lo).max() * 0.5 + self.spacing
        camera = fit_camera(lo - pad, hi + pad, direction, up, o.width / o.height)
        hi_d = max(self.travel_m, self.spacing)  # a colormap range, even at rest
        return {"name": name, "camera": camera.to_dict(), "width": o.width,
                "height": o.height, "field": "displacement", "colormap": o.colormap,
                "range": [0.0, float(hi_d * (1.0 + o.margin))],
                "occlusion_cull": o.occlusion_cull}

    def _standing_views(self) -> list[dict]:
        """No flow predicted: each view renders the run's start and end, every particle."""
        end = self.events.duration_s
        return [{**self._view(name, phase, direction, up),
                 "schedule": [{"t_start_s": 0.0, "t_end_s": end, "every_s": end,
                               "regions": ["domain"]}]}
                for name, phase, direction, up in VIEWS]

    def _spec(self, views: list[dict], regions: list[dict], provenance: dict | None) -> Spec:
        o = self.o
        events = []
        for name, t in event_times(self.events, self.dt).items():
            event = {"name": name, "time_s": t, "tolerance_s": max(0.1 * t, self.dt)}
            if name in self.intervals:
                event["earliest_s"], event["latest_s"] = self.intervals[name]
            events.append(event)
        doc = {"version": SPEC_VERSION, "run": o.run, "views": views, "regions": regions,
               "events": events, "budget": {"frames": o.frames, "bytes": None},
               "provenance": {"oracle": ORACLE_VERSION, **(provenance or {}),
                              "predicted": self.summary()}}
        if len(self.each) > 1:
            doc["deposit"] = deposit_spread([o.positions for o in self.each],
                                            o.interval_widen)
        return Spec.from_dict(doc)

    def summary(self) -> dict:
        """What the spec's choices rest on (JSON-ready), for the score and for a person."""
        e = self.events
        return {"onset_s": e.onset_s, "peak_s": e.peak_s, "runout_end_s": e.runout_end_s,
                "duration_s": e.duration_s, "peak_speed_m_s": e.peak_speed_m_s,
                "moving_speed_m_s": self.threshold,
                "displacement_range_m": list(self.displacement),
                "fast_windows_s": [list(w) for w in fast_windows(self.time, self.scale)],
                "windows_s": {k: list(v) for k, v in self.windows().items()},
                "particles": int(self.positions.shape[1]), "frame_interval_s": self.dt,
                **({"standing": True} if self.standing() else {}),
                **({"ensemble": self.ensemble_summary()} if len(self.each) > 1 else {})}

    def ensemble_summary(self) -> dict:
        """Each member's event times (s) and the intervals the spec states (JSON-ready)."""
        times = [event_times(o.events, self.dt) for o in self.each]
        return {"members": len(self.each),
                "interval_widen": self.o.interval_widen,
                "interval_pad_s": self.o.interval_pad_frames * self.dt,
                "event_times_s": {n: [t[n] for t in times] for n in EVENT_NAMES},
                "intervals_s": {n: list(v) for n, v in self.intervals.items()},
                "windows_s": {k: list(v) for k, v in self.windows().items()}}
