"""What a rank publishes: only the particles inside the spec's regions, only the requested
fields, at the scheduled steps; the render server renders the culled chunks; without a
server, or with a subscriber that never reads, the run finishes with every drop counted.
Network tests: loopback, a free port each, waits on counts with timeouts."""

import io
import json
import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import free_port
from test_loopback import wait_until

from protocol import Chunk, Event, EventKind, Spec, decode_as, keys
from protocol.log import read_log
from protocol.session import Inbox, NetworkOptions, Role, open_session
from protocol.spec import DataRequest, Region
from protocol.wire import decode
from render_server.daemon import RenderServer, ServerOptions
from sim.driver import Simulator
from sim.publish import SIM_FIELDS, PublishOptions, cull, particle_bytes, record_path
from sim.ranks import RankRunConfig, run_ranks
from sim.scene import builtin_scene_path, load_scene
from sim.state import seed_particles

RUN = "test-run"
TINY = builtin_scene_path("tiny")  # 0.1 m column at x in [0, 0.1] m
FRONT = {"name": "front", "lo_m": [0.05, -1.0, -1.0], "hi_m": [1.0, 1.0, 1.0]}


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
    fields = cull(ps, DataRequest(("side",), ("displacement", "velocity_magnitude"), (box,)))
    assert list(fields) == ["positions", "displacement", "velocity_magnitude"]
    expected = np.flatnonzero(ps.x[:, 0] >= 0.05)
    assert 0 < expected.size < ps.n
    assert np.array_equal(fields["positions"], ps.x[expected].astype(np.float32))
    assert np.array_equal(fields["displacement"], (ps.x - ps.x0)[expected].astype(np.float32))
    np.testing.assert_allclose(fields["velocity_magnitude"],
                               np.linalg.norm(ps.v[expected], axis=1), rtol=1e-6)
    everything = cull(ps, DataRequest(("side",), ("id", "pressure"), None))
    assert np.array_equal(everything["id"], ps.pid) and everything["pressure"].shape == (ps.n,)
    assert set(cull(ps, DataRequest(("v",), ("no_such_field",), None))) == {"positions"}


def test_culling_reduces_the_bytes_as_predicted():
    """Predicted: particles inside the regions x bytes per particle of the requested fields;
    the rest of a payload is its header and padding (under a kilobyte)."""
    ps = moved_particles()
    box = Region("front", (0.05, -1.0, -1.0), (1.0, 1.0, 1.0))
    m = int((ps.x[:, 0] >= 0.05).sum())

    def encoded(request):
        payload = Chunk(RUN, 0, 0.0, 0, 1, 0.005, ((0, 0, 0), (1, 1, 1)),
                        cull(ps, request)).encode()
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
        summary = run_ranks(config(endpoint, tmp_path, 40), stream=log)
        assert summary.spec_version == 2 and summary.run == RUN
        p = summary.publish
        assert (p["scheduled"], p["sent"], p["dropped"]) == (3, 3, 0)  # steps 0, 20, 40
        assert wait_until(lambda: chunks.received == 3 and events.received == 2)
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
            assert 0 < c.count == len(inside) < 400
            assert np.array_equal(sorted_rows(c.positions), sorted_rows(inside))
        assert p["particles_sent"] == sum(c.count for c in got.values()) < p["particles_total"]
        assert p["bytes_sent"] == sum(len(c.encode()) for c in got.values())
        start, done = (decode_as(events.get(1).payload, Event) for _ in range(2))
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
    assert log.getvalue().count("running without publishing") == 1
    # ... and the record keeps what would have been sent: spec, chunks, events
    topics = [r.topic for r in read_log(tmp_path / "sim.mcap")]
    assert topics.count(f"minority/{RUN}/chunk") == 11 and topics[0] == f"minority/{RUN}/spec"
    assert topics.count(f"minority/{RUN}/event") == 2  # run start, rank done


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


def test_a_subscriber_that_never_reads_costs_counted_drops_not_time(endpoint, tmp_path):
    """A server whose chunk callback blocks forever: zenoh stops reading the link, the
    rank's puts block, the sender stalls, and the simulation runs on to the end."""
    server_cfg = tmp_path / "server.json5"
    server_cfg.write_text('{ mode: "peer", scouting: { multicast: { enabled: false } }, '
                          'transport: { link: { tcp: { so_rcvbuf: 65536 } } } }')
    (tmp_path / "client.json5").write_text(SIM_SIDE_CONFIG)
    server = open_session(NetworkOptions(listen=[endpoint], config=server_cfg), Role.SERVER)
    gate, arrived = threading.Event(), []
    spec = Spec.from_dict(spec_dict(every_steps=1, regions=False))

    def never_return(sample):
        arrived.append(1)
        gate.wait()

    queryable = server.declare_queryable(keys.spec(RUN), lambda q: q.reply(
        keys.spec(RUN), bytes(spec.encode())))
    stuck = server.declare_subscriber(keys.chunks(RUN), never_return)
    try:
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
    finally:
        gate.set()
        stuck.undeclare()
        queryable.undeclare()
        server.close()


@pytest.mark.parametrize("name", sorted(SIM_FIELDS))
def test_every_field_the_sim_offers_has_the_declared_shape(name):
    ps = moved_particles()
    a = cull(ps, DataRequest(("v",), (name,), None))[name]
    f = SIM_FIELDS[name]
    assert a.shape == ((ps.n,) if f.components == 1 else (ps.n, f.components))
    assert a.dtype == np.dtype(f.dtype)


def test_an_error_mid_run_is_published_as_an_event(tmp_path, monkeypatch):
    from sim.decomp import SlabSimulator
    from sim.driver import NonFiniteError

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
