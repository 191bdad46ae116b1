"""`minority oracle follow RUN`: the closed-loop oracle. It reads a run's live Stats, and when
the run leaves what its spec predicted it re-forecasts from the run's own state and puts an
updated spec on minority/{run}/spec, which the server and the ranks adopt without stopping.

Departures (`Detector`, on the ranks' Stats summed per step, `LiveFlow`):
- an event early: observed before its predicted interval (the ensemble's [earliest_s,
  latest_s], else time_s +- tolerance_s), by more than one stats interval;
- an event late: the interval has passed and the event has not happened (the flow still
  moving at the predicted rest is the runout end late);
- motion outside the regions: under 99 % of the moving particles inside the open regions
  at two stats steps in a row.
Events are read online by the rules of gns.events, against the predicted peak speed until
the run's own peak is known.

An update is two spec puts, each logged with its reason and cost (provenance: reason, kind,
update, from_t_s, forecast_s, ...):
1. "shift": at once, the spec's timeline moved by the departure (events already seen put at
   their observed times) and `snapshots`: C + 1 simulated times one model frame apart, at
   which every rank sends every particle through the ordinary chunk path (protocol.spec);
2. "forecast": once the snapshots are in, their particles grouped by the cube of the
   model's spacing their initial position x - displacement lies in (as the training data
   were coarse-grained: gns.dataset.coarse_grain), the GNS rolls forward from them until
   the flow rests (`reforecast`), and the oracle plans the rest of the run on that rollout
   (gns.oracle), with the events of the run's observed past joined to the forecast's.
"""

from __future__ import annotations

import json
import queue
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from minority.gns.events import (
    EVENT_NAMES,
    FAST_FRACTION,
    events_from_series,
    fast_windows,
    speeds,
)
from minority.gns.oracle import VIEWS, Oracle, OracleOptions
from minority.protocol.flow import (
    MOVING_SPEED_FRACTION,
    SPEED_QUANTILE,
    histogram_quantile,
    moving_count,
)
from minority.protocol.spec import Spec

REGIONS_TARGET = 0.99  # share of the moving particles the regions must hold
PEAK_FALL = 0.9  # the kinetic-energy peak is past once it falls below this share of its max
REST_FRACTION = 0.01  # gns.events: rest is the kinetic energy below 1 % of its peak
RESERVE_SHARE = 0.25  # of the frames left, kept for later updates while re-forecasts remain
PLAN_WALL_S = 1.0  # first guess of the planning's wall time after the rollout, s
RATE_WINDOW_S = 5.0  # the run's progress rate is measured over this much wall time, s
WIDEN = 0.25  # a regions departure grows the regions in use by this share of their size
CALIBRATION = (0.5, 2.0)  # bounds of the run / forecast speed ratio at the join
QUEUE_MESSAGES = 65536  # messages queued for the follower's thread at most


# --- the run as its Stats tell it -------------------------------------------------------
class LiveFlow:
    """The ranks' Stats summed per step, in time order: a step counts once `ranks` ranks
    sent it (ranks 0: the most seen at any step, once a later step arrived)."""

    def __init__(self, ranks: int = 0):
        self.ranks = ranks
        self._pending: dict[int, list] = defaultdict(list)
        self.time_s: list[float] = []
        self.hist: list[np.ndarray] = []  # [bins] every particle's speeds
        self.hist_in: list[np.ndarray] = []  # [bins] those inside the open regions
        self.ke: list[float] = []  # mean |v|^2, m^2/s^2
        self.windows_open: list[bool] = []
        self.wall_s: list[float] = []  # monotonic wall time each step arrived complete, s
        self.count = 0
        self._seen = 0

    def add(self, stats, wall_s: float | None = None) -> int:
        """Take one rank's Stats (wall_s: when it arrived, monotonic s; default now);
        returns how many steps became complete."""
        self._wall = time.monotonic() if wall_s is None else wall_s
        self._pending[stats.step].append(stats)
        self._seen = max(self._seen, len({s.rank for s in self._pending[stats.step]}))
        need = self.ranks or self._seen
        done = 0
        for step in sorted(self._pending):
            rows = self._pending[step]
            full = len({s.rank for s in rows}) >= need
            if not full and (self.ranks or step >= max(self._pending)):
                break  # wait for the rest of this step
            del self._pending[step]
            if full and (not self.time_s or rows[0].time_s > self.time_s[-1]):
                self._append(rows)
                done += 1
        return done

    def _append(self, rows: list) -> None:
        hin = np.sum([s.hist_in_regions for s in rows], axis=0)
        hall = hin + np.sum([s.hist_elsewhere for s in rows], axis=0)
        count = sum(s.count for s in rows)
        self.time_s.append(rows[0].time_s)
        self.hist.append(hall)
        self.hist_in.append(hin)
        self.ke.append(sum(s.speed_sq_sum_m2_s2 for s in rows) / max(count, 1))
        self.windows_open.append(rows[0].windows_open)
        self.wall_s.append(self._wall)
        self.count = max(self.count, count)

    def rate(self) -> float | None:
        """The run's progress, s of simulated time per s of wall time, over the steps that
        arrived in the last RATE_WINDOW_S of wall time; None before two steps of it."""
        if len(self.wall_s) < 2:
            return None
        w = np.array(self.wall_s)
        k = max(0, min(int(np.searchsorted(w, w[-1] - RATE_WINDOW_S)), len(w) - 2))
        span = w[-1] - w[k]
        return float((self.time_s[-1] - self.time_s[k]) / span) if span > 0 else None

    @property
    def now_s(self) -> float:
        return self.time_s[-1] if self.time_s else 0.0

    def scale(self) -> np.ndarray:
        """[k] speed scale (m/s) of each complete step."""
        return histogram_quantile(np.array(self.hist), SPEED_QUANTILE) if self.hist else np.zeros(0)


def observed_events(t: np.ndarray, scale: np.ndarray, ke: np.ndarray,
                    ref_peak_m_s: float) -> dict[str, float]:
    """The events the series [k] (times s, speed scale m/s, mean |v|^2) show so far, s, by
    gns.events' rules: the onset against the larger of ref_peak_m_s (the prediction's) and
    the peak so far; the peak once the kinetic energy fell below PEAK_FALL of it; the runout
    start (the first fast window, as minority score reads it) once the peak is known; rest
    below REST_FRACTION of the peak."""
    out: dict[str, float] = {}
    if not len(t):
        return out
    peak_ref = max(ref_peak_m_s, float(scale.max()))
    above = np.flatnonzero(scale >= 0.05 * peak_ref)
    if not len(above):
        return out
    onset = int(above[0])
    out["failure_onset"] = float(t[onset])
    peak = onset + int(np.argmax(ke[onset:]))
    if ke[-1] >= PEAK_FALL * ke[peak] or ke[peak] <= 0:
        return out
    out["peak_motion"] = float(t[peak])
    fast = fast_windows(t, scale)
    out["runout_start"] = float(fast[0][0]) if fast else float(t[peak])
    rest = np.flatnonzero(ke[peak:] < REST_FRACTION * ke[peak])
    if len(rest):
        out["runout_end"] = float(t[peak + rest[0]])
    return out


@dataclass(frozen=True)
class Departure:
    kind: str  # "early", "late" or "regions"
    event: str | None  # the event, for early and late
    at_s: float  # the run's time when it was seen, s
    shift_s: float  # how far the predicted timeline should move, s
    reason: str


class Detector:
    """When the run leaves its spec's predictions (see the module docstring). Each (kind,
    event) is acted on once; motion outside the regions at most twice; regions are judged
    only on Stats after `armed_s` (the ranks measured them with an older spec before)."""

    def __init__(self, interval_s: float = 0.005):
        self.interval_s = interval_s
        self.acted: set[tuple[str, str | None]] = set()
        self.armed_s = -1.0

    def check(self, spec: Spec, flow: LiveFlow) -> Departure | None:
        if not flow.time_s:
            return None
        t, scale, ke = np.array(flow.time_s), flow.scale(), np.array(flow.ke)
        predicted = spec.provenance.get("predicted", {})
        seen = observed_events(t, scale, ke, float(predicted.get("peak_speed_m_s", 0.0)))
        now, slack = float(t[-1]), self.interval_s
        for e in spec.events:
            if e.name not in EVENT_NAMES:
                continue
            lo, hi = e.interval_s or (e.time_s - e.tolerance_s, e.time_s + e.tolerance_s)
            got = seen.get(e.name)
            if got is not None and got < lo - slack and ("early", e.name) not in self.acted:
                self.acted.add(("early", e.name))
                return Departure("early", e.name, now, got - e.time_s,
                                 f"{e.name} at {got:.3f} s, before the predicted "
                                 f"{lo:.3f}-{hi:.3f} s")
            # late: not for the runout start (read only once the peak is known; a late
            # peak says it), nor for a peak while the kinetic energy no longer grows
            rising = len(ke) < 3 or int(np.argmax(ke)) >= len(ke) - 2
            if (got is None and now > hi + slack and ("late", e.name) not in self.acted
                    and e.name != "runout_start" and (e.name != "peak_motion" or rising)):
                self.acted.add(("late", e.name))
                what = ("the flow still moving at the predicted rest" if e.name == "runout_end"
                        else f"no {e.name} yet")
                return Departure("late", e.name, now, now + slack - e.time_s,
                                 f"{what}: {now:.3f} s, the prediction {lo:.3f}-{hi:.3f} s")
        return self._regions(flow, scale, seen, predicted)

    def _regions(self, flow: LiveFlow, scale: np.ndarray, seen: dict,
                 predicted: dict) -> Departure | None:
        if sum(k == "regions" for k, _ in self.acted) >= 2 or len(flow.time_s) < 2:
            return None
        peak = max(float(predicted.get("peak_speed_m_s", 0.0)), float(scale.max()))
        threshold = MOVING_SPEED_FRACTION * peak
        low = []
        for k in (-2, -1):
            if flow.time_s[k] <= self.armed_s or not flow.windows_open[k]:
                return None
            every = int(moving_count(flow.hist[k][None], threshold)[0])
            inside = int(moving_count(flow.hist_in[k][None], threshold)[0])
            if every < max(10, 0.001 * flow.count) or inside >= REGIONS_TARGET * every:
                return None
            low.append(inside / every)
        self.acted.add(("regions", f"{len(self.acted)}"))
        return Departure("regions", None, flow.now_s, 0.0,
                         f"motion outside the regions: {100 * low[-1]:.1f} % of the moving "
                         f"particles inside at {flow.now_s:.3f} s")


def shifted(spec: Spec, shift_s: float, seen: dict[str, float], now_s: float | None = None,
            end_s: float | None = None, **changes) -> Spec:
    """The spec with its timeline (windows, events) moved by shift_s (s, within t >= 0), the
    events in `seen` put at their observed times (s), and `changes` to its JSON fields.
    end_s (the run's end, s) with now_s (the run's time, s): a timeline moved past the end
    is squeezed into [now_s, end_s] (window times after now_s and cadences scaled alike, so
    the frames stay as many), events put no later than the end."""
    d = spec.to_dict()
    move = lambda x: None if x is None else max(0.0, x + shift_s)  # noqa: E731
    windows = [w for v in d["views"] for w in v["schedule"]]
    for w in windows:
        w["t_start_s"], w["t_end_s"] = move(w["t_start_s"]), move(w["t_end_s"])
    last = max((w["t_end_s"] for w in windows if w["t_end_s"] is not None), default=None)
    if end_s is not None and now_s is not None and last is not None and now_s < end_s < last:
        k = (end_s - now_s) / (last - now_s)
        squeeze = lambda x: x if x is None or x <= now_s else now_s + (x - now_s) * k  # noqa: E731
        for w in windows:
            w["t_start_s"], w["t_end_s"] = squeeze(w["t_start_s"]), squeeze(w["t_end_s"])
            if w.get("every_s"):
                w["every_s"] *= k
    for e in d["events"]:
        at = seen.get(e["name"])
        delta = (at - e["time_s"]) if at is not None else shift_s
        for key in ("time_s", "earliest_s", "latest_s"):
            if key in e:
                e[key] = max(0.0, e[key] + delta)
                if end_s is not None:
                    e[key] = min(e[key], end_s)
    d.update(changes)
    return Spec.from_dict(d)


def widened(spec: Spec, now_s: float, bounds_m: np.ndarray, share: float = WIDEN) -> Spec:
    """The spec with the regions of the windows open at now_s (s) or later grown by `share`
    of their size on every side, twice that ahead along +x (where the flow goes), within
    bounds_m [3, 2] (m): at once, until a re-forecast places them."""
    d = spec.to_dict()
    names = {n for v in d["views"] for w in v["schedule"]
             if w["t_end_s"] is None or w["t_end_s"] >= now_s for n in w.get("regions", ())}
    for r in d["regions"]:
        if r["name"] in names:
            lo, hi = np.array(r["lo_m"]), np.array(r["hi_m"])
            pad = share * (hi - lo)
            r["lo_m"] = np.maximum(lo - pad, bounds_m[:, 0]).tolist()
            r["hi_m"] = np.minimum(hi + pad * [2.0, 1.0, 1.0], bounds_m[:, 1]).tolist()
    return Spec.from_dict(d)


def without_future(spec: Spec, from_s: float) -> dict:
    """The spec's JSON with no window after from_s (s): windows that start later dropped,
    those open then ended there (a view left with none keeps an instant at t = 0, past)."""
    d = spec.to_dict()
    for v in d["views"]:
        kept = [w for w in v["schedule"] if w["t_start_s"] < from_s]
        for w in kept:
            w["t_end_s"] = from_s if w["t_end_s"] is None else min(w["t_end_s"], from_s)
        v["schedule"] = kept or [{**v["schedule"][0], "t_start_s": 0.0, "t_end_s": 0.0}]
    d["snapshots"] = []
    return d


# --- the re-forecast ----------------------------------------------------------------------
@dataclass
class Snapshot:
    """Every particle of the run at one step: positions and displacement [n, 3] (m)."""

    time_s: float
    positions: np.ndarray
    displacement: np.ndarray


def coarse_history(snaps: list[Snapshot], spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """([len(snaps), m, 3] positions, [m, 3] initial positions), m: each snapshot's
    particles averaged per cube of edge spacing_m (the model's) their initial position
    x - displacement starts in, cubes in gns.dataset.coarse_grain's order (x, then y, z).
    ValueError when the snapshots do not hold the same particles."""
    out, keys0, x0 = [], None, None
    for s in snaps:
        start = s.positions.astype(np.float64) - s.displacement
        cube = np.floor(start / spacing_m + 1e-6).astype(np.int64)
        keys, group = np.unique(cube, axis=0, return_inverse=True)
        group = group.reshape(-1)
        if keys0 is None:
            keys0 = keys
            counts = np.bincount(group)
            x0 = np.stack([np.bincount(group, start[:, a]) / counts for a in range(3)], 1)
        elif not np.array_equal(keys, keys0):
            raise ValueError(f"snapshot at {s.time_s:.4f} s holds other particles than the "
                             f"first ({len(keys)} groups, not {len(keys0)})")
        counts = np.bincount(group)
        out.append(np.stack([np.bincount(group, s.positions[:, a]) / counts
                             for a in range(3)], 1))
    return np.stack(out), x0


def roll_to_rest(model, history: np.ndarray, friction_deg: float, bounds_m: np.ndarray,
                 frames: int, peak_ke: float, chunk: int = 20, check=None) -> np.ndarray:
    """[C+1+frames, m, 3] (m): the rollout from history [C+1, m, 3], chunk frames at a time,
    stopped once its mean |v|^2 has stayed below REST_FRACTION of max(peak_ke, its own peak)
    for a chunk (the rest filled with its last frame: at rest). check(): called between
    chunks, raises to abandon the rollout (the run ended or departed again meanwhile)."""
    from minority.gns.rollout import rollout

    c1 = history.shape[0]
    traj, peak = [np.asarray(history, np.float32)], peak_ke
    done = 0
    while done < frames:
        n = min(chunk, frames - done)
        pos, _ = rollout(model, np.concatenate(traj)[-c1:].astype(np.float64), friction_deg,
                         bounds_m, n)
        traj.append(pos[c1:])
        done += n
        v = np.diff(np.concatenate(traj)[-(n + 1):].astype(np.float64), axis=0)
        ke = (v * v).sum(axis=2).mean(axis=1)
        peak = max(peak, float(ke.max()))
        if done >= 2 * chunk and ke[-5:].mean() < REST_FRACTION * peak:
            break
        if check is not None and done < frames:
            check()
    out = np.concatenate(traj)
    if done < frames:
        out = np.concatenate([out, np.repeat(out[-1:], frames - done, axis=0)])
    return out


def joined_events(flow: LiveFlow, t0_s: float, dt: float, rollout: np.ndarray,
                  c1: int) -> tuple[dict[str, float], float, float]:
    """The run's events (s) on its observed Stats up to the rollout's last history frame
    joined to the rollout's series after it (speeds at its frames' times, scaled by the
    run / rollout speed-scale ratio at the join, within CALIBRATION), that ratio, and the
    end of the joined series' last fast window (speed scale >= half its peak), s."""
    sp = speeds(rollout, dt, centered=True)  # [frames, m] m/s
    r_t = t0_s + np.arange(len(sp)) * dt
    r_scale = np.quantile(sp, SPEED_QUANTILE, axis=1)
    r_ke = (sp * sp).mean(axis=1)
    t_join = r_t[c1 - 1]
    t, scale, ke = np.array(flow.time_s), flow.scale(), np.array(flow.ke)
    past = t <= t_join
    # the ratio over the history frames (the one stretch both measure), not one noisy frame
    both = (t >= r_t[0]) & past
    run_s = float(scale[both].mean()) if both.any() else 0.0
    gns_s = float(r_scale[1:c1 - 1].mean()) if c1 > 2 else float(r_scale[c1 - 1])
    ratio = float(np.clip(run_s / gns_s, *CALIBRATION)) if run_s > 1e-6 and gns_s > 1e-6 else 1.0
    after = r_t > (t[past][-1] if past.any() else -1.0)
    tt = np.r_[t[past], r_t[after]]
    e = events_from_series(tt, np.r_[scale[past], ratio * r_scale[after]],
                           np.r_[ke[past], ratio ** 2 * r_ke[after]])
    fast = fast_windows(tt, e.speed_scale_m_s)
    start = fast[0][0] if fast else e.peak_s  # as minority score reads the runout start
    at = {"failure_onset": e.onset_s, "runout_start": start, "peak_motion": e.peak_s,
          "runout_end": e.runout_end_s}
    # what the run already showed, by the online rules, over the joined series' reading
    return ({**at, **observed_events(t, scale, ke, float(ratio * r_scale.max()))}, ratio,
            float(fast[-1][1]) if fast else e.peak_s)


class _Segment(Oracle):
    """The oracle of a rollout that starts mid-run: frame 0 of `positions` is at t0_s (s);
    the windows follow the run's joined events `at` (absolute s), none before from_s (s:
    when the spec will be adopted); displacement is measured from the initial positions x0
    [m, 3] (m). Its spec is in the segment's time: `absolute` moves it onto the run's."""

    def __init__(self, positions, dt, bounds_m, spacing_m, options, t0_s: float,
                 at: dict[str, float], x0: np.ndarray, from_s: float | None = None):
        super().__init__(positions, dt, bounds_m, spacing_m, options)
        self.t0, self.at = t0_s, at
        self.from_s = t0_s if from_s is None else max(t0_s, from_s)
        d = np.linalg.norm(self.positions - x0[None], axis=2)
        self.displacement = (float(d.min()), float(d.max()))
        self.travel_m = self.displacement[1]

    def _own_windows(self) -> dict[str, tuple[float, float]]:
        e = {k: max(0.0, v - self.t0) for k, v in self.at.items()}
        end, pad = self.events.duration_s, self.dt
        first = min(self.from_s - self.t0, max(0.0, end - pad))  # nothing before adoption

        def adopted(a: float, b: float) -> tuple[float, float]:
            a = min(max(a, first), end)
            return a, min(max(b, a + pad), end)

        runout = adopted(max(0.0, e["runout_start"] - pad),
                         max(e["runout_end"], e["runout_start"] + pad) + pad)
        failing = max(e["peak_motion"], e["failure_onset"] + pad)
        if e["peak_motion"] <= pad or failing + pad <= first + pad:
            return {"initiation": runout, "runout": runout}  # the side view follows the runout
        return {"initiation": adopted(max(0.0, e["failure_onset"] - pad), failing + pad),
                "runout": runout}

    def absolute(self, spec: Spec, **provenance) -> Spec:
        d = spec.to_dict()
        for v in d["views"]:
            for w in v["schedule"]:
                w["t_start_s"] += self.t0
                if w["t_end_s"] is not None:
                    w["t_end_s"] += self.t0
        d["events"] = [{"name": n, "time_s": t, "tolerance_s": max(0.1 * t, self.dt)}
                       for n, t in self.at.items()]
        p = d["provenance"]["predicted"]
        p.update(onset_s=self.at["failure_onset"], peak_s=self.at["peak_motion"],
                 runout_end_s=self.at["runout_end"], duration_s=self.t0 + p["duration_s"],
                 fast_windows_s=[[a + self.t0, b + self.t0] for a, b in p["fast_windows_s"]],
                 windows_s={k: [a + self.t0, b + self.t0] for k, (a, b) in
                            p["windows_s"].items()})
        d["provenance"].update(provenance)
        return Spec.from_dict(d)


@dataclass
class Scene:
    """What a rollout needs of the run's scene."""

    bounds_m: np.ndarray  # [3, 2] m
    friction_deg: float
    duration_s: float  # simulated, s


class TooLate(ValueError):
    """The re-forecast would be adopted after the run's end."""


class Superseded(Exception):
    """The run departed again while the GNS rolled: the re-forecast is stale."""

    def __init__(self, departure: Departure):
        super().__init__(departure.reason)
        self.departure = departure


def reforecast(model, stats: dict, spec: Spec, flow: LiveFlow, snaps: list[Snapshot],
               scene: Scene, plan, check=None) -> tuple[Spec, dict]:
    """The spec of the rest of the run from the snapshots ([C + 1] one model frame apart):
    coarse-grain, roll the GNS to rest, then ask plan() -> (from_s, frames): when the spec
    will be adopted (s of the run's time) and how many frames it may plan; join the events
    and plan (gns.oracle) windows from from_s on within those frames (none when the joined
    forecast's fast phase is over by then or the budget is spent: the spec in force ended
    at from_s, with the forecast's events). stats: the checkpoint's
    (particle_spacing_m, frame_interval_s). Returns the spec (snapshots cleared) and what
    its provenance records; TooLate when from_s is past the run's last model frame.
    check: see roll_to_rest."""
    t_start = time.perf_counter()
    dt, spacing = float(stats["frame_interval_s"]), float(stats["particle_spacing_m"])
    history, x0 = coarse_history(snaps, spacing)
    c1 = history.shape[0]
    t0 = snaps[0].time_s
    frames = max(1, round((scene.duration_s - t0) / dt) - (c1 - 1))
    peak_ke = max(flow.ke) if flow.ke else 0.0
    traj = roll_to_rest(model, history, scene.friction_deg, scene.bounds_m, frames,
                        peak_ke * dt * dt,  # the run's peak mean |v|^2, as (m per frame)^2
                        check=check)
    t_plan = time.perf_counter()
    from_s, frames_left = plan()  # the run has moved on while the GNS rolled
    if from_s > scene.duration_s - dt:
        raise TooLate(f"it would be adopted at {from_s:.3f} s, the run ends at "
                      f"{scene.duration_s:.3f} s")
    at, ratio, fast_end = joined_events(flow, t0, dt, traj, c1)
    # frames go where the motion is fast: none when the fast phase is over by then (the
    # joined forecast's, and the run's newest speed scale under half its peak so far: a
    # run still speeding up is not over whatever the rollout says), or the budget spent
    # (under 2 frames a view the oracle plans): events only
    scale = flow.scale()
    slow = len(scale) > 0 and scale[-1] < FAST_FRACTION * scale.max()
    rest = (fast_end <= from_s and slow) or frames_left < 2 * len(VIEWS)
    v0 = spec.to_dict()["views"][0]
    options = OracleOptions(run=spec.run, frames=max(frames_left, 2 * len(VIEWS)),
                            width=v0["width"],
                            height=v0["height"],
                            colormap=v0["colormap"] if isinstance(v0["colormap"], str)
                            else OracleOptions.colormap,
                            occlusion_cull=all(v.occlusion_cull for v in spec.views))
    seg = _Segment(traj, dt, scene.bounds_m, spacing, options, t0, at, x0, from_s)
    new = seg.absolute(seg.spec())
    if rest:  # the spec in force, its windows ended at from_s, with the forecast's events
        new = Spec.from_dict({**without_future(spec, from_s), "events": new.to_dict()["events"],
                              "provenance": new.provenance})
    info = {"particles": int(history.shape[1]), "rollout_frames": int(len(traj) - c1),
            "calibration": float(ratio), "from_s": float(from_s), "fast_end_s": fast_end,
            "frames_planned": 0 if rest else int(options.frames),
            "plan_s": time.perf_counter() - t_plan, "forecast_s": time.perf_counter() - t_start}
    return Spec.from_dict({**new.to_dict(), "provenance": {**new.provenance,
                                                           "forecast": info}}), info


# --- the follower ----------------------------------------------------------------------------
@dataclass
class FollowOptions:
    ranks: int = 0  # ranks of the run (0: the most seen sending Stats at one step)
    max_updates: int = 3  # re-forecasts at most
    snapshot_lead_s: float = 0.01  # first snapshot this long (simulated) after the last Stats
    interval_s: float = 0.005  # the ranks' Stats cadence, s
    wait_s: float = 30.0  # give up waiting for the run's spec after this long (wall)


@dataclass
class Update:
    update: int
    kind: str  # "shift" or "forecast"
    reason: str
    at_t_s: float  # the run's time (latest Stats) when it was put, s
    wall_s: float  # its cost: the re-forecast's wall time (0 for a shift), s
    detail: dict = field(default_factory=dict)

    def line(self) -> str:
        return json.dumps({"update": self.update, "kind": self.kind, "reason": self.reason,
                           "at_t_s": round(self.at_t_s, 4), "wall_s": round(self.wall_s, 3),
                           **self.detail})


class Follower:
    """Follows one run over a zenoh session: call `run` (returns at the run's end)."""

    def __init__(self, session, run: str, model, stats: dict, scene: Scene,
                 options: FollowOptions | None = None, log=None, forecast=reforecast):
        """forecast: (model, stats, spec, flow, snapshots, scene, plan, check) -> (Spec,
        info), reforecast unless a test stubs it (plan() -> (from_s, frames), check(): see
        reforecast)."""
        from minority.protocol import keys

        self.session, self.run_id, self.model, self.stats = session, run, model, stats
        self.scene, self.o = scene, options or FollowOptions()
        self.log = log if log is not None else sys.stderr
        self.forecast = forecast
        self.flow = LiveFlow(self.o.ranks)
        self.detector = Detector(self.o.interval_s)
        self.spec: Spec | None = None
        self.budget_total = 0  # frames, all updates together: the first spec's budget
        self.updates: list[Update] = []
        self.frames = 0  # rendered so far (the server's Timing messages)
        self._plan_wall = PLAN_WALL_S  # the last re-forecast's planning wall time, s
        self._planned: tuple = (None, None, 0)  # the last plan(): (from_s, rate, frames left)
        self._q: queue.Queue = queue.Queue(QUEUE_MESSAGES)
        self.dropped = 0  # messages dropped on a full queue
        self._subs = [session.declare_subscriber(k, self._on(kind)) for k, kind in (
            (keys.stats(run), "stats"), (keys.timing(run), "timing"),
            (keys.event(run), "event"), (keys.spec(run), "spec"))]
        self._chunks = None
        self._snaps: dict[int, dict] = {}  # step -> {rank: chunk}
        self._wanted: tuple[float, ...] = ()
        self._pending: Departure | None = None
        self.ended = False

    def _on(self, kind: str):
        def take(sample) -> None:  # zenoh's thread: enqueue only, with the arrival time
            try:
                self._q.put_nowait((kind, sample.payload.to_bytes(), time.monotonic()))
            except queue.Full:
                self.dropped += 1
        return take

    def fetch_spec(self) -> Spec:
        from minority.protocol import keys
        from minority.protocol.messages import decode_as

        deadline = time.monotonic() + self.o.wait_s
        while time.monotonic() < deadline:
            for reply in self.session.get(keys.spec(self.run_id), timeout=2.0):
                if reply.ok:
                    self._adopt(decode_as(reply.ok.payload.to_bytes(), Spec))
                    return self.spec
            time.sleep(0.2)
        raise TimeoutError(f"no server serves the spec of run {self.run_id!r} "
                           f"(waited {self.o.wait_s:g} s)")

    def _adopt(self, spec: Spec) -> None:
        """The spec in force; the budget of all updates together is the first one's (a
        re-forecast's own budget is what it had left: its provenance keeps the total)."""
        self.spec = spec
        if not self.budget_total:
            self.budget_total = int(spec.provenance.get("budget_total_frames")
                                    or spec.budget.frames or 120)

    def run(self, stop=None, timeout_s: float | None = None) -> list[Update]:
        """Follow until the server says the run ended (or `stop` is set, or timeout_s)."""
        if self.spec is None:
            self.fetch_spec()
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.ended and not (stop is not None and stop.is_set()):
            if deadline is not None and time.monotonic() > deadline:
                break
            try:
                item = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            fresh = self._take(*item) | self._catch_up()  # the run as it is, then judge it
            if fresh:
                self._step()
        self.close()
        return self.updates

    def _catch_up(self) -> bool:
        """Take every queued message; whether one completed a Stats step."""
        fresh = False
        while not self._q.empty():
            fresh |= self._take(*self._q.get_nowait())
        return fresh

    def _take(self, kind: str, payload: bytes, wall_s: float | None = None) -> bool:
        """Take one message (arrived at wall_s, monotonic s); whether it completed a Stats
        step."""
        from minority.protocol.messages import Chunk, Event, EventKind, Stats, decode_as

        if kind == "stats":
            return self.flow.add(decode_as(payload, Stats), wall_s) > 0
        elif kind == "timing":
            self.frames += 1
        elif kind == "event":
            ev = decode_as(payload, Event)
            self.ended |= ev.kind == EventKind.RUN_END and ev.rank < 0
        elif kind == "spec":
            spec = decode_as(payload, Spec)
            if spec.run == self.run_id:
                self._adopt(spec)  # ours come back; another peer's are followed too
        elif kind == "chunk":
            self._chunk(decode_as(payload, Chunk))
        return False

    def _step(self) -> None:
        """A complete Stats step: look for a departure unless snapshots are awaited; retry
        snapshots the run passed without sending."""
        if self._wanted:
            if self.flow.now_s > self._wanted[-1] + 10 * self.o.interval_s:
                self._request_snapshots(self._pending, retry=True)
            return
        forecasts = sum(u.kind == "forecast" for u in self.updates)
        if forecasts >= self.o.max_updates:
            return
        d = self.detector.check(self.spec, self.flow)
        if d is not None:
            self._pending = d
            self._request_snapshots(d)

    def _request_snapshots(self, d: Departure, retry: bool = False) -> None:
        from minority.protocol import keys

        c1 = int(self.model.config.input_velocities) + 1 if self.model is not None else 6
        dt = float(self.stats["frame_interval_s"])
        t0 = self.flow.now_s + self.o.snapshot_lead_s
        if t0 + (c1 - 1) * dt > self.scene.duration_s:
            self._wanted = ()
            return  # too near the end to roll anything forward
        self._wanted = tuple(round(t0 + k * dt, 9) for k in range(c1))
        self._snaps = {}
        if self._chunks is None:
            self._chunks = self.session.declare_subscriber(keys.chunks(self.run_id),
                                                           self._on("chunk"))
        t = np.array(self.flow.time_s)
        seen = observed_events(t, self.flow.scale(), np.array(self.flow.ke), float(
            self.spec.provenance.get("predicted", {}).get("peak_speed_m_s", 0.0)))
        spec = shifted(self.spec, 0.0 if retry else d.shift_s, seen, now_s=self.flow.now_s,
                       end_s=self.scene.duration_s, snapshots=list(self._wanted))
        if d.kind == "regions" and not retry:  # the movers are outside: widen at once
            spec = widened(spec, self.flow.now_s, self.scene.bounds_m)
        self._put(spec, Update(len(self.updates) + 1, "shift", d.reason, self.flow.now_s, 0.0,
                               {"shift_s": 0.0 if retry else d.shift_s, "departure": d.kind,
                                "event": d.event, "snapshots_s": list(self._wanted)}))

    def _chunk(self, chunk) -> None:
        if not self._wanted or "displacement" not in chunk.fields:
            return
        due = (chunk.time_s in self._wanted if chunk.prev_time_s is None else
               any(chunk.prev_time_s < t <= chunk.time_s for t in self._wanted))
        if not due:
            return
        step = self._snaps.setdefault(chunk.step, {})
        step[chunk.rank] = chunk
        full = [s for s in self._snaps.values() if len(s) == next(iter(s.values())).ranks]
        if len(full) < len(self._wanted):
            return
        snaps = [Snapshot(float(next(iter(s.values())).time_s),
                          np.concatenate([c.positions for c in s.values()]).astype(np.float64),
                          np.concatenate([c.fields["displacement"] for c in s.values()]
                                         ).astype(np.float64))
                 for s in sorted(full, key=lambda s: next(iter(s.values())).step)]
        self._chunks.undeclare()
        self._chunks, self._wanted = None, ()
        self._forecast(snaps)

    def plan(self) -> tuple[float, int]:
        """(from_s, frames) of a re-forecast about to be planned: the run's time when its
        spec will be adopted, s (the newest Stats, caught up, plus the planning's expected
        wall time at the run's progress rate, plus a stats interval), and the frames left
        of the budget, less RESERVE_SHARE of them while more re-forecasts may follow."""
        self._catch_up()
        rate = self.flow.rate() or 0.0
        from_s = float(self.flow.now_s + rate * self._plan_wall + self.o.interval_s)
        left = self.budget_total - self.frames
        more = sum(u.kind == "forecast" for u in self.updates) + 1 < self.o.max_updates
        self._planned = (from_s, rate, left)
        return from_s, left - (round(RESERVE_SHARE * left) if more else 0)

    def check_rollout(self) -> None:
        """Between a re-forecast's rollout chunks: catch up with the run; TooLate once it
        reached its end, Superseded when it left the spec in force again (a slow rollout,
        as of a large scene, must not blind the follower until the run ends)."""
        if self._catch_up():
            d = self.detector.check(self.spec, self.flow)
            if d is not None:
                raise Superseded(d)
        end = self.scene.duration_s - float(self.stats["frame_interval_s"])
        if self.flow.now_s >= end:
            raise TooLate(f"the run reached {self.flow.now_s:.3f} s while the GNS rolled")

    def _forecast(self, snaps: list[Snapshot]) -> None:
        d = self._pending
        t0 = time.perf_counter()
        self._planned = (None, None, self.budget_total - self.frames)
        try:
            spec, info = self.forecast(self.model, self.stats, self.spec, self.flow, snaps,
                                       self.scene, self.plan, self.check_rollout)
        except Superseded as exc:  # the new departure's own shift and snapshots instead
            print(f"oracle follow: the re-forecast was abandoned after "
                  f"{time.perf_counter() - t0:.1f} s: the run departed again ({exc})",
                  file=self.log, flush=True)
            self._pending = exc.departure
            self._request_snapshots(exc.departure)
            return
        except Exception as exc:  # noqa: BLE001 - a failed forecast leaves the spec in force
            print(f"oracle follow: the re-forecast failed: {exc!r}", file=self.log, flush=True)
            return
        wall = time.perf_counter() - t0
        self._plan_wall = float(info.get("plan_s", self._plan_wall))
        from_s, rate, left = self._planned
        k = len(self.updates) + 1
        spec = Spec.from_dict({**spec.to_dict(), "run": self.run_id, "provenance": {
            **spec.provenance, "reason": d.reason, "kind": "forecast", "update": k,
            "from_t_s": snaps[0].time_s, "forecast_s": wall,
            "budget_total_frames": self.budget_total, "frames_before": self.frames}})
        self.detector.armed_s = self.flow.now_s + 2 * self.o.interval_s
        self._put(spec, Update(k, "forecast", d.reason, self.flow.now_s, wall,
                               {"from_t_s": snaps[0].time_s, "frames_left": left,
                                "adopt_from_s": from_s, "rate_s_per_s": rate,
                                "events": {e.name: round(e.time_s, 4) for e in spec.events},
                                **{k_: v for k_, v in info.items() if k_ != "forecast_s"}}))

    def _put(self, spec: Spec, u: Update) -> None:
        from minority.protocol import keys
        from minority.protocol.session import CONTROL_QOS, put

        if u.kind == "shift":
            spec = Spec.from_dict({**spec.to_dict(), "provenance": {
                **spec.provenance, "reason": u.reason, "kind": "shift", "update": u.update,
                "from_t_s": u.at_t_s, "forecast_s": 0.0}})
            self.detector.armed_s = self.flow.now_s + 2 * self.o.interval_s
        self._adopt(spec)
        put(self.session, keys.spec(self.run_id), spec.encode(), CONTROL_QOS)
        self.updates.append(u)
        print(u.line(), file=self.log, flush=True)

    def close(self) -> None:
        for s in self._subs + ([self._chunks] if self._chunks is not None else []):
            s.undeclare()
        self._subs, self._chunks = [], None
