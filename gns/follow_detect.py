"""The closed-loop oracle's eyes: the run as its Stats tell it (`LiveFlow`, the ranks' Stats
summed per step) and when it leaves what its spec predicted (`Detector`).

Departures:
- an event early: observed before its predicted interval (the ensemble's [earliest_s,
  latest_s], else time_s +- tolerance_s), by more than one stats interval, unless a later
  event was seen inside its own interval;
- an event late: the interval has passed and the event has not happened (the flow still
  moving at the predicted rest is the runout end late);
- motion outside the regions: under 99 % of the moving particles inside the open regions
  at two stats steps in a row.
Events are read online by the rules of gns.events, against the predicted peak speed until
the run's own peak is known.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from minority.gns.events import EVENT_NAMES, FAST_FRACTION, fast_windows
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
RATE_WINDOW_S = 5.0  # the run's progress rate is measured over this much wall time, s

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


def slow_after_peak(flow: LiveFlow, steps: int = 1) -> bool:
    """Whether the run is past its fast phase: its kinetic-energy peak seen (fallen below
    PEAK_FALL of it, as observed_events reads the peak) and its speed scale under
    FAST_FRACTION of its peak so far at the last `steps` Stats steps."""
    if len(flow.ke) < steps + 1:
        return False
    ke, scale = np.array(flow.ke), flow.scale()
    return bool(ke.max() > 0 and ke[-1] < PEAK_FALL * ke.max()
                and (scale[-steps:] < FAST_FRACTION * scale.max()).all())


@dataclass(frozen=True)
class Departure:
    kind: str  # "early", "late" or "regions"
    event: str | None  # the event, for early and late
    at_s: float  # the run's time when it was seen, s
    shift_s: float  # how far the predicted timeline should move, s
    reason: str


class Detector:
    """When the run leaves its spec's predictions (see the module docstring). Each (kind,
    event) is acted on once per prediction (`new_prediction` forgets them: a re-forecast's
    event missed again is a new departure); motion outside the regions at most twice
    altogether; regions are judged
    only on Stats after `armed_s` (the ranks measured them with an older spec before)."""

    def __init__(self, interval_s: float = 0.005):
        self.interval_s = interval_s
        self.acted: set[tuple[str, str | None]] = set()
        self.armed_s = -1.0

    def new_prediction(self) -> None:
        """A re-forecast's events are in force: their departures are acted on anew."""
        self.acted = {a for a in self.acted if a[0] == "regions"}

    def check(self, spec: Spec, flow: LiveFlow) -> Departure | None:
        if not flow.time_s:
            return None
        t, scale, ke = np.array(flow.time_s), flow.scale(), np.array(flow.ke)
        predicted = spec.provenance.get("predicted", {})
        seen = observed_events(t, scale, ke, float(predicted.get("peak_speed_m_s", 0.0)))
        now, slack = float(t[-1]), self.interval_s

        def interval(e) -> tuple[float, float]:
            return e.interval_s or (e.time_s - e.tolerance_s, e.time_s + e.tolerance_s)

        # the latest event seen inside its interval: the run was on the prediction then, so
        # an event early before it (the runout start, read only once the peak is known)
        # says nothing of what is to come
        back = max((seen[e.name] for e in spec.events if e.name in seen
                    and interval(e)[0] - slack <= seen[e.name] <= interval(e)[1] + slack),
                   default=-1.0)
        for e in spec.events:
            if e.name not in EVENT_NAMES:
                continue
            lo, hi = interval(e)
            got = seen.get(e.name)
            if (got is not None and got < lo - slack and got > back
                    and ("early", e.name) not in self.acted):
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
        return self._regions(flow, scale, predicted)

    def _regions(self, flow: LiveFlow, scale: np.ndarray, predicted: dict) -> Departure | None:
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
