"""The closed-loop oracle's updates: the spec edits of a "shift" (`shifted`, `widened`) and
the "forecast" (`reforecast`): once the snapshots are in, their particles grouped by the cube
of the model's spacing their initial position x - displacement lies in (as the training data
were coarse-grained: gns.dataset.coarse_grain), the GNS rolls forward from them until the
flow rests, and the oracle plans the rest of the run on that rollout (gns.oracle), with the
events of the run's observed past joined to the forecast's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from minority.gns.events import FAST_FRACTION, events_from_series, fast_windows, speeds
from minority.gns.follow_detect import REST_FRACTION, Departure, LiveFlow, observed_events
from minority.gns.oracle import VIEWS, Oracle, OracleOptions
from minority.protocol.flow import SPEED_QUANTILE
from minority.protocol.spec import Spec

WIDEN = 0.25  # a regions departure grows the regions in use by this share of their size
CALIBRATION = (0.5, 2.0)  # bounds of the run / forecast speed ratio at the join
TREND_S = 0.025  # a run speeding up at the join: its growth rate over this stretch, s
TREND_GROWTH = 0.1  # ... once its speed scale grew by this share over it
G_M_S2 = 9.81  # gravity, m/s^2


def shifted(spec: Spec, shift_s: float, seen: dict[str, float], now_s: float | None = None,
            end_s: float | None = None, **changes) -> Spec:
    """The spec with its timeline (windows, events) moved by shift_s (s, within t >= 0), the
    events in `seen` put at their observed times (s), and `changes` to its JSON fields.
    end_s (the run's end, s) with now_s (the run's time, s): a timeline moved past the end
    is squeezed into [now_s, end_s] (window times after now_s and cadences scaled alike, so
    the frames stay as many), events put no later than the end, and those not in `seen`
    no earlier than now_s."""
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
        # an event not seen by now_s has not happened: it is not put before now_s
        floor = now_s if at is None and now_s is not None else 0.0
        for key in ("time_s", "earliest_s", "latest_s"):
            if key in e:
                e[key] = max(floor, e[key] + delta)
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


def standing(spec: Spec) -> bool:
    """Whether the spec is the oracle's prediction of no flow (each view at the run's start
    and end: gns.oracle's standing spec)."""
    return bool(spec.provenance.get("predicted", {}).get("standing"))


def without_future(spec: Spec, from_s: float) -> dict:
    """The spec's JSON with no window after from_s (s): windows that start later dropped,
    those open then ended there (a view left with none keeps an instant at t = 0, past).
    A standing spec (no flow predicted: each view at the run's start and end) keeps its
    picture of the end: an instant, not frames spent on a fast phase."""
    d = spec.to_dict()
    keep_end = standing(spec)
    for v in d["views"]:
        ends = [{**w, "t_start_s": w["t_end_s"]} for w in v["schedule"] if keep_end
                and w["t_end_s"] is not None and w["t_end_s"] > max(from_s, w["t_start_s"])]
        kept = [w for w in v["schedule"] if w["t_start_s"] < from_s]
        for w in kept:
            w["t_end_s"] = from_s if w["t_end_s"] is None else min(w["t_end_s"], from_s)
        v["schedule"] = (kept or [{**v["schedule"][0], "t_start_s": 0.0, "t_end_s": 0.0}]) + ends
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
                 frames: int, peak_ke: float, chunk: int = 20, check=None,
                 enough=None) -> tuple[np.ndarray, int]:
    """([C+1+frames, m, 3] (m), frames rolled): the rollout from history [C+1, m, 3], chunk
    frames at a time,
    stopped once its mean |v|^2 has stayed below REST_FRACTION of max(peak_ke, its own peak)
    for a chunk, or enough(rollout so far) says so (the rest filled with its last frame: at
    rest). check(): called between chunks, raises to abandon the rollout (the run ended or
    departed again meanwhile)."""
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
        if enough is not None and done < frames and enough(np.concatenate(traj)):
            break
        if check is not None and done < frames:
            check()
    out = np.concatenate(traj)
    if done < frames:
        out = np.concatenate([out, np.repeat(out[-1:], frames - done, axis=0)])
    return out, done


def speeding_up(t: np.ndarray, scale: np.ndarray, ke: np.ndarray,
                until_s: float) -> float | None:
    """The growth rate (1/s) of the run's speed scale over the TREND_S before until_s (s)
    when the run is speeding up then: its kinetic energy at its largest so far and its speed
    scale grown by at least TREND_GROWTH over that stretch; else None. t, scale, ke [k]:
    the run's Stats (s, m/s, mean |v|^2)."""
    k = np.flatnonzero(t <= until_s + 1e-9)
    if len(k) < 3:
        return None
    last = k[-1]
    tail = k[t[k] >= t[last] - TREND_S - 1e-9]
    if len(tail) < 3 or ke[last] < ke[:last + 1].max() or scale[tail[0]] <= 0:
        return None
    if scale[last] < (1.0 + TREND_GROWTH) * scale[tail[0]]:
        return None
    rate = np.polyfit(t[tail] - t[last], np.log(np.maximum(scale[tail], 1e-12)), 1)[0]
    return float(rate) if rate > 0 else None


class Joined(NamedTuple):
    at: dict[str, float]  # the events, s
    ratio: float  # the run / rollout speed-scale ratio at the join
    fast_end_s: float  # the end of the joined series' last fast window, s
    speed_scale_m_s: np.ndarray  # [len(rollout)] the joined series at the rollout's frames
    trend: bool  # the run's own trend replaced the rollout after the join


def joined_events(flow: LiveFlow, t0_s: float, dt: float, rollout: np.ndarray,
                  c1: int) -> Joined:
    """The run's events (s) on its observed Stats up to the rollout's last history frame
    joined to the rollout's series after it (speeds at its frames' times, scaled by the
    run / rollout speed-scale ratio at the join, within CALIBRATION), that ratio, the end
    of the joined series' last fast window (speed scale >= half its peak), s, and the
    joined speed scale at the rollout's frames [len(rollout)] (m/s; the run's, linearly
    interpolated, up to the join).
    A run speeding up at the join (`speeding_up`) that the rollout has slowing at once (its
    scaled speed after the join never above the run's there: a model outside what it
    learnt, e.g. a column creeping before it fails) is joined to its own trend instead: its
    speed scale growing at its rate until the run's end, at most the free-fall speed from
    the top of the material (sqrt(2 g h), h its height at the join, m); the rate and the
    series are the run's up to its newest Stats when it is still speeding up then (a
    failing column's growth accelerates: the freshest stretch is the best guess), and its
    runout start is the start of the fast window that holds its peak (the trend's peak is a
    guess from below: an earlier, smaller motion is not the runout)."""
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
    f_scale, f_ke = ratio * r_scale[after], ratio ** 2 * r_ke[after]
    rate = speeding_up(t, scale, ke, t_join) if past.any() else None
    trend = rate is not None and after.any() and f_scale.max() <= scale[past][-1]
    newest = speeding_up(t, scale, ke, float(t[-1])) if trend else None
    if newest is not None:  # the rollout set aside: the run's newest Stats, its growth then
        rate, past, after = newest, np.ones(len(t), bool), r_t > t[-1]
    if trend:
        z = rollout[c1 - 1][:, 2]
        cap = max(np.sqrt(2 * G_M_S2 * float(z.max() - z.min())), scale[past][-1])
        grow = np.exp(rate * (r_t[after] - t[past][-1]))
        f_scale = np.minimum(scale[past][-1] * grow, cap)
        f_ke = ke[past][-1] * (f_scale / scale[past][-1]) ** 2
    tt = np.r_[t[past], r_t[after]]
    e = events_from_series(tt, np.r_[scale[past], f_scale], np.r_[ke[past], f_ke])
    fast = fast_windows(tt, e.speed_scale_m_s)
    if trend:  # the run past anything it did before: its fast phase is the trend's
        fast = [w for w in fast if w[1] >= e.peak_s - 1e-9] or fast
    start = fast[0][0] if fast else e.peak_s  # as minority score reads the runout start
    at = {"failure_onset": e.onset_s, "runout_start": start, "peak_motion": e.peak_s,
          "runout_end": e.runout_end_s}
    # what the run already showed, by the online rules, over the joined series' reading
    ref = max(float(ratio * r_scale.max()), float(f_scale.max(initial=0.0)))
    joined = np.r_[np.interp(r_t[~after], t, scale) if len(t) else r_scale[~after], f_scale]
    return Joined({**at, **observed_events(t, scale, ke, ref)}, ratio,
                  float(fast[-1][1]) if fast else e.peak_s, joined, bool(trend))


class _Segment(Oracle):
    """The oracle of a rollout that starts mid-run: frame 0 of `positions` is at t0_s (s);
    the windows follow the run's joined events `at` (absolute s), none before from_s (s:
    when the spec will be adopted); displacement is measured from the initial positions x0
    [m, 3] (m); speed_scale_m_s [frames] (m/s; default the rollout's own): where its
    frames go (the fast phase its windows are cut at, the cadence). Its spec is in the
    segment's time: `absolute` moves it onto the run's."""

    def __init__(self, positions, dt, bounds_m, spacing_m, options, t0_s: float,
                 at: dict[str, float], x0: np.ndarray, from_s: float | None = None,
                 speed_scale_m_s: np.ndarray | None = None):
        super().__init__(positions, dt, bounds_m, spacing_m, options)
        self.t0, self.at = t0_s, at
        if speed_scale_m_s is not None:  # the joined series: cadence and fast phase follow it
            self.scale = self.envelope = np.asarray(speed_scale_m_s, dtype=np.float64)
        self.from_s = t0_s if from_s is None else max(t0_s, from_s)
        d = np.linalg.norm(self.positions - x0[None], axis=2)
        self.displacement = (float(d.min()), float(d.max()))
        self.travel_m = self.displacement[1]

    def standing(self) -> bool:
        return False  # the run departed: its own speed series says where frames go

    def _own_windows(self) -> dict[str, tuple[float, float]]:
        e = {k: max(0.0, v - self.t0) for k, v in self.at.items()}
        end, pad = self.events.duration_s, self.dt
        first = min(self.from_s - self.t0, max(0.0, end - pad))  # nothing before adoption

        def adopted(a: float, b: float) -> tuple[float, float]:
            a = min(max(a, first), end)
            return a, min(max(b, a + pad), end)

        runout = adopted(e["runout_start"],  # from its first frame, as gns.oracle's
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
    traj, rolled = roll_to_rest(model, history, scene.friction_deg, scene.bounds_m, frames,
                        peak_ke * dt * dt,  # the run's peak mean |v|^2, as (m per frame)^2
                        check=check,  # a rollout the run's trend replaces: no further
                        enough=lambda so_far: joined_events(flow, t0, dt, so_far, c1).trend)
    t_plan = time.perf_counter()
    from_s, frames_left = plan()  # the run has moved on while the GNS rolled
    if from_s > scene.duration_s - dt:
        raise TooLate(f"it would be adopted at {from_s:.3f} s, the run ends at "
                      f"{scene.duration_s:.3f} s")
    at, ratio, fast_end, joined, trend = joined_events(flow, t0, dt, traj, c1)
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
    seg = _Segment(traj, dt, scene.bounds_m, spacing, options, t0, at, x0, from_s,
                   speed_scale_m_s=joined)
    new = seg.absolute(seg.spec())
    if rest:  # the spec in force, its windows ended at from_s, with the forecast's events
        new = Spec.from_dict({**without_future(spec, from_s), "events": new.to_dict()["events"],
                              "provenance": new.provenance})
    info = {"particles": int(history.shape[1]), "rollout_frames": int(len(traj) - c1),
            "rolled_frames": int(rolled), "rollout_s": t_plan - t_start,
            "calibration": float(ratio), "from_s": float(from_s), "fast_end_s": fast_end,
            "frames_planned": 0 if rest else int(options.frames),
            "plan_s": time.perf_counter() - t_plan, "forecast_s": time.perf_counter() - t_start}
    return Spec.from_dict({**new.to_dict(), "provenance": {**new.provenance,
                                                           "forecast": info}}), info
