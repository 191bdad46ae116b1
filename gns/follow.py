"""`minority oracle follow RUN`: the closed-loop oracle. It reads a run's live Stats, and when
the run leaves what its spec predicted it re-forecasts from the run's own state and puts an
updated spec on minority/{run}/spec, which the server and the ranks adopt without stopping.

Three modules: minority.gns.follow_detect (departures: `LiveFlow`, the ranks' Stats summed per
step, and `Detector`), minority.gns.follow_forecast (the updates' specs and the re-forecast) and
this one (`Follower`, the zenoh peer's loop).

An update is two spec puts, each logged with its reason and cost (provenance: reason, kind,
update, from_t_s, forecast_s, ...):
1. "shift": at once, the spec's timeline moved by the departure (events already seen put at
   their observed times) and `snapshots`: C + 1 simulated times one model frame apart, at
   which every rank sends every particle through the ordinary chunk path (protocol.spec);
2. "forecast": once the snapshots are in, the GNS rolls forward from them until the flow
   rests (`reforecast`), and the oracle plans the rest of the run on that rollout.
"""

from __future__ import annotations

import json
import queue
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from minority.gns.events import FAST_FRACTION
from minority.gns.follow_detect import (  # noqa: F401 - re-exported: minority.gns.follow's names
    PEAK_FALL,
    REGIONS_TARGET,
    REST_FRACTION,
    Departure,
    Detector,
    LiveFlow,
    observed_events,
    slow_after_peak,
)
from minority.gns.follow_forecast import (  # noqa: F401 - re-exported
    CALIBRATION,
    WIDEN,
    Scene,
    Snapshot,
    Superseded,
    TooLate,
    _Segment,
    coarse_history,
    joined_events,
    reforecast,
    roll_to_rest,
    shifted,
    standing,
    widened,
    without_future,
)
from minority.protocol.spec import Spec

RESERVE_SHARE = 0.25  # of the frames left, kept for later updates while re-forecasts remain
PLAN_WALL_S = 1.0  # first guess of the planning's wall time after the rollout, s
FORECAST_WALL_S = 5.0  # first guess of a re-forecast's wall time, snapshots in to spec put, s
QUEUE_MESSAGES = 65536  # messages queued for the follower's thread at most


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
    kind: str  # "shift", "forecast" or "end" (the windows ended after the fast phase)
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
        self._forecast_wall = FORECAST_WALL_S  # the last re-forecast's wall time, s
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
        self._fast_over = False  # the windows were ended after the run's fast phase
        self._join_s = float("-inf")  # the last snapshot of the forecast in flight, s
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
        self._end_after_fast_phase()
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

    def _end_after_fast_phase(self) -> None:
        """Once: the run slow after its fast phase (two Stats steps in a row, see
        slow_after_peak) while the spec in force has frames ahead: its windows end now (the
        snapshots awaited kept), an "end" update. Frames go where the motion is fast: the
        prediction's longer fast phase, or its deceleration to rest, would spend them after
        the critical window."""
        now = self.flow.now_s
        if self._fast_over or not slow_after_peak(self.flow, steps=2):
            return
        if standing(self.spec):
            return  # its frames ahead are the picture of the end, no fast phase's
        if not any(w.t_end_s is None or w.t_end_s > now
                   for v in self.spec.views for w in v.schedule):
            return
        self._fast_over = True
        spec = Spec.from_dict({**without_future(self.spec, now),
                               "snapshots": list(self._wanted)})
        scale = self.flow.scale()
        self._put(spec, Update(len(self.updates) + 1, "end",
                               f"the fast phase over at {now:.3f} s: the speed scale "
                               f"{scale[-1]:.3g} m/s, under half its peak {scale.max():.3g} m/s",
                               now, 0.0))

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
        hold = not retry and self.holds(d)
        if hold:  # no frame until the forecast plans them
            spec = Spec.from_dict({**without_future(spec, self.flow.now_s),
                                   "snapshots": list(self._wanted)})
        self._put(spec, Update(len(self.updates) + 1, "shift", d.reason, self.flow.now_s, 0.0,
                               {"shift_s": 0.0 if retry else d.shift_s, "departure": d.kind,
                                "event": d.event, "snapshots_s": list(self._wanted),
                                "hold": hold}))

    def holds(self, d: Departure) -> bool:
        """Whether a departure's shift renders nothing new (the moved timeline would spend
        frames where the motion is slow): the run past its fast phase (slow_after_peak), or
        an event late while the kinetic energy rises again and the run is slow (its speed
        scale under FAST_FRACTION of its peak so far: when its fast phase comes is what the
        prediction got wrong) and the re-forecast, which plans the frames, can land before
        the run's end."""
        if slow_after_peak(self.flow):
            return True
        scale, ke = self.flow.scale(), np.array(self.flow.ke)
        rising = len(ke) >= 3 and int(np.argmax(ke)) >= len(ke) - 2
        return bool(d.kind == "late" and rising and scale[-1] < FAST_FRACTION * scale.max()
                    and self.lands_s(self.flow.now_s) < self.scene.duration_s)

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
        of the budget, less RESERVE_SHARE of them while another re-forecast may follow and
        land before the run's end (`lands_s`)."""
        self._catch_up()
        rate = self.flow.rate() or 0.0
        from_s = float(self.flow.now_s + rate * self._plan_wall + self.o.interval_s)
        left = self.budget_total - self.frames
        more = (sum(u.kind == "forecast" for u in self.updates) + 1 < self.o.max_updates
                and self.lands_s(from_s) < self.scene.duration_s)
        self._planned = (from_s, rate, left)
        return from_s, left - (round(RESERVE_SHARE * left) if more else 0)

    def lands_s(self, from_s: float) -> float:
        """The run's time (s) a re-forecast asked for at from_s (s) would be adopted: the
        snapshots' lead and span, then the last re-forecast's wall time at the run's
        progress rate, and a stats interval."""
        c1 = int(self.model.config.input_velocities) + 1 if self.model is not None else 6
        span = self.o.snapshot_lead_s + (c1 - 1) * float(self.stats["frame_interval_s"])
        rate = self.flow.rate() or 0.0
        return from_s + span + rate * self._forecast_wall + self.o.interval_s

    def check_rollout(self) -> None:
        """Between a re-forecast's rollout chunks: catch up with the run; TooLate once it
        reached its end, Superseded when it left the spec in force again (a slow rollout,
        as of a large scene, must not blind the follower until the run ends)."""
        if self._catch_up():
            d = self.detector.check(self.spec, self.flow)
            if d is not None and self._stale(d):
                raise Superseded(d)
        end = self.scene.duration_s - float(self.stats["frame_interval_s"])
        if self.flow.now_s >= end:
            raise TooLate(f"the run reached {self.flow.now_s:.3f} s while the GNS rolled")

    def _stale(self, d: Departure) -> bool:
        """Whether a departure seen while the GNS rolls makes the forecast in flight stale:
        motion outside the regions, or an event early that happened after its snapshots.
        One before them the forecast reads from the run's Stats at its join; a late one
        says the shift's guess was wrong, which the forecast replaces."""
        if d.kind == "regions":
            return True
        e = {e.name: e for e in self.spec.events}.get(d.event)
        return d.kind == "early" and (e is None or e.time_s + d.shift_s > self._join_s)

    def _forecast(self, snaps: list[Snapshot]) -> None:
        d = self._pending
        t0 = time.perf_counter()
        self._join_s = snaps[-1].time_s if snaps else float("-inf")  # the rollout's start
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
        self._forecast_wall = wall
        from_s, rate, left = self._planned
        k = len(self.updates) + 1
        spec = Spec.from_dict({**spec.to_dict(), "run": self.run_id, "provenance": {
            **spec.provenance, "reason": d.reason, "kind": "forecast", "update": k,
            "from_t_s": snaps[0].time_s, "forecast_s": wall,
            "budget_total_frames": self.budget_total, "frames_before": self.frames}})
        self.detector.armed_s = self.flow.now_s + 2 * self.o.interval_s
        self.detector.new_prediction()
        self._put(spec, Update(k, "forecast", d.reason, self.flow.now_s, wall,
                               {"from_t_s": snaps[0].time_s, "frames_left": left,
                                "adopt_from_s": from_s, "rate_s_per_s": rate,
                                "events": {e.name: round(e.time_s, 4) for e in spec.events},
                                **{k_: v for k_, v in info.items() if k_ != "forecast_s"}}))

    def _put(self, spec: Spec, u: Update) -> None:
        from minority.protocol import keys
        from minority.protocol.session import CONTROL_QOS, put

        if u.kind != "forecast":  # a shift or an end
            spec = Spec.from_dict({**spec.to_dict(), "provenance": {
                **spec.provenance, "reason": u.reason, "kind": u.kind, "update": u.update,
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
