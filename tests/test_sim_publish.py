"""What a rank publishes: only the particles inside the spec's regions, only the requested
fields, every `decimate`-th particle by id, at the scheduled steps (`every_s` cadences from
the previous step's time, which the chunk carries); Stats on their own cadence; the render
server renders the culled chunks; without a server, or with a subscriber that never reads,
the run finishes with every drop counted.
Network tests: loopback, a free port each, waits on counts with timeouts."""

import contextlib
import dataclasses
import io
import json
import math
import re
import threading
import time
import warnings
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh
from conftest import fail_call, free_port
from test_loopback import wait_until

from minority.insitu.outbox import CONTROL, STATS, Outbox, OutboxItem
from minority.insitu.payload import cull, flow_stats, particle_bytes, speed_bins
from minority.insitu.publisher import PublishOptions, record_path
from minority.protocol import Chunk, Event, EventKind, Spec, Stats, decode_as, keys
from minority.protocol.log import read_log
from minority.protocol.messages import SPEED_BINS, SPEED_EDGES_M_S, speed_histogram
from minority.protocol.session import Inbox, NetworkOptions, Role, open_session
from minority.protocol.spec import DataRequest, Region
from minority.protocol.view import Window
from minority.protocol.wire import decode
from minority.render_server.daemon import RenderServer, ServerOptions
from minority.sim.driver import Simulator
from minority.sim.publish import SIM_FIELDS, sim_particles
from minority.sim.ranks import RankRunConfig, run_ranks
from minority.sim.scene import builtin_scene_path, load_scene
from minority.sim.state import PARTICLE_FIELDS, seed_particles

RUN = "test-run"
TINY = builtin_scene_path("tiny")  # 0.1 m column at x in [0, 0.1] m
FRONT = {"name": "front", "lo_m": [0.05, -1.0, -1.0], "hi_m": [1.0, 1.0, 1.0]}
FRONT_BOX = Region("front", (0.05, -1.0, -1.0), (1.0, 1.0, 1.0))
CAMERA = {"position": [0.2, -1.0, 0.08], "focal_point": [0.2, 0.02, 0.08]}


def spec_dict(every_steps: int = 20, regions: bool = True, field: str = "displacement") -> dict:
    view = {"name": "side", "camera": {"position": [0.2, -1.0, 0.08],
                                       "focal_point": [0.2, 0.02, 0.08]},
            "width": 64, "height": 48, "field": field, "range": [0.0, 0.1],
            "every_steps": every_steps}
    d = {"version": 1, "run": RUN, "views": [view]}
    if regions:
        d["regions"] = [FRONT]
        view["regions"] = ["front"]
    return d


def moved_particles():
    ps = seed_particles(load_scene(TINY))
    rng = np.random.default_rng(0)
    ps.x += rng.normal(0.0, 0.003, ps.x.shape)
    ps.v[:] = rng.normal(0.0, 0.5, ps.v.shape)
    return ps


def test_cull_keeps_the_particles_in_the_regions_and_the_requested_fields_only():
    ps = moved_particles()
    box = Region("front", (0.05, -1.0, -1.0), (1.0, 1.0, 1.0))
    fields = cull(sim_particles(ps), DataRequest(("side",), ("displacement", "velocity_magnitude"), (box,)))
    assert list(fields) == ["positions", "displacement", "velocity_magnitude"]
    expected = np.flatnonzero(ps.x[:, 0] >= 0.05)
    assert 0 < expected.size < ps.n
    assert np.array_equal(fields["positions"], ps.x[expected].astype(np.float32))
    assert np.array_equal(fields["displacement"], (ps.x - ps.x0)[expected].astype(np.float32))
    np.testing.assert_allclose(fields["velocity_magnitude"],
                               np.linalg.norm(ps.v[expected], axis=1), rtol=1e-6)
    everything = cull(sim_particles(ps), DataRequest(("side",), ("id", "pressure"), None))
    assert np.array_equal(everything["id"], ps.pid) and everything["pressure"].shape == (ps.n,)
    assert set(cull(sim_particles(ps), DataRequest(("v",), ("no_such_field",), None))) == {"positions"}


def test_culling_reduces_the_bytes_as_predicted():
    """Predicted: particles inside the regions x bytes per particle of the requested fields;
    the rest of a payload is its header and padding (under a kilobyte)."""
    ps = moved_particles()
    box = Region("front", (0.05, -1.0, -1.0), (1.0, 1.0, 1.0))
    m = int((ps.x[:, 0] >= 0.05).sum())

    def encoded(request):
        payload = Chunk(RUN, 0, 0.0, 0, 1, 0.005, ((0, 0, 0), (1, 1, 1)),
                        cull(sim_particles(ps), request)).encode()
        return len(payload), sum(a.nbytes for a in decode(payload).arrays.values())

    full, full_arrays = encoded(DataRequest(("v",), ("displacement", "velocity"), None))
    culled, culled_arrays = encoded(DataRequest(("v",), ("displacement",), (box,)))
    assert particle_bytes(["displacement", "velocity"]) == 36
    assert particle_bytes(["displacement"]) == 24
    assert full_arrays == ps.n * 36 and culled_arrays == m * 24
    assert 0 < full - full_arrays < 1024 and 0 < culled - culled_arrays < 1024
    assert culled_arrays / full_arrays == pytest.approx(m * 24 / (ps.n * 36))
    assert culled < 0.4 * full


def test_record_path_per_rank():
    assert record_path(Path("a/run.mcap"), 0) == Path("a/run.mcap")
    assert record_path(Path("a/run.mcap"), 2) == Path("a/run.rank2.mcap")


def reference_positions(steps: list[int]) -> dict[int, np.ndarray]:
    """Positions (float32) of the single-process run at the given steps, as a rank steps
    (the CFL step of the first output interval, 0.02 s)."""
    sim = Simulator(load_scene(TINY))
    out = {}
    for step in steps:
        sim.advance_to(0.02, max_steps=step - sim.step_count)
        out[step] = sim.particles.x.astype(np.float32)
    return out


def sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


def config(endpoint: str, tmp_path: Path, max_steps: int, **publish) -> RankRunConfig:
    return RankRunConfig(scene_path=TINY, out=tmp_path / "out.h5", progress=False, run=RUN,
                         max_steps=max_steps,
                         publish=PublishOptions(network=NetworkOptions(connect=[endpoint]),
                                                **publish))


def test_rank_fetches_the_spec_and_the_server_renders_culled_chunks(server, client_factory,
                                                                     endpoint, tmp_path):
    spec = Spec.from_dict(spec_dict())
    daemon = RenderServer(server, ServerOptions(spec, tmp_path / "frames", None, timeout_s=30.0,
                                                write_png=False))
    observer = client_factory()
    chunks, events = Inbox(observer, keys.chunks(RUN)), Inbox(observer, keys.event(RUN))
    tokens = []
    watch = server.liveliness().declare_subscriber(keys.rank_tokens(RUN),
                                                   lambda s: tokens.append(s.kind), history=True)
    try:
        log = io.StringIO()
        # the regions alone (context rows, sent again as the tiny scene's particles all fall,
        # are tests/test_particle_cache.py's)
        summary = run_ranks(config(endpoint, tmp_path, 40, context=False), stream=log)
        assert summary.spec_version == 2 and summary.run == RUN
        p = summary.publish
        assert (p["scheduled"], p["sent"], p["dropped"]) == (3, 3, 0)  # steps 0, 20, 40
        # the rank's start and done, then the server's end of the run
        assert wait_until(lambda: chunks.received == 3 and events.received == 3)
        # the server renders the newest complete step (older ones may be skipped)
        assert wait_until(lambda: daemon.summary()["steps_rendered"]
                          + daemon.summary()["steps_skipped"] == 3)
        assert daemon.stats.frames >= 1 and daemon.stats.view_errors == 0
        assert daemon.summary()["timed_out"] == 0  # every step complete: no rank missing
        got = {c.step: c for c in (decode_as(chunks.get(1).payload, Chunk) for _ in range(3))}
        for step, x in reference_positions([20, 40]).items():
            c = got[step]
            assert set(c.fields) == {"positions", "displacement"}  # nothing else
            inside = x[x[:, 0] >= np.float32(0.05)]
            assert 0 < c.count == len(inside) < 400 and c.context_ids is None
            assert np.array_equal(sorted_rows(c.positions), sorted_rows(inside))
        assert p["particles_sent"] == sum(c.count for c in got.values()) < p["particles_total"]
        assert p["bytes_sent"] == sum(len(c.encode()) for c in got.values())
        start, done, end = (decode_as(events.get(1).payload, Event) for _ in range(3))
        assert end.kind == EventKind.RUN_END and end.rank == -1
        assert end.detail["chunks"] == 3 and end.detail["lost_in_transit"] == 0
        assert start.kind == EventKind.RUN_START and start.detail["spec_version"] == 2
        assert start.detail["scene"] == "tiny" and start.detail["ranks"] == 1
        assert done.kind == EventKind.RANK_DONE and done.rank == 0
        assert done.detail["sent"] == 3 and done.detail["dropped"] == 0
        assert wait_until(lambda: tokens == [zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE])
        assert "spec version 2" in log.getvalue()
    finally:
        watch.undeclare()
        daemon.close()


def test_without_a_server_the_run_goes_on_and_counts_every_drop(tmp_path):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict(every_steps=10)))
    log = io.StringIO()
    cfg = config(f"tcp/127.0.0.1:{free_port()}", tmp_path, 100, spec_file=spec_file,
                 record=tmp_path / "sim.mcap")
    summary = run_ranks(cfg, stream=log)
    assert summary.steps == 100
    p = summary.publish
    assert p["scheduled"] == 11 and p["sent"] == 0  # steps 0, 10, ..., 100
    assert p["dropped"] == p["dropped_no_server"] == 11
    assert log.getvalue().count("this run is NOT published") == 1  # said once, for all ranks
    assert summary.not_published.startswith("not connecting: tcp/127.0.0.1:")
    assert "no password file" in summary.not_published  # no server ever started there
    # ... and the record keeps what would have been sent: spec, chunks, events
    topics = [r.topic for r in read_log(tmp_path / "sim.mcap")]
    assert topics.count(f"minority/{RUN}/chunk") == 11 and topics[0] == f"minority/{RUN}/spec"
    assert topics.count(f"minority/{RUN}/event") == 2  # run start, rank done
    assert topics.count(f"minority/{RUN}/stats") == p["stats_due"] == p["stats_dropped"] > 0


SIM_SIDE_CONFIG = """{
  mode: "client",
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },
  transport: {
    shared_memory: { enabled: false },
    link: { tcp: { so_sndbuf: 65536 },
            tx: { queue: { congestion_control: { block: { wait_before_close: 500000 } } } } },
  },
}
"""


@contextlib.contextmanager
def stalled_server(endpoint: str, tmp_path: Path, spec: Spec):
    """A server that answers the spec but whose chunk callback never returns (until the
    block ends): zenoh stops reading the link (small socket buffers, no shared memory on
    the rank's side: tmp_path/client.json5). Yields the list the callback appends to."""
    server_cfg = tmp_path / "server.json5"
    server_cfg.write_text('{ mode: "peer", scouting: { multicast: { enabled: false } }, '
                          'transport: { link: { tcp: { so_rcvbuf: 65536 } } } }')
    (tmp_path / "client.json5").write_text(SIM_SIDE_CONFIG)
    server = open_session(NetworkOptions(listen=[endpoint], config=server_cfg), Role.SERVER)
    gate, arrived = threading.Event(), []

    def never_return(sample):
        arrived.append(1)
        gate.wait()

    run = spec.run
    queryable = server.declare_queryable(keys.spec(run), lambda q: q.reply(
        keys.spec(run), bytes(spec.encode())))
    stuck = server.declare_subscriber(keys.chunks(run), never_return)
    try:
        yield arrived
    finally:
        gate.set()
        stuck.undeclare()
        queryable.undeclare()
        server.close()


def test_a_subscriber_that_never_reads_costs_counted_drops_not_time(endpoint, tmp_path):
    """A server whose chunk callback blocks forever: zenoh stops reading the link, the
    rank's puts block, the sender stalls, and the simulation runs on to the end."""
    spec = Spec.from_dict(spec_dict(every_steps=1, regions=False))
    with stalled_server(endpoint, tmp_path, spec) as arrived:
        cfg = config(endpoint, tmp_path, 300, drain_timeout_s=2.0)
        cfg.publish.network.config = tmp_path / "client.json5"
        cfg.scene_path = tmp_path / "slide.toml"  # 3,200 particles: 77 kB per chunk
        from test_sim_mpi import SLIDE_TOML

        cfg.scene_path.write_text(SLIDE_TOML)
        log = io.StringIO()
        summary = run_ranks(cfg, stream=log)
        p = summary.publish
        assert summary.steps == 300 and p["scheduled"] == 301
        assert summary.wall_s < 60  # not a speed check: a blocked sim would never get here
        assert p["stalls"] >= 1 and p["dropped"] > 0
        assert p["sent"] + p["dropped"] == p["scheduled"]  # every chunk accounted for
        assert "the server stopped reading" in log.getvalue()
        assert len(arrived) == 1  # the one chunk the callback holds


def wait_for_subscriber(server, key: str) -> None:
    """Until the server (the router) knows a subscriber of `key` (a client's declaration has
    crossed the link), so a rank that connects next sees it."""
    probe = server.declare_publisher(key)
    try:
        assert wait_until(lambda: probe.matching_status.matching)
    finally:
        probe.undeclare()


def test_chunks_nobody_subscribes_to_count_as_dropped_not_sent(server, client_factory,
                                                               endpoint, tmp_path):
    """A server listens but nothing subscribes to the run's chunks or stats (no render server,
    no recorder): zenoh would take the puts without an error and deliver them nowhere. They
    are not put; they count as dropped (no subscriber), not sent, in the rank's rank_done."""
    observer = client_factory()
    events = Inbox(observer, keys.event(RUN))  # not a chunk or stats subscriber
    wait_for_subscriber(server, keys.event(RUN))
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict(every_steps=10)))
    summary = run_ranks(config(endpoint, tmp_path, 100, spec_file=spec_file),
                        stream=io.StringIO())
    p = summary.publish
    assert p["scheduled"] == 11  # steps 0, 10, ..., 100
    assert p["sent"] == p["sent_confirmed"] == p["bytes_sent"] == p["particles_sent"] == 0
    assert p["dropped"] == p["dropped_no_subscriber"] == 11
    assert p["stats_due"] == p["stats_dropped"] > 0 and p["stats_sent"] == 0
    assert wait_until(lambda: events.received == 2)
    start, done = (decode_as(events.get(1).payload, Event) for _ in range(2))
    assert (start.kind, done.kind) == (EventKind.RUN_START, EventKind.RANK_DONE)
    assert done.detail["sent"] == 0
    assert done.detail["dropped"] == done.detail["dropped_no_subscriber"] == 11


def test_chunks_put_since_the_last_confirmation_count_as_dropped_when_a_stall_comes(
        server, client_factory, endpoint, monkeypatch):
    """A staged stall, clock and put injected (no waiting for zenoh's block timeout): step 0
    is put and confirmed (the server answers a checkpoint); then the server stops answering;
    steps 1 and 2 are put (they do arrive, but nothing confirms it); zenoh gives up step 3
    after the block timeout: steps 1 and 2 move from sent to dropped_before_stall (an upper
    bound), step 3 and step 4 (not put while stalled) are dropped_stalled; the server
    answers the probe again and step 5 is sent and confirmed. `sent` never exceeds what the
    subscriber received."""
    from minority.insitu import publisher, sender

    spec = Spec.from_dict(spec_dict(every_steps=1))
    answering = threading.Event()
    answering.set()

    def on_query(query):  # not answered: zenoh ends the query with no reply
        if answering.is_set():
            query.reply(keys.spec(RUN), bytes(spec.encode()))

    queryable = server.declare_queryable(keys.spec(RUN), on_query)
    observer = client_factory()
    chunks, events = Inbox(observer, keys.chunks(RUN)), Inbox(observer, keys.event(RUN))
    wait_for_subscriber(server, keys.chunks(RUN))
    offset_s = [0.0]  # added to the publisher's clock
    real_put, given_up = sender.put, keys.chunk(RUN, 3, 0)

    def put(session, key, payload, qos):
        if key == given_up:  # the put zenoh gives up after the block timeout: not delivered
            offset_s[0] += sender.BLOCK_TIMEOUT_S
            return
        real_put(session, key, payload, qos)

    monkeypatch.setattr(sender, "put", put)
    log = io.StringIO()
    pub = publisher.RankPublisher(
        0, 1, PublishOptions(network=NetworkOptions(connect=[endpoint]), stats_every_s=0.0), log,
        clock=lambda: time.monotonic() + offset_s[0])
    args = (sim_particles(moved_particles()), 0.005, ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    try:
        assert pub.connect(5.0)
        pub.start(RUN, spec)
        pub.publish(0, 0.0, *args)
        assert wait_until(lambda: pub.stats.sent_confirmed == 1)
        answering.clear()
        for step in (1, 2):
            pub.publish(step, step * 1e-4, *args)
        assert wait_until(lambda: chunks.received == 3 and pub.stats.sent == 3)
        pub.publish(3, 3e-4, *args)
        assert wait_until(lambda: pub.stats.stalls == 1)
        pub.publish(4, 4e-4, *args)  # stalled, no probe due (or one not answered): not put
        assert wait_until(lambda: pub.stats.dropped_stalled == 2)
        s = pub.stats
        assert (s.sent, s.sent_confirmed, s.dropped_before_stall) == (1, 1, 2)
        answering.set()
        offset_s[0] += sender.PROBE_INTERVAL_S  # a probe is due: answered, the link flows
        pub.publish(5, 5e-4, *args)
        assert wait_until(lambda: chunks.received == 4 and pub.stats.sent_confirmed == 2)
    finally:
        stats = pub.close()
        queryable.undeclare()
    got = {c.step: c for c in (decode_as(chunks.get(1).payload, Chunk) for _ in range(4))}
    assert sorted(got) == [0, 1, 2, 5]  # 1 and 2 did arrive: dropped_before_stall bounds
    assert (stats.scheduled, stats.sent, stats.sent_confirmed) == (6, 2, 2)
    assert (stats.dropped_before_stall, stats.dropped_stalled, stats.dropped) == (2, 2, 4)
    assert stats.bytes_sent == sum(len(got[k].encode()) for k in (0, 5))
    assert stats.particles_sent == got[0].count + got[5].count
    assert "2 chunk(s) put since the last confirmation count as dropped" in log.getvalue()
    assert wait_until(lambda: events.received == 1)
    done = decode_as(events.get(1).payload, Event)
    assert done.kind == EventKind.RANK_DONE
    assert done.detail["sent"] == 2 <= len(got)  # what the server waits for, it has
    assert done.detail["dropped_before_stall"] == 2 and done.detail["dropped"] == 4


@pytest.mark.parametrize("name", sorted(SIM_FIELDS))
def test_every_field_the_sim_offers_has_the_declared_shape(name):
    ps = moved_particles()
    a = cull(sim_particles(ps), DataRequest(("v",), (name,), None))[name]
    f = SIM_FIELDS[name]
    assert a.shape == ((ps.n,) if f.components == 1 else (ps.n, f.components))
    assert a.dtype == np.dtype(f.dtype)


def test_an_error_mid_run_is_published_as_an_event(tmp_path, monkeypatch):
    from minority.sim.decomp import SlabSimulator
    from minority.sim.driver import NonFiniteError

    step = SlabSimulator.step

    def failing_step(self, dt):
        if self.step_count == 5:
            raise NonFiniteError("non-finite velocity at step 5 (t = 0.001 s), particle 7")
        step(self, dt)

    monkeypatch.setattr(SlabSimulator, "step", failing_step)
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict(every_steps=1)))
    cfg = config(f"tcp/127.0.0.1:{free_port()}", tmp_path, 100, spec_file=spec_file,
                 record=tmp_path / "sim.mcap")
    with pytest.raises(NonFiniteError, match="particle 7"):
        run_ranks(cfg, stream=io.StringIO())
    events = [r.decode() for r in read_log(tmp_path / "sim.mcap", [f"minority/{RUN}/event"])]
    assert [e.kind for e in events] == [EventKind.RUN_START, EventKind.ERROR, EventKind.RANK_DONE]
    assert "NonFiniteError: non-finite velocity at step 5" in events[1].message
    assert events[2].detail["scheduled"] == 6  # steps 0-5 were scheduled (all recorded)


# --- decimation, Stats, every_s cadences (spec version 2) ------------------------------------

def in_box(x: np.ndarray, r: Region) -> np.ndarray:
    """[n] bool, by hand: x [n, 3] inside the box (bounds included)."""
    lo, hi = np.array(r.lo_m), np.array(r.hi_m)
    return ((x >= lo) & (x <= hi)).all(axis=1)


def shuffled_particles():
    """moved_particles in a shuffled storage order: slot k no longer holds particle id k."""
    ps = moved_particles()
    ps.permute(np.random.default_rng(1).permutation(ps.n))
    assert not np.array_equal(ps.pid, np.arange(ps.n))
    return ps


def view(name: str, decimate: int, *windows: dict) -> dict:
    return {"name": name, "camera": CAMERA, "width": 64, "height": 48, "field": "displacement",
            "range": [0.0, 0.1], "decimate": decimate, "schedule": list(windows)}


def test_cull_keeps_every_nth_particle_by_original_id_after_the_region_test():
    ps = shuffled_particles()
    for regions in ((FRONT_BOX,), None):
        fields = cull(sim_particles(ps), DataRequest(("side",), ("id", "velocity"), regions, decimate=3))
        keep = ps.pid % 3 == 0
        if regions is not None:
            keep &= in_box(ps.x, FRONT_BOX)
        assert 0 < keep.sum() < ps.n
        assert np.array_equal(fields["id"], ps.pid[keep])
        assert np.array_equal(fields["positions"], ps.x[keep].astype(np.float32))
        assert np.array_equal(fields["velocity"], ps.v[keep].astype(np.float32))
    plain = cull(sim_particles(ps), DataRequest(("side",), ("displacement",), None, decimate=3))
    assert set(plain) == {"positions", "displacement"}
    assert plain["positions"].shape[0] == np.count_nonzero(ps.pid % 3 == 0)


def test_views_that_decimate_differently_get_the_common_stride_with_ids():
    ps = shuffled_particles()
    spec = Spec.from_dict({"version": 2, "run": RUN, "views": [
        view("a", 2, {"every_steps": 1}), view("b", 4, {"every_steps": 2})]})
    both = spec.request(2, 0.001, 0.0005)
    assert both.decimate == 2 and "id" in both.fields
    fields = cull(sim_particles(ps), both)
    ids = fields["id"]
    assert np.array_equal(np.sort(ids), np.arange(0, ps.n, 2))  # every even id, once
    b = fields["positions"][ids % 4 == 0]  # what the server keeps for view b
    assert np.array_equal(sorted_rows(b), sorted_rows(ps.x[ps.pid % 4 == 0].astype(np.float32)))
    alone = spec.request(1, 0.0005, 0.0)  # view a only: its stride, no ids needed
    assert alone.decimate == 2 and "id" not in alone.fields and "id" not in cull(sim_particles(ps), alone)


def test_speed_bins_equal_a_search_of_the_edges():
    edges = np.asarray(SPEED_EDGES_M_S)
    rng = np.random.default_rng(2)
    speeds = np.concatenate([edges, np.nextafter(edges, 0.0), np.nextafter(edges, np.inf),
                             [0.0, 5e-324, 1e-300, 1e300], 10.0 ** rng.uniform(-8.0, 3.0, 20_000)])
    bins = speed_bins(speeds)
    assert np.array_equal(bins, np.searchsorted(edges, speeds, side="right"))
    assert np.bincount(bins, minlength=SPEED_BINS).tolist() == speed_histogram(speeds)


def test_flow_stats_match_a_hand_computation():
    ps = shuffled_particles()
    speed = np.linalg.norm(ps.v, axis=1)
    front = in_box(ps.x, FRONT_BOX)
    assert 0 < front.sum() < ps.n
    everyone, no_one = np.ones(ps.n, bool), np.zeros(ps.n, bool)
    for regions, inside in (((FRONT_BOX,), front), (None, everyone), ((), no_one)):
        st = flow_stats(RUN, 1, 7, 0.0125, sim_particles(ps), regions)
        assert (st.rank, st.step, st.time_s, st.count) == (1, 7, 0.0125, ps.n)
        assert st.windows_open == (regions != ())
        assert st.hist_in_regions == speed_histogram(speed[inside])
        assert st.hist_elsewhere == speed_histogram(speed[~inside])
        assert st.max_speed_m_s == pytest.approx(speed.max(), rel=1e-12)
        assert st.speed_sq_sum_m2_s2 == pytest.approx((speed ** 2).sum(), rel=1e-12)
        assert st.max_displacement_m == pytest.approx(
            np.linalg.norm(ps.x - ps.x0, axis=1).max(), rel=1e-12)
        again = decode_as(st.encode(), Stats)  # decoding checks that the histograms add up
        assert again == msgspec.structs.replace(st, sent_ns=again.sent_ns)
    empty = dataclasses.replace(ps, **{name: getattr(ps, name)[:0] for name in PARTICLE_FIELDS})
    st = flow_stats(RUN, 0, 0, 0.0, sim_particles(empty), (FRONT_BOX,))
    assert (st.count, st.max_speed_m_s, st.max_displacement_m) == (0, 0.0, 0.0)
    assert st.hist_in_regions == st.hist_elsewhere == [0] * SPEED_BINS
    decode_as(st.encode(), Stats)


def test_the_outbox_bounds_stats_on_their_own():
    box = Outbox(max_chunks=4, max_bytes=1 << 20, max_stats=2)
    puts = [box.put(OutboxItem(keys.stats(RUN), bytearray(b"s%d" % i), STATS)) for i in range(3)]
    assert puts == [0, 0, 1]  # the oldest made room
    assert box.put(OutboxItem(keys.event(RUN), bytearray(b"e"), CONTROL)) == 0
    taken = []
    for _ in range(3):
        taken.append(bytes(box.take(1.0).payload))
        box.done()
    assert taken == [b"s1", b"s2", b"e"] and box.discard_chunks() == (0, 0)


@dataclasses.dataclass
class Snapshot:
    time_s: float
    x: np.ndarray  # [n, 3] float64, m
    x0: np.ndarray
    v: np.ndarray  # [n, 3] float64, m/s
    pid: np.ndarray  # [n] int64


def reference_run(steps: int) -> list[Snapshot]:
    """Steps 0..steps of the single-process run as a rank steps it (towards the first output
    frame, 0.02 s): the time the simulation reports and the particles after each step."""
    sim = Simulator(load_scene(TINY))

    def snap() -> Snapshot:
        ps = sim.particles
        return Snapshot(sim.time_s, ps.x.copy(), ps.x0.copy(), ps.v.copy(), ps.pid.copy())

    out = [snap()]
    while sim.step_count < steps:
        sim.advance_to(0.02, max_steps=1)
        out.append(snap())
    return out


def schedule_spec() -> Spec:
    """`side` (every 2nd particle): the front region every 1 ms up to 4 ms, every particle
    every 1.5 ms from 6 ms; `top` (every 4th particle) every 3 ms from 6 ms, so both views
    are due at the first step at or after 6 ms (and their strides differ: ids are sent)."""
    return Spec.from_dict({"version": 2, "run": RUN, "regions": [FRONT], "views": [
        view("side", 2, {"t_end_s": 0.004, "every_s": 0.001, "regions": ["front"]},
             {"t_start_s": 0.006, "every_s": 0.0015}),
        view("top", 4, {"t_start_s": 0.006, "every_s": 0.003})]})


def test_every_s_cadences_and_stats_follow_the_steps_times(server, client_factory, endpoint,
                                                           tmp_path):
    """The chunks' steps are exactly those an every_s window wants given the simulated
    times, with prev_time_s the previous step's time (the server decides from it); the
    chunks hold every request's stride and ids; Stats come every 2 ms of simulated time with
    the in/out split of the windows open then (front region, none, every particle)."""
    steps, stats_every_s = 60, 0.002
    spec = schedule_spec()
    ref = reference_run(steps)
    times = [r.time_s for r in ref]
    prev = [None, *times[:-1]]
    due = [k for k in range(steps + 1)
           if any(w.wants(k, times[k], prev[k]) for v in spec.views for w in v.schedule)]
    stats_due = [k for k in range(steps + 1)
                 if Window(every_s=stats_every_s).wants(k, times[k], prev[k])]
    assert times[-1] > 0.012 and 8 <= len(due) < steps // 3 and len(stats_due) == 7
    observer = client_factory()
    chunks, stats = Inbox(observer, keys.chunks(RUN)), Inbox(observer, keys.stats(RUN))
    wait_for_subscriber(server, keys.chunks(RUN))
    wait_for_subscriber(server, keys.stats(RUN))
    queryable = server.declare_queryable(keys.spec(RUN), lambda q: q.reply(
        keys.spec(RUN), bytes(spec.encode())))
    try:
        summary = run_ranks(config(endpoint, tmp_path, steps, stats_every_s=stats_every_s),
                            stream=io.StringIO())
    finally:
        queryable.undeclare()
    p = summary.publish
    assert (p["scheduled"], p["sent"]) == (len(due), len(due))
    assert (p["stats_due"], p["stats_sent"], p["stats_dropped"]) == (len(stats_due),) * 2 + (0,)
    assert wait_until(lambda: chunks.received == len(due) and stats.received == len(stats_due))

    got = sorted((decode_as(chunks.get(1).payload, Chunk) for _ in due), key=lambda c: c.step)
    assert [c.step for c in got] == due
    kinds = set()
    for c in got:
        r = ref[c.step]
        assert c.time_s == times[c.step] and c.prev_time_s == prev[c.step]  # the very floats
        request = spec.request(c.step, c.time_s, c.prev_time_s)
        keep = r.pid % request.decimate == 0
        if request.regions is not None:
            keep &= in_box(r.x, FRONT_BOX)
        fresh = c.positions[:c.fresh]  # the rest: context rows (insitu.context)
        assert np.array_equal(sorted_rows(fresh), sorted_rows(r.x[keep].astype(np.float32)))
        assert ("id" in c.fields) == (set(request.views) == {"side", "top"})
        if "id" in c.fields:
            assert np.array_equal(np.sort(c.fields["id"]), np.sort(r.pid[keep]))
        kinds.add((request.regions is None, request.decimate, "id" in c.fields))
    assert kinds == {(False, 2, False), (True, 2, False), (True, 2, True)}

    got_stats = sorted((decode_as(stats.get(1).payload, Stats) for _ in stats_due),
                       key=lambda m: m.step)
    assert [m.step for m in got_stats] == stats_due
    phases = set()
    for m in got_stats:
        r, t = ref[m.step], m.time_s
        assert t == times[m.step] and m.rank == 0 and m.count == r.pid.size
        # open then: side's front window up to 4 ms, nothing, then windows of every particle
        inside = in_box(r.x, FRONT_BOX) if t <= 0.004 else np.full(r.pid.size, t >= 0.006)
        assert m.windows_open == (t <= 0.004 or t >= 0.006)
        speed = np.linalg.norm(r.v, axis=1)
        assert m.hist_in_regions == speed_histogram(speed[inside])
        assert m.hist_elsewhere == speed_histogram(speed[~inside])
        assert sum(m.hist_in_regions) + sum(m.hist_elsewhere) == m.count
        assert m.max_displacement_m == pytest.approx(
            np.linalg.norm(r.x - r.x0, axis=1).max(), rel=1e-12, abs=1e-300)
        assert m.max_speed_m_s == pytest.approx(speed.max(), rel=1e-12)
        phases.add((t <= 0.004, t >= 0.006))
    assert phases == {(True, False), (False, False), (False, True)}
    assert got_stats[-1].max_displacement_m > 1e-4  # the column has moved


def test_stats_are_published_before_any_spec_is_known(tmp_path):
    """No server, no spec: nothing is scheduled, yet Stats (every 5 ms of simulated time,
    step 0 included) are recorded, every particle elsewhere, no window open."""
    cfg = config(f"tcp/127.0.0.1:{free_port()}", tmp_path, 30, record=tmp_path / "sim.mcap")
    summary = run_ranks(cfg, stream=io.StringIO())
    p = summary.publish
    got = [r.decode() for r in read_log(tmp_path / "sim.mcap", [f"minority/{RUN}/stats"])]
    assert p["scheduled"] == 0 and p["stats_due"] == p["stats_dropped"] == len(got) == 2
    assert got[0].step == 0 and got[1].time_s >= 0.005 > got[1].time_s - 0.001
    for m in got:
        assert not m.windows_open and m.hist_in_regions == [0] * SPEED_BINS
        assert sum(m.hist_elsewhere) == m.count == summary.particles


def test_a_rank_without_a_server_warns_at_connect_and_again_at_close(tmp_path):
    """minority.insitu's own report (any simulation's): the reason with the attempts made
    over wait_s, and the run said unobserved once more when it ends."""
    from minority.insitu import connect

    log = io.StringIO()
    port = free_port()
    viz = connect(RUN, connect=(f"tcp/127.0.0.1:{port}",), wait_s=0.6, log=log,
                  options=PublishOptions(network=NetworkOptions(auth=False)))
    assert viz.no_server_reason.startswith(f"no zenoh server reachable at tcp/127.0.0.1:{port}")
    tries = re.search(r"(\d+) connection attempts? in ([\d.]+) s\)$", viz.no_server_reason)
    assert tries and int(tries.group(1)) >= 1 and float(tries.group(2)) >= 0.5
    start = log.getvalue()
    assert f"rank 0: WARNING: {viz.no_server_reason}: this run is NOT observed" in start
    viz.close()
    end = log.getvalue()[len(start):]
    assert f"rank 0: WARNING: this run was NOT published/observed: {viz.no_server_reason}" in end


def test_stats_every_s_must_be_a_time():
    for bad in (-0.001, math.nan, math.inf):
        with pytest.raises(ValueError, match="stats_every_s"):
            PublishOptions(stats_every_s=bad)


def test_a_rank_asks_again_for_the_spec_of_a_server_still_starting(server, endpoint, tmp_path):
    """The server's session listens before its spec queryable exists (it is warming up):
    the rank keeps asking within --wait and follows the served spec, not the file."""
    from minority.insitu.publisher import RankPublisher

    served = Spec.from_dict(spec_dict(every_steps=7))
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict(every_steps=20)))
    asked = threading.Event()
    ready = []

    def on_query(query):  # the first question comes before the server is ready
        if asked.is_set():
            query.reply(keys.spec(RUN), bytes(served.encode()))
        asked.set()

    ready.append(server.declare_queryable(keys.spec(RUN), on_query))
    pub = RankPublisher(0, 1, PublishOptions(
        network=NetworkOptions(connect=[endpoint]), spec_file=spec_file), io.StringIO())
    try:
        assert pub.connect(5.0)
        assert pub.fetch_spec(RUN, wait_s=20.0) == served
        assert asked.is_set()
    finally:
        pub.close()
        ready[0].undeclare()


def test_a_record_write_error_is_counted_and_publishing_goes_on(tmp_path):
    """A full disk under the rank's record: the record ends there, what it missed is counted
    and said once, and the sender thread keeps going (it used to die, the outbox filling)."""
    from minority.insitu.publisher import RankPublisher

    log = io.StringIO()
    pub = RankPublisher(0, 1, PublishOptions(record=tmp_path / "sim.mcap"), log)
    pub.start(RUN, Spec.from_dict(spec_dict(every_steps=1)))
    assert pub._outbox.wait_empty(5.0)  # the spec it follows is recorded
    pub._writer.write_payload, calls = fail_call(pub._writer.write_payload, 2,
                                                 OSError(28, "No space left on device"))
    for k in range(3):
        pub.event(EventKind.ERROR, f"message {k}")
    stats = pub.close()
    # the record ends at the failed write: message 1, message 2 and rank_done not recorded
    assert len(calls) == 2 and stats.record_errors == 3 and stats.recorded == 1 + 1
    assert log.getvalue().count("cannot write its record") == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # it ends where writing stopped, with its summary
        events = [r.decode() for r in read_log(tmp_path / "sim.mcap", [f"minority/{RUN}/event"])]
    assert [e.message for e in events] == ["message 0"]
