"""The closed-loop oracle (minority.gns.follow, `minority oracle follow`): the spec's optional
snapshots, the departure detector on synthetic Stats, the coarse-graining of snapshots, the
timeline shift, and one loopback run (a real server and rank) whose early onset makes the
follower ask for snapshots, receive them through the ordinary chunk path and put a
re-forecast (stubbed) that the server and the rank adopt without stopping."""

import io
import threading

import numpy as np
import pytest
from test_loopback import wait_until

from minority.gns.dataset import coarse_grain
from minority.gns.follow import (
    Detector,
    Follower,
    FollowOptions,
    LiveFlow,
    Scene,
    Snapshot,
    coarse_history,
    observed_events,
    shifted,
)
from minority.insitu import connect
from minority.protocol import Spec
from minority.protocol.errors import SpecError
from minority.protocol.messages import Stats, speed_histogram
from minority.render_server.daemon import RenderServer, ServerOptions

RUN = "follow-run"
DT = 0.001  # s per sim step of the synthetic runs
FRAME_S = 0.005  # the model's frame interval of the stub checkpoint stats
NONE = np.zeros(0)


def spec(**extra) -> Spec:
    d = {"version": 2, "run": RUN, "views": [{
        "name": "side", "camera": {"position": [0.5, -2.0, 0.5], "focal_point": [0.5, 0.5, 0.5]},
        "width": 32, "height": 24, "field": "displacement", "range": [0, 1],
        "schedule": [{"t_start_s": 0.2, "t_end_s": 0.4, "every_s": 0.05, "regions": ["a"]}]}],
        "regions": [{"name": "a", "lo_m": [0, 0, 0], "hi_m": [1, 1, 1]}],
        "events": [{"name": "failure_onset", "time_s": 0.2, "tolerance_s": 0.02},
                   {"name": "runout_start", "time_s": 0.25, "tolerance_s": 0.025},
                   {"name": "peak_motion", "time_s": 0.3, "tolerance_s": 0.03},
                   {"name": "runout_end", "time_s": 0.5, "tolerance_s": 0.05}],
        "budget": {"frames": 30},
        "provenance": {"predicted": {"peak_speed_m_s": 1.0}}, **extra}
    return Spec.from_dict(d)


# --- the spec's snapshots ---------------------------------------------------------------------
def test_snapshots_ask_every_particle_at_their_steps_and_old_specs_encode_unchanged():
    plain = spec()
    assert "snapshots" not in plain.to_dict()  # absent: the spec encodes as before
    s = spec(snapshots=[0.0105, 0.3])
    assert Spec.from_dict(s.to_dict()) == s and s.to_dict()["snapshots"] == [0.0105, 0.3]
    assert plain.request(10, 0.010, 0.009) is None
    assert s.request(10, 0.010, 0.009) is None and s.request(12, 0.012, 0.011) is None
    r = s.request(11, 0.011, 0.010)  # 0.0105 in (0.010, 0.011]
    assert r.snapshot and r.regions is None and r.decimate == 1 and not r.visible_in
    assert r.views == () and set(r.fields) == {"displacement"}
    # merged with a view due at the same step: rendered as usual, every particle sent
    due = s.request(300, 0.3, 0.2995)
    assert due.snapshot and due.views == ("side",) and due.regions is None
    assert plain.request(300, 0.3, 0.2995).regions is not None


@pytest.mark.parametrize(("times", "problem"), [([0.2, 0.1], "snapshots: times must increase"),
                                                ([-0.1], "snapshots")])
def test_bad_snapshot_times_are_refused_by_name(times, problem):
    with pytest.raises(SpecError, match=problem):
        spec(snapshots=times)


# --- the detector ---------------------------------------------------------------------------
def stats_at(step: int, speeds_in: np.ndarray, speeds_out: np.ndarray = NONE,
             rank: int = 0) -> Stats:
    every = np.r_[speeds_in, speeds_out]
    return Stats(RUN, rank, step, step * DT, len(every), float((every ** 2).sum()),
                 float(every.max(initial=0.0)), 0.0, True, speed_histogram(speeds_in),
                 speed_histogram(speeds_out))


def flow_of(speed_of_t, until_s: float, outside=lambda t: 0.0, ranks: int = 2) -> LiveFlow:
    """Stats every 5 ms from two ranks of 100 particles each moving at speed_of_t(t) m/s
    (inside the regions) and a share outside(t) of them elsewhere."""
    flow = LiveFlow(ranks)
    for step in range(0, round(until_s / DT) + 1, 5):
        t = step * DT
        n_out = round(100 * outside(t))
        for rank in range(ranks):
            flow.add(stats_at(step, np.full(100 - n_out, speed_of_t(t)),
                              np.full(n_out, speed_of_t(t)), rank))
    return flow


def collapse(onset_s: float, rest_s: float):
    """Speed (m/s) of a collapse: rising from onset_s, peak 1 m/s halfway, rest at rest_s."""
    mid = 0.5 * (onset_s + rest_s)
    return lambda t: 0.0 if t < onset_s or t > rest_s else max(
        0.0, 1.0 - abs(t - mid) / (mid - onset_s)) + 1e-3


def test_a_stats_step_counts_once_every_rank_sent_it():
    flow = LiveFlow(2)
    assert flow.add(stats_at(0, np.zeros(10), rank=0)) == 0
    assert flow.add(stats_at(0, np.zeros(10), rank=1)) == 1 and flow.count == 20


def test_an_early_onset_is_a_departure_with_its_shift():
    flow = flow_of(collapse(0.1, 0.5), 0.13)
    d = Detector().check(spec(), flow)
    assert d.kind == "early" and d.event == "failure_onset"
    assert d.shift_s == pytest.approx(observed_events(
        np.array(flow.time_s), flow.scale(), np.array(flow.ke), 1.0)["failure_onset"] - 0.2)
    assert d.shift_s < -0.05 and "before the predicted" in d.reason


def test_an_event_early_before_one_on_time_is_no_departure():
    """The runout start (read once the peak is known) early, the peak on time: the run was
    back on the prediction by then; with the peak late too, it is a departure."""
    def fast_rise(peak_s):  # onset at 0.19 s, half the peak speed by 0.2 s, peak at peak_s
        return lambda t: (0.0 if t < 0.19 else 0.5 * min(1.0, (t - 0.19) / 0.01)
                          + 0.5 * float(np.clip((t - 0.2) / (peak_s - 0.2), 0, 1))
                          - float(np.clip((t - peak_s) / 0.15, 0, 1))) + 1e-3
    on_time = flow_of(fast_rise(0.3), 0.34)
    seen = observed_events(np.array(on_time.time_s), on_time.scale(), np.array(on_time.ke),
                           1.0)
    assert seen["runout_start"] < 0.22 and seen["peak_motion"] == pytest.approx(0.3, abs=0.01)
    assert Detector().check(spec(), on_time) is None
    d = Detector().check(spec(), flow_of(fast_rise(0.36), 0.4))  # the peak late as well
    assert d is not None and d.kind == "early" and d.event == "runout_start"


def test_a_run_on_time_is_no_departure_and_a_flow_moving_at_the_predicted_rest_is():
    on_time = flow_of(collapse(0.19, 0.47), 0.55)
    det = Detector()
    assert det.check(spec(), on_time) is None
    late = flow_of(collapse(0.19, 0.7), 0.58)
    d = Detector().check(spec(), late)
    assert d.kind == "late" and d.event == "runout_end"
    assert d.reason.startswith("the flow still moving at the predicted rest")
    assert d.shift_s > 0.0


def test_motion_outside_the_regions_is_a_departure_once_armed():
    flow = flow_of(lambda t: 0.5 if t >= 0.2 else 0.0, 0.25, outside=lambda t: 0.1)
    det = Detector()
    s = Spec.from_dict({**spec().to_dict(), "events": []})
    d = det.check(s, flow)
    assert d.kind == "regions" and "90.0 %" in d.reason
    det2 = Detector()
    det2.armed_s = 0.25  # Stats measured under an older spec do not count
    assert det2.check(s, flow) is None


def test_shifted_moves_the_timeline_and_puts_seen_events_at_their_times():
    s = shifted(spec(), -0.1, {"failure_onset": 0.09}, snapshots=[0.12, 0.125])
    w = s.views[0].schedule[0]
    assert (w.t_start_s, w.t_end_s) == pytest.approx((0.1, 0.3))
    times = {e.name: e.time_s for e in s.events}
    assert times == pytest.approx({"failure_onset": 0.09, "runout_start": 0.15,
                                   "peak_motion": 0.2, "runout_end": 0.4})
    assert s.snapshots == (0.12, 0.125)


def test_a_timeline_shifted_past_the_run_end_is_squeezed_into_what_is_left():
    s = shifted(spec(), 0.7, {}, now_s=0.8, end_s=1.0)  # windows 0.9-1.1, rest at 1.2
    w = s.views[0].schedule[0]
    assert (w.t_start_s, w.t_end_s) == pytest.approx((0.8 + 0.1 * 0.2 / 0.3, 1.0))
    assert w.every_s == pytest.approx(0.05 * 0.2 / 0.3)  # as many frames as before
    assert max(e.time_s for e in s.events) == pytest.approx(1.0)
    inside = shifted(spec(), 0.1, {}, now_s=0.3, end_s=1.0).views[0].schedule[0]
    assert (inside.t_start_s, inside.t_end_s, inside.every_s) == pytest.approx((0.3, 0.5, 0.05))
    # events not seen by now are not put in the past (the runout end late at 0.55 s, the
    # peak not seen: moved by 0.1 s it would be at 0.4 s)
    times = {e.name: e.time_s for e in shifted(spec(), 0.1, {"failure_onset": 0.19},
                                               now_s=0.55, end_s=1.0).events}
    assert times == pytest.approx({"failure_onset": 0.19, "runout_start": 0.55,
                                   "peak_motion": 0.55, "runout_end": 0.6})


def test_the_progress_rate_is_simulated_over_wall_time_of_the_latest_stats():
    flow = LiveFlow(1)
    assert flow.rate() is None
    for k in range(40):  # a Stats step every 5 ms of simulated time, every 0.25 s of wall
        flow.add(stats_at(5 * k, np.zeros(4)), wall_s=100.0 + 0.25 * k)
    assert flow.rate() == pytest.approx(0.005 / 0.25)


class _Session:  # what a Follower declares on and puts to, no network
    def __init__(self):
        self.puts = []

    def declare_subscriber(self, key, handler):
        return type("Sub", (), {"undeclare": lambda self: None})()

    def put(self, key, payload, **qos):
        self.puts.append((key, bytes(payload)))


def test_the_budget_is_the_first_specs_and_a_reserve_is_kept_for_later_updates():
    stats = {"frame_interval_s": FRAME_S, "particle_spacing_m": 0.02}
    f = Follower(_Session(), RUN, None, stats, Scene(np.array([[0, 1.0]] * 3), 30.0, 1.0),
                 FollowOptions(ranks=1, max_updates=3), log=io.StringIO())
    f._adopt(spec())
    # a re-forecast's own budget is what it had left; the total stays the first spec's
    f._adopt(Spec.from_dict({**spec().to_dict(), "budget": {"frames": 8},
                             "provenance": {"budget_total_frames": 30}}))
    assert f.budget_total == 30
    for k in range(21):  # the run at 0.1 s, 0.1 s of run per s of wall
        f.flow.add(stats_at(5 * k, np.zeros(4)), wall_s=10.0 + 0.05 * k)
    f.frames = 10
    from_s, frames = f.plan()
    assert from_s == pytest.approx(0.1 + 0.1 * 1.0 + 0.005)  # + the planning's wall time
    assert type(from_s) is float and type(frames) is int  # JSON in the spec's provenance
    assert frames == 20 - 5  # 20 left, a quarter kept
    # another re-forecast (its snapshots 35 ms, then 5 s of wall at 0.1 s/s) lands at 0.75 s
    assert f.lands_s(from_s) == pytest.approx(from_s + 0.035 + 0.5 + 0.005)
    f._forecast_wall = 8.0  # ... but at 1.05 s after a slower one: past the run's end, all
    assert f.plan()[1] == 20
    f._forecast_wall = 5.0
    f.updates = [type("U", (), {"kind": "forecast"})()] * 2  # the last re-forecast: all
    assert f.plan()[1] == 20


def test_a_segment_plans_no_window_before_its_adoption():
    from minority.gns.follow import _Segment
    from minority.gns.oracle import OracleOptions

    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.0, 0.2, (200, 3))
    t = np.arange(60) * FRAME_S  # a flow over frames 5-35 of the segment
    v = np.clip(np.sin(np.pi * (t - 0.025) / 0.15), 0.0, None) * (t >= 0.025) * (t <= 0.175)
    x = x0[None] + np.cumsum(v * FRAME_S)[:, None, None] * np.array([1.0, 0.0, 0.0])
    at = {"failure_onset": 0.525, "runout_start": 0.55, "peak_motion": 0.6, "runout_end": 0.7}
    bounds = np.array([[0, 1.0]] * 3)
    whole = _Segment(x, FRAME_S, bounds, 0.01, OracleOptions(frames=30), 0.5, at, x0)
    late = _Segment(x, FRAME_S, bounds, 0.01, OracleOptions(frames=30), 0.5, at, x0, 0.62)
    assert min(w.t_start_s for v in whole.absolute(whole.spec()).views
               for w in v.schedule) < 0.55
    starts = [w.t_start_s for v in late.absolute(late.spec()).views for w in v.schedule]
    assert min(starts) == pytest.approx(0.62)  # the initiation is past: side follows runout


# --- the snapshots' coarse-graining -------------------------------------------------------------
def lattice(n: int, spacing: float) -> np.ndarray:
    g = (np.arange(n) + 0.5) * spacing
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def test_coarse_history_groups_as_the_training_data_in_any_particle_order():
    fine, coarse = 0.01, 0.02
    x0 = lattice(4, fine)
    rng = np.random.default_rng(1)
    frames = np.stack([x0 + k * rng.normal(0, 1e-3, x0.shape) for k in range(3)])
    snaps = []
    for k, x in enumerate(frames):
        order = rng.permutation(len(x0))  # ranks send them in any order
        snaps.append(Snapshot(k * FRAME_S, x[order], (x - x0)[order]))
    history, start = coarse_history(snaps, coarse)
    expected = coarse_grain(np.concatenate([x0[None], frames]), fine, 2)
    assert history.shape == (3, 8, 3)
    np.testing.assert_allclose(history, expected[1:], atol=1e-12)
    np.testing.assert_allclose(start, expected[0], atol=1e-12)
    with pytest.raises(ValueError, match="holds other particles"):
        coarse_history([snaps[0], Snapshot(0.01, frames[1][:10], (frames[1] - x0)[:10])], coarse)


# --- end to end on loopback ---------------------------------------------------------------------
@pytest.fixture
def daemon(server, tmp_path):
    d = RenderServer(server, ServerOptions(spec(), tmp_path / "frames", tmp_path / "run.mcap",
                                           timeout_s=30.0))
    yield d
    d.close()


def test_a_follower_reforecasts_from_snapshots_and_server_and_rank_follow(
        daemon, client_factory, endpoint):
    x0 = lattice(4, 0.01) + [0.3, 0.3, 0.0]  # 64 particles, 8 groups at the model's 0.02 m
    got: dict = {}

    def stub(model, stats, old, flow, snaps, scene, plan, check):
        from_s, frames = plan()
        got.update(snaps=snaps, frames=frames, from_s=from_s, now_s=flow.now_s)
        new = shifted(old, 0.0, {}, snapshots=[])
        return Spec.from_dict({**new.to_dict(), "events": [
            {"name": "runout_end", "time_s": 0.3, "tolerance_s": 0.03}]}), {"stub": True}

    follower = Follower(client_factory(), RUN, None, {"frame_interval_s": FRAME_S,
                                                      "particle_spacing_m": 0.02},
                        Scene(np.array([[0, 1.0]] * 3), 30.0, 100.0),  # long: a reserve is kept
                        FollowOptions(ranks=1, wait_s=5.0), log=io.StringIO(), forecast=stub)
    follower.fetch_spec()
    thread = threading.Thread(target=follower.run, kwargs={"timeout_s": 60.0})
    thread.start()
    viz = connect(RUN, connect=(endpoint,), wait_s=5.0, log=io.StringIO(), report=False)
    sent = {}
    try:
        x = x0.copy()
        for step in range(0, 200):
            t = (step + 1) * DT
            v = np.zeros_like(x) if t < 0.05 else np.tile([0.5, 0.0, 0.0], (len(x), 1))
            x = x + v * DT
            if viz.due(step, t):
                viz.publish(step, t, x, fields={"velocity": v, "displacement": x - x0},
                            spacing_m=0.01)
                if viz.spec.snapshot_due(t, t - DT):
                    sent[round(t, 6)] = x.copy()
            # every Stats sent (one per 5 ms) read by the follower, and its update taken by
            # the rank, before the run goes on: the run waits for the follower, not the
            # other way round (the sim's pace is not the test's)
            stats = int(t / 0.005 + 1e-6)
            assert wait_until(lambda n=stats: len(follower.flow.time_s) >= n)
            assert wait_until(lambda: not follower._wanted or viz.spec.snapshots)
            if follower.updates and follower.updates[-1].kind == "forecast":
                break
            if sent and len(sent) == 6:  # every snapshot sent: wait for the re-forecast
                assert wait_until(lambda: any(u.kind == "forecast" for u in follower.updates))
        final = follower.spec
        assert wait_until(lambda: daemon.spec_updates == 2 and viz.spec == final)
    finally:
        viz.close()
        follower.ended = True
        thread.join(timeout=30)
    kinds = [u.kind for u in follower.updates]
    assert kinds == ["shift", "forecast"]
    shift = follower.updates[0]
    assert shift.detail["departure"] == "early" and shift.detail["event"] == "failure_onset"
    assert daemon.spec == final and final.provenance["kind"] == "forecast"
    assert final.provenance["update"] == 2 and final.provenance["forecast_s"] >= 0.0
    assert not final.snapshots and [e.name for e in final.events] == ["runout_end"]
    snaps = got["snaps"]
    assert [s.time_s for s in snaps] == pytest.approx(sorted(sent))
    for s in snaps:  # every particle, as the rank had it at that step
        x_sent = sent[round(s.time_s, 6)]
        order = np.lexsort(s.positions.T)
        np.testing.assert_allclose(s.positions[order], x_sent[np.lexsort(x_sent.T)], atol=1e-6)
        start = s.positions - s.displacement  # the initial lattice, whatever the order
        np.testing.assert_allclose(start[np.lexsort(start.T)], x0[np.lexsort(x0.T)], atol=1e-6)
    # planned from when it will be adopted, within what the budget of 30 has left, a
    # reserve kept for the re-forecasts that may follow (3 at most)
    assert got["from_s"] >= got["now_s"] + 0.005
    left = follower.updates[-1].detail["frames_left"]
    assert 0 < left <= 30 and got["frames"] == left - round(0.25 * left)


def test_a_snapshot_keeps_the_servers_cache_of_the_outside(tmp_path):
    """At a snapshot step every particle travels, the ones outside the regions as context
    rows (the server's cache refreshed, not evicted): the next step resends nothing of the
    outside that did not move."""
    import json

    from minority.demo import free_port
    from minority.protocol.log import read_log
    from minority.protocol.messages import Chunk

    d = spec(snapshots=[0.0025]).to_dict()
    d["views"][0]["schedule"] = [{"every_steps": 1, "regions": ["a"]}]
    d["regions"] = [{"name": "a", "lo_m": [0, 0, 0], "hi_m": [0.5, 1, 1]}]
    (tmp_path / "spec.json").write_text(json.dumps(d))
    x0 = np.r_[lattice(2, 0.1), lattice(2, 0.1) + [0.6, 0.0, 0.0]]  # 8 inside, 8 outside
    viz = connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",), spec=tmp_path / "spec.json",
                  record=tmp_path / "rec.mcap", log=io.StringIO(), report=False)
    for step in range(6):
        x = x0 + np.array([[0.01 * step, 0, 0]] * 8 + [[0, 0, 0]] * 8)  # the outside rests
        if viz.due(step, (step + 1) * DT):
            viz.publish(step, (step + 1) * DT, x, fields={"displacement": x - x0},
                        spacing_m=0.05)
        viz.wait_sent(10.0)  # every step sent: none refused by a full outbox
    viz.close()
    chunks = {c.step: c for c in (r.decode() for r in read_log(tmp_path / "rec.mcap"))
              if isinstance(c, Chunk)}
    outside = np.arange(8, 16)
    assert sorted(chunks[0].context_ids) == outside.tolist()  # sent once
    snap = chunks[2]  # t 0.003: the snapshot at 0.0025
    assert snap.count == 16 and sorted(snap.context_ids) == outside.tolist()
    assert not len(snap.evict_ids) and not snap.context_reset
    np.testing.assert_allclose(np.sort(snap.positions[:, 0]),
                               np.sort(np.r_[x0[:8, 0] + 0.02, x0[8:, 0]]), atol=1e-6)
    for k in (1, 3, 4):  # the outside rests: nothing of it resent, nothing evicted
        assert chunks[k].count == 8 and not len(chunks[k].context_ids)
        assert not len(chunks[k].evict_ids)


@pytest.mark.parametrize(("frames", "slowing"), [(12, False), (5, False), (12, True)])
def test_a_reforecast_with_the_shipped_model_plans_from_its_adoption(frames, slowing):
    """The real re-forecast on a small column (the shipped checkpoint, 128 particles at its
    spacing): rolled to rest, planned from plan()'s time within its frames (none when under
    2 a view are left), a spec that encodes (its provenance plain JSON)."""
    from minority.demo import CHECKPOINT
    from minority.gns.follow import reforecast
    from minority.gns.train import load_checkpoint

    model, ckpt = load_checkpoint(CHECKPOINT)
    stats = ckpt["stats"]
    h, dt = float(stats["particle_spacing_m"]), float(stats["frame_interval_s"])
    g = (np.arange(4) + 0.5) * h
    x0 = np.stack(np.meshgrid(g, g, (np.arange(8) + 0.5) * h, indexing="ij"),
                  -1).reshape(-1, 3)
    t0 = 0.05
    snaps = [Snapshot(t0 + k * dt, x0 + [0.02 * k * dt, 0, -0.01 * k * dt],
                      np.tile([0.02 * k * dt, 0, -0.01 * k * dt], (len(x0), 1)))
             for k in range(6)]
    # the run steady, or slowing down to a tenth of its peak speed
    flow = flow_of(lambda t: 0.02 if not slowing or t < 0.02 else 0.002, t0 + 5 * dt, ranks=1)
    asked = []

    def plan():
        asked.append(flow.now_s)
        return t0 + 0.04, frames

    new, info = reforecast(model, stats, spec(), flow, snaps,
                           Scene(np.array([[0, 0.4], [0, 0.04], [0, 0.2]]), 30.0, 0.4), plan)
    assert asked and info["from_s"] == pytest.approx(t0 + 0.04) and info["particles"] == 128
    assert 0 < info["rolled_frames"] <= info["rollout_frames"]
    assert 0 < info["rollout_s"] <= info["forecast_s"]
    assert Spec.from_dict(new.to_dict()) == new and new.encode()
    windows = [w for v in new.views for w in v.schedule]
    # events only when the budget is spent, or the fast phase over by the adoption (the
    # forecast's) while the run slowed down (a steady run is not over, whatever the GNS says)
    over = slowing and info["fast_end_s"] <= t0 + 0.04
    assert (not info["frames_planned"]) == (frames < 6 or over)
    if info["frames_planned"]:  # planned from its adoption on
        assert 6 <= info["frames_planned"] <= 12
        assert min(w.t_start_s for w in windows) >= t0 + 0.04 - 1e-9
    else:  # at rest by then: nothing planned after it
        assert max(w.t_end_s for w in windows) <= t0 + 0.04 + 1e-9
    assert new.provenance["forecast"]["from_s"] == pytest.approx(t0 + 0.04)
    assert {e.name for e in new.events} == {"failure_onset", "runout_start", "peak_motion",
                                            "runout_end"}


def test_a_regions_departure_widens_the_regions_in_use_within_the_domain():
    from minority.gns.follow import widened

    s = Spec.from_dict({**spec().to_dict(), "regions": [
        {"name": "a", "lo_m": [0.2, 0.2, 0.0], "hi_m": [0.4, 0.6, 0.2]}]})
    w = widened(s, 0.3, np.array([[0.0, 1.0], [0.0, 0.65], [0.0, 1.0]]))
    r = w.region("a")
    np.testing.assert_allclose(r.lo_m, [0.15, 0.1, 0.0])  # the floor is the domain's
    np.testing.assert_allclose(r.hi_m, [0.5, 0.65, 0.25])  # ahead along x: twice as far
    assert widened(s, 0.5, np.array([[0, 1.0]] * 3)).region("a") == s.region("a")  # past


def test_without_future_ends_every_window_at_the_adoption():
    from minority.gns.follow import without_future

    d = without_future(spec(snapshots=[0.3]), 0.25)
    assert d["views"][0]["schedule"][0]["t_end_s"] == 0.25 and not d.get("snapshots")
    gone = without_future(spec(), 0.1)["views"][0]["schedule"]  # the window starts later
    assert [(w["t_start_s"], w["t_end_s"]) for w in gone] == [(0.0, 0.0)]


def standing_spec() -> Spec:
    """spec() as the oracle writes a prediction with no flow: each view at the start and
    the end of a 1 s run."""
    d = spec().to_dict()
    d["views"][0]["schedule"] = [{"t_start_s": 0.0, "t_end_s": 1.0, "every_s": 1.0,
                                  "regions": ["a"]}]
    d["provenance"] = {"predicted": {"standing": True}}
    return Spec.from_dict(d)


def test_a_standing_spec_cut_short_keeps_its_picture_of_the_end():
    from minority.gns.follow import without_future

    cut = Spec.from_dict(without_future(standing_spec(), 0.09))
    windows = [(w.t_start_s, w.t_end_s) for w in cut.views[0].schedule]
    assert windows == [(0.0, 0.09), (1.0, 1.0)]
    due = [t for t in np.arange(0.0, 1.0001, 0.005)
           if cut.wants(round(t / 0.005), t, t - 0.005 if t > 0 else None)]
    assert due == pytest.approx([0.0, 1.0])  # the start, and the end
    # a spec of a predicted flow is cut at the adoption, as before
    flowing = {**standing_spec().to_dict(), "provenance": {}}
    cut = Spec.from_dict(without_future(Spec.from_dict(flowing), 0.09))
    assert [(w.t_start_s, w.t_end_s) for w in cut.views[0].schedule] == [(0.0, 0.09)]


def test_a_departure_while_the_gns_rolls_abandons_the_stale_forecast():
    """Stats queued while the forecast runs are read between its rollout chunks: an early
    onset there abandons it for the new departure's shift and snapshots."""
    stats = {"frame_interval_s": FRAME_S, "particle_spacing_m": 0.02}
    rolled = []

    def slow(model, stats_, old, flow, snaps, scene, plan, check):
        for chunk in range(5):  # what roll_to_rest does between its chunks
            rolled.append(chunk)
            check()
        raise AssertionError("the departure was not seen")

    session = _Session()
    f = Follower(session, RUN, None, stats, Scene(np.array([[0, 1.0]] * 3), 30.0, 1.0),
                 FollowOptions(ranks=2), log=io.StringIO(), forecast=slow)
    f._adopt(spec())
    run = collapse(0.1, 0.5)  # the onset predicted at 0.2 s comes at 0.1 s
    for step in range(0, 131, 5):
        for rank in range(2):
            f._q.put(("stats", stats_at(step, np.full(100, run(step * DT)), rank=rank).encode(),
                      10.0 + step * 0.01))
    f._pending = None
    f._forecast([])
    assert rolled == [0]  # abandoned at the first chunk's end
    assert f.flow.now_s == pytest.approx(0.13)  # caught up
    shift = f.updates[-1]
    assert shift.kind == "shift" and shift.detail["event"] == "failure_onset"
    assert f._wanted and f._wanted[0] > 0.13 and session.puts
    assert "abandoned" in f.log.getvalue()


# --- a run past what the model learnt (friction_45: a column that creeps, then fails) ----------
def creep_then_fail(t: float) -> float:
    """Speed (m/s): a first settling (0.1 m/s at 0.02 s, at rest by 0.07 s), then a creep
    from 0.2 s growing tenfold every 0.2 s: faster than the settling from 0.54 s on."""
    first = 0.1 * max(0.0, 1.0 - abs(t - 0.02) / 0.05)
    return first + (0.002 * 10 ** ((t - 0.2) / 0.2) if t >= 0.2 else 0.0) + 1e-4


def rollout_of(speed_of_t, t0_s: float, end_s: float, n: int = 27) -> np.ndarray:
    """[frames, n, 3] (m): n particles of a 0.1 m block all moving along x at speed_of_t(t)
    (m/s), one frame every FRAME_S from t0_s to end_s."""
    t = t0_s + np.arange(round((end_s - t0_s) / FRAME_S) + 1) * FRAME_S
    x = np.cumsum([speed_of_t(s) * FRAME_S for s in t])
    return lattice(3, 0.05)[None] + x[:, None, None] * np.array([1.0, 0.0, 0.0])


def test_a_run_speeding_up_past_a_rollout_at_rest_is_joined_to_its_own_trend():
    from minority.gns.follow import joined_events

    flow = flow_of(creep_then_fail, 0.6)
    t0 = 0.6 - 5 * FRAME_S
    rests = rollout_of(lambda t: creep_then_fail(t) if t <= 0.6 else 1e-4, t0, 0.7)
    at, _, fast_end, _, trend = joined_events(flow, t0, FRAME_S, rests, 6)
    # tenfold in 0.2 s to the run's end: the peak at the end, the runout from half of it on
    half = 0.6 + 0.2 * np.log10(0.5 * creep_then_fail(0.7) / creep_then_fail(0.6))
    assert trend and at["peak_motion"] == pytest.approx(0.7) and fast_end == pytest.approx(0.7)
    # (the rate read through the Stats' speed histogram: its bins are 26 % apart)
    assert at["runout_start"] == pytest.approx(half, abs=3 * FRAME_S)
    assert at["runout_end"] == pytest.approx(0.7) and at["failure_onset"] < 0.02
    # a longer run: at most the free fall from the block's top (0.1 m: 1.4 m/s, by 0.74 s)
    at, _, fast_end, _, trend = joined_events(flow, t0, FRAME_S, rollout_of(
        lambda t: creep_then_fail(t) if t <= 0.6 else 1e-4, t0, 0.9), 6)
    assert trend and 0.7 < at["peak_motion"] < 0.75 and fast_end == pytest.approx(0.9)
    # a rollout that goes on speeding up is believed: its peak, then its rest
    fails = rollout_of(lambda t: creep_then_fail(min(t, 0.7)) if t <= 0.72 else 1e-4, t0, 0.75)
    at, _, _, _, trend = joined_events(flow, t0, FRAME_S, fails, 6)
    assert not trend and at["runout_end"] < 0.75
    assert at["peak_motion"] == pytest.approx(0.7, abs=2 * FRAME_S)
    # a run slowing at the join is joined to the rollout as before (its settling at 0.02 s)
    early = flow_of(creep_then_fail, 0.04)
    at, _, _, _, trend = joined_events(early, 0.015, FRAME_S,
                                       rollout_of(creep_then_fail, 0.015, 0.75), 6)
    assert not trend and at["peak_motion"] < 0.05


def accelerating_creep(t: float) -> float:
    """Speed (m/s): a creep from 0.2 s whose growth rate grows with time (log speed
    quadratic from 0.4 s: 6/s at 0.5 s, 12/s at 0.6 s, 18/s at 0.7 s), as a failing column's."""
    grow = 0.002 * np.exp(30 * (t - 0.4) ** 2) if t >= 0.4 else 0.002 * (t >= 0.2)
    return 1e-4 + grow


def test_the_trend_is_read_from_the_newest_stats_when_the_run_is_still_speeding_up():
    from minority.gns.follow import joined_events

    t0 = 0.6 - 5 * FRAME_S  # snapshots to 0.6 s; the forecast planned at 0.65 s
    rests = rollout_of(lambda t: accelerating_creep(t) if t <= 0.6 else 1e-4, t0, 0.75)
    ts = np.arange(0.6, 0.75, 0.001)
    half = ts[np.argmax([accelerating_creep(x) >= 0.5 * accelerating_creep(0.75) for x in ts])]
    at_join = joined_events(flow_of(accelerating_creep, 0.6), t0, FRAME_S, rests, 6).at
    at_newest, *_, trend = joined_events(flow_of(accelerating_creep, 0.65), t0, FRAME_S, rests, 6)
    assert trend and at_newest["peak_motion"] == pytest.approx(0.75)
    # the growth at the join (12/s) puts the runout start 6 frames early; at 0.65 s, 15/s
    assert at_join["runout_start"] < half - 5 * FRAME_S
    assert at_newest["runout_start"] == pytest.approx(half, abs=2 * FRAME_S)


def test_an_event_missed_again_after_a_reforecast_is_a_new_departure():
    late = flow_of(collapse(0.19, 0.7), 0.58)
    det = Detector()
    assert det.check(spec(), late).event == "runout_end"
    assert det.check(spec(), late) is None  # acted on once per prediction
    moved = Spec.from_dict({**spec().to_dict(), "events": [
        {"name": "runout_end", "time_s": 0.52, "tolerance_s": 0.052}]})
    assert det.check(moved, late) is None
    det.new_prediction()  # a re-forecast put runout_end at 0.52 s: missed again at 0.58 s
    d = det.check(moved, late)
    assert d.kind == "late" and d.event == "runout_end"


def follower_at(speeds_of_t, until_s: float, duration_s: float = 1.0):
    """A Follower (no network) of spec() that has read Stats of a run whose 100 particles
    move at speeds_of_t(t) ([100] m/s) until until_s, 5 ms of run per 0.25 s of wall
    (0.02 s/s)."""
    f = Follower(_Session(), RUN, None, {"frame_interval_s": FRAME_S,
                                         "particle_spacing_m": 0.02},
                 Scene(np.array([[0, 1.0]] * 3), 30.0, duration_s),
                 FollowOptions(ranks=1), log=io.StringIO())
    f._adopt(spec())
    for step in range(0, round(until_s / DT) + 1, 5):
        f.flow.add(stats_at(step, speeds_of_t(step * DT)), wall_s=0.05 * step)
    return f


def settle_then_creep(t: float) -> np.ndarray:
    """[100] speeds (m/s): 10 particles settling (0.1 m/s at 0.02 s, at rest by 0.07 s),
    then all creeping from 0.2 s, 0.04 m/s at 0.45 s: more kinetic energy than the
    settling's from 0.35 s on, a speed scale under half of its."""
    v = np.full(100, 1e-4 + (0.16 * (t - 0.2) if t >= 0.2 else 0.0))
    v[:10] += 0.1 * max(0.0, 1.0 - abs(t - 0.02) / 0.05)
    return v


def uniform(speed_of_t):
    return lambda t: np.full(100, speed_of_t(t))


def test_a_late_event_while_the_run_is_slow_holds_the_frames_for_the_reforecast():
    from minority.gns.follow import Departure

    late_peak = Departure("late", "peak_motion", 0.45, 0.15, "no peak_motion yet")
    f = follower_at(settle_then_creep, 0.45)  # speeding up again, slow
    assert f.lands_s(0.45) == pytest.approx(0.45 + 0.035 + 0.02 * 5.0 + 0.005)
    f._request_snapshots(late_peak)
    shift = f.updates[-1]
    assert shift.kind == "shift" and shift.detail["hold"]
    windows = [w for v in f.spec.views for w in v.schedule]
    assert max(w.t_end_s for w in windows) <= 0.45 + 1e-9  # no frame until the forecast
    assert f.spec.snapshots == f._wanted and len(f._wanted) == 6
    # in its fast phase, or with no time left for a re-forecast: the moved timeline renders
    fast = follower_at(uniform(collapse(0.2, 0.8)), 0.45)
    fast._request_snapshots(late_peak)
    assert not fast.updates[-1].detail["hold"]
    assert max(w.t_end_s for v in fast.spec.views for w in v.schedule) > 0.45
    short = follower_at(settle_then_creep, 0.45, duration_s=0.55)
    short._request_snapshots(late_peak)
    assert not short.updates[-1].detail["hold"]
    # past its fast phase (slowing to rest), any departure holds
    done = follower_at(uniform(collapse(0.1, 0.3)), 0.28)
    done._request_snapshots(Departure("regions", None, 0.28, 0.0, "outside"))
    assert done.updates[-1].detail["hold"]


def test_the_windows_end_once_when_the_fast_phase_is_over():
    f = follower_at(uniform(collapse(0.1, 0.3)), 0.22)  # past the peak, still fast
    f._end_after_fast_phase()
    assert not f.updates
    for step in (225, 230, 235, 240, 245, 250, 255, 260, 265, 270, 275, 280):
        f.flow.add(stats_at(step, uniform(collapse(0.1, 0.3))(step * DT)), wall_s=0.05 * step)
    f._end_after_fast_phase()  # 0.275 and 0.28 s under half the peak speed
    end = f.updates[-1]
    assert end.kind == "end" and "fast phase over at 0.280 s" in end.reason
    assert f.spec.provenance["kind"] == "end" and f.spec.provenance["update"] == 1
    assert max(w.t_end_s for v in f.spec.views for w in v.schedule) == pytest.approx(0.28)
    f._end_after_fast_phase()
    assert len(f.updates) == 1  # once
    # a standing spec's frames ahead are its picture of the end: no end update
    still = follower_at(uniform(collapse(0.1, 0.3)), 0.28)
    still._adopt(standing_spec())
    still._end_after_fast_phase()
    assert not still.updates


@pytest.mark.parametrize("early", [False, True])
def test_a_late_event_while_the_gns_rolls_leaves_the_forecast_to_land(early):
    """A late event seen between the rollout's chunks says the shift's guess was wrong,
    which the forecast in flight replaces; an event early, seen once the peak is known,
    that happened before its snapshots is in the Stats it joins: it is not abandoned."""
    from minority.gns.follow import Departure

    stats = {"frame_interval_s": FRAME_S, "particle_spacing_m": 0.02}

    seen = []

    def rolls(model, stats_, old, flow, snaps, scene, plan, check):
        for _ in range(3):
            check()
        seen.extend(f.detector.acted)  # the departure, seen between the chunks
        return Spec.from_dict({**old.to_dict(), "snapshots": []}), {"plan_s": 0.1}

    f = Follower(_Session(), RUN, None, stats, Scene(np.array([[0, 1.0]] * 3), 30.0, 1.0),
                 FollowOptions(ranks=2), log=io.StringIO(), forecast=rolls)
    # the flow still moving at the predicted rest (0.5 s), or its runout start at 0.2 s
    # read once the kinetic energy has fallen from its peak (0.25 s) 10 %
    f._adopt(spec() if not early else Spec.from_dict({**spec().to_dict(), "events": [
        {"name": "failure_onset", "time_s": 0.02, "tolerance_s": 0.005},
        {"name": "runout_start", "time_s": 0.23, "tolerance_s": 0.005}]}))
    run = collapse(0.19, 0.7) if not early else collapse(0.02, 0.48)
    for step in range(0, 581 if not early else 291, 5):
        for rank in range(2):
            f._q.put(("stats", stats_at(step, np.full(100, run(step * DT)), rank=rank).encode(),
                      10.0 + step * 0.01))
    f._pending = Departure("regions", None, 0.1, 0.0, "outside")
    f._forecast([Snapshot(0.2, np.zeros((1, 3)), np.zeros((1, 3)))])
    assert [u.kind for u in f.updates] == ["forecast"] and "abandoned" not in f.log.getvalue()
    assert f.flow.now_s == pytest.approx(0.58 if not early else 0.29)  # caught up
    assert seen == [("early", "runout_start") if early else ("late", "runout_end")]


def test_a_segment_spends_its_frames_where_the_joined_series_is_fast():
    """A rollout at rest joined to a run speeding up: the frames follow the joined speed
    scale (speed^4), most of them at the end, not evenly as the resting rollout would."""
    from minority.gns.follow import _Segment
    from minority.gns.oracle import OracleOptions

    x0 = lattice(4, 0.05)
    rest = np.repeat(x0[None], 41, axis=0)  # 0.2 s of a rollout that does not move
    t = np.arange(41) * FRAME_S
    growing = 0.01 * np.exp(15.0 * t)  # m/s, 20-fold over the 0.2 s
    at = {"failure_onset": 0.01, "runout_start": 0.55, "peak_motion": 0.7, "runout_end": 0.7}
    seg = _Segment(rest, FRAME_S, np.array([[0, 1.0]] * 3), 0.05, OracleOptions(frames=60),
                   0.5, at, x0, 0.5, speed_scale_m_s=growing)
    top = {v.name: v for v in seg.absolute(seg.spec()).views}["top"]
    cadence = [(w.t_start_s, w.every_s) for w in top.schedule]
    assert cadence[-1][0] > 0.6 and cadence[-1][1] < cadence[0][1] / 3  # denser at the end


def test_a_rollout_the_trend_replaces_stops_after_its_first_chunk():
    from minority.demo import CHECKPOINT
    from minority.gns.follow import roll_to_rest
    from minority.gns.train import load_checkpoint

    model, ckpt = load_checkpoint(CHECKPOINT)
    h = float(ckpt["stats"]["particle_spacing_m"])
    x0 = lattice(4, h)
    history = np.repeat(x0[None], int(model.config.input_velocities) + 1, axis=0)
    seen = []
    out, rolled = roll_to_rest(model, history, 30.0, np.array([[0, 0.4], [0, 0.2], [0, 0.2]]),
                               60, 1.0, chunk=10,
                               enough=lambda so_far: seen.append(len(so_far)) or True)
    c1 = len(history)
    assert seen == [c1 + 10] and rolled == 10 and out.shape == (c1 + 60, len(x0), 3)
    assert (out[c1 + 10:] == out[c1 + 9]).all()  # the rest at its last frame
