"""The in situ API (minority.insitu) without sim/: a loop of synthetic particles calls
`connect`, `due`, `publish`, `close` against a real RenderServer on loopback, a spec file,
a subscriber that never reads, or no server at all (a record that `minority replay`
renders). Network tests: loopback, a free port each, waits on counts with timeouts."""

import io
import json

import numpy as np
import pytest
from conftest import free_port
from test_loopback import wait_until
from test_sim_publish import stalled_server, wait_for_subscriber

from minority.cli import main
from minority.insitu import PublishOptions, connect
from minority.protocol import Chunk, Event, EventKind, Spec, Stats, decode_as, keys
from minority.protocol.log import read_log
from minority.protocol.session import Inbox, NetworkOptions
from minority.protocol.view import Window
from minority.render_server.daemon import RenderServer, ServerOptions

RUN = "insitu-run"
SPACING_M = 0.01
DT_S = 1e-3  # simulated time per step
CAMERA = {"position": [0.1, -1.0, 0.05], "focal_point": [0.1, 0.05, 0.05]}


def spec_dict(schedule=None, field="velocity_magnitude") -> dict:
    return {"version": 2, "run": RUN, "views": [{
        "name": "side", "camera": CAMERA, "width": 48, "height": 32, "field": field,
        "range": [0.0, 1.0], "schedule": schedule or [{"every_steps": 2}]}]}


def block(n: int, seed: int = 0) -> np.ndarray:
    """[n, 3] m: a 0.2 x 0.1 x 0.1 m box of random particles."""
    return np.random.default_rng(seed).random((n, 3)) * [0.2, 0.1, 0.1]


def fields_at(x0: np.ndarray, step: int) -> tuple[np.ndarray, dict]:
    """Positions at `step` of a block sliding along x at 0.5 m/s, and its fields."""
    v = np.zeros_like(x0)
    v[:, 0] = 0.5
    x = x0 + v * step * DT_S
    return x, {"velocity": v, "displacement": x - x0}


def test_a_loop_of_synthetic_particles_makes_frames_and_a_log(server, endpoint, tmp_path):
    """Steps 0..6 against a RenderServer: chunks at steps 0, 2, 4, 6 with the view's field
    computed from the given vector (velocity_magnitude from velocity), ids by default, Stats,
    frames, and the server's MCAP log of all of it."""
    spec = Spec.from_dict(spec_dict())
    daemon = RenderServer(server, ServerOptions(spec, tmp_path / "frames", tmp_path / "run.mcap",
                                                timeout_s=30.0))
    x0 = block(500)
    try:
        with connect(RUN, connect=(endpoint,), wait_s=5.0, log=io.StringIO()) as viz:
            assert viz.spec == spec
            due = []
            for step in range(7):
                time_s = step * 7e-4  # the Stats cadence (5 ms) picks step 0 only
                x, fields = fields_at(x0, step)
                if viz.due(step, time_s):
                    due.append(step)
                    assert viz.wanted == (("velocity_magnitude", "velocity", "displacement")
                                          if step == 0 else ("velocity_magnitude",))
                    viz.publish(step, time_s, x, fields=fields, spacing_m=SPACING_M)
        stats = viz.stats
        assert due == [0, 2, 4, 6]
        assert (stats.scheduled, stats.sent, stats.dropped) == (4, 4, 0)
        assert stats.stats_due == stats.stats_sent == 1
        assert wait_until(lambda: daemon.summary()["steps_rendered"]
                          + daemon.summary()["steps_skipped"] == 4)
        assert daemon.stats.frames >= 1 and daemon.stats.view_errors == 0
    finally:
        daemon.close()
    frames = sorted((tmp_path / "frames" / RUN / "side").glob("*.png"))
    assert frames and frames[-1].name == "000006.png"
    records = list(read_log(tmp_path / "run.mcap"))
    chunks = [r.decode() for r in records if r.topic == f"minority/{RUN}/chunk"]
    assert [c.step for c in chunks] == [0, 2, 4, 6]
    last = chunks[-1]
    assert set(last.fields) == {"positions", "velocity_magnitude"} and last.count == 500
    np.testing.assert_allclose(last.fields["velocity_magnitude"], 0.5, rtol=1e-6)
    x, _ = fields_at(x0, 6)
    np.testing.assert_array_equal(last.positions, x.astype(np.float32))
    events = [r.decode() for r in records if r.topic == f"minority/{RUN}/event"]
    done = next(e for e in events if e.kind == EventKind.RANK_DONE)
    assert done.detail["sent"] == 4 and done.detail["dropped"] == 0


def test_due_follows_the_spec_schedule(tmp_path):
    """every_steps in one window, every_s in another (the instants 5.5, 9, 12.5, 16 and
    19.5 ms fall to the steps after them), and the Stats cadence (every 4.7 ms from 0), from
    a spec file, recording only; what `due` says is what is recorded."""
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict([
        {"t_end_s": 0.005, "every_steps": 2},
        {"t_start_s": 0.0055, "every_s": 0.0035}])))
    options = PublishOptions(stats_every_s=0.0047, outbox_chunks=64)  # the disk keeps up
    x0 = block(50)
    viz = connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",), spec=spec_file,
                         record=tmp_path / "rec.mcap", options=options, log=io.StringIO())
    due = []
    for step in range(21):
        if viz.due(step, step * DT_S):
            due.append(step)
            viz.publish(step, step * DT_S, *fields_at(x0, step), spacing_m=SPACING_M)
    stats = viz.close()
    views = [0, 2, 4, 6, 9, 13, 16, 20]
    stats_steps = [0, 5, 10, 15, 19]
    assert due == sorted(set(views + stats_steps))
    assert (stats.scheduled, stats.stats_due) == (len(views), len(stats_steps))
    # the same answer as the spec's own schedule, given each step's previous time
    spec = Spec.load(spec_file)
    assert views == [k for k in range(21) if spec.request(k, k * DT_S, (k - 1) * DT_S
                                                          if k else None) is not None]
    assert stats_steps == [k for k in range(21) if Window(every_s=0.0047).wants(
        k, k * DT_S, (k - 1) * DT_S if k else None)]
    records = [r.decode() for r in read_log(tmp_path / "rec.mcap")
               if r.topic != f"minority/{RUN}/spec"]
    assert [c.step for c in records if isinstance(c, Chunk)] == views
    assert [s.step for s in records if isinstance(s, Stats)] == stats_steps


def test_publish_never_waits_for_a_server_that_stopped_reading(endpoint, tmp_path):
    """A server whose chunk callback never returns: zenoh stops reading the link, the
    sender's put blocks, and every publish call still returns: the loop runs until the
    outbox has overflowed (drops counted), and every scheduled chunk is accounted for."""
    spec = Spec.from_dict(spec_dict([{"every_steps": 1}]))
    options = PublishOptions(network=NetworkOptions(config=tmp_path / "client.json5"),
                             drain_timeout_s=1.0, stats_every_s=0.0)
    x0 = block(4000)  # 64 kB per chunk
    log = io.StringIO()
    with stalled_server(endpoint, tmp_path, spec) as arrived:
        viz = connect(RUN, connect=(endpoint,), wait_s=5.0, options=options, log=log)
        step = 0
        while viz.stats.dropped_outbox == 0 and step < 100_000:
            if viz.due(step, step * DT_S):  # False once the outbox is full: nothing to build
                x, fields = fields_at(x0, step)
                viz.publish(step, step * DT_S, x, fields=fields, spacing_m=SPACING_M)
            step += 1
        assert viz.stats.dropped_outbox > 0  # the outbox was full, and publish returned
        assert not viz.due(step, step * DT_S)  # still full: refused before any work
        step += 1
        stats = viz.close()
        assert stats.scheduled == step and stats.sent + stats.dropped == stats.scheduled
        assert stats.dropped >= stats.dropped_outbox > 0
        assert len(arrived) == 1  # the one chunk the callback holds


def test_an_exception_in_the_loop_arrives_as_an_error_event_then_done(server, client_factory,
                                                                        endpoint):
    observer = client_factory()
    events = Inbox(observer, keys.event(RUN))
    wait_for_subscriber(server, keys.event(RUN))
    with pytest.raises(RuntimeError, match="the solver diverged"):
        with connect(RUN, connect=(endpoint,), wait_s=5.0, log=io.StringIO()) as viz:
            viz.due(0, 0.0)
            raise RuntimeError("the solver diverged")
    assert wait_until(lambda: events.received == 2)
    error, done = (decode_as(events.get(1).payload, Event) for _ in range(2))
    assert error.kind == EventKind.ERROR and "RuntimeError: the solver diverged" in error.message
    assert done.kind == EventKind.RANK_DONE and done.detail["error"] == "the solver diverged"
    assert viz.close() is viz.stats  # closed once; a second close only returns the counts


def test_without_a_server_the_record_replays_into_frames(tmp_path):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict(field="displacement")))
    log = io.StringIO()
    x0 = block(300)
    with connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",), spec=spec_file,
                        record=tmp_path / "rec.mcap", log=log) as viz:
        for step in range(5):
            if viz.due(step, step * DT_S):
                viz.publish(step, step * DT_S, *fields_at(x0, step), ids=np.arange(300) + 7,
                            spacing_m=SPACING_M, bounds_m=((0, 0, 0), (0.3, 0.1, 0.1)))
    assert "running without publishing (recording only)" in log.getvalue()
    assert viz.stats.dropped_no_server == 3 and viz.stats.recorded > 3
    assert main(["replay", str(tmp_path / "rec.mcap"), "--out", str(tmp_path / "out"), "-q"]) == 0
    frames = sorted(p.name for p in (tmp_path / "out").rglob("*.png"))
    assert frames == ["000000.png", "000002.png", "000004.png"]


@pytest.mark.parametrize(("positions", "fields", "problem"), [
    (np.zeros((10, 2)), {}, r"positions must be an \[n, 3\] array"),
    (np.zeros(30), {}, r"positions must be an \[n, 3\] array"),
    (np.zeros((10, 3)), {"velocity": np.zeros((9, 3))}, r"field 'velocity' must be .* n = 10"),
    (np.zeros((10, 3)), {"pressure": np.array(["a"] * 10)}, r"field 'pressure' must hold real"),
    (np.zeros((10, 3)), {"id": np.zeros(10)}, r"field 'id' is reserved"),
    (np.where(np.arange(30).reshape(10, 3) == 13, np.nan, 0.0), {},
     r"positions: particle 4 .* not finite"),
    (np.zeros((10, 3)), {"velocity": np.full((10, 3), np.inf)},
     r"field 'velocity': particle 0 .* not finite"),
])
def test_bad_input_raises_before_anything_is_sent(tmp_path, positions, fields, problem):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict([{"every_steps": 1}])))
    viz = connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",), spec=spec_file,
                         record=tmp_path / "rec.mcap", log=io.StringIO())
    try:
        assert viz.due(0, 0.0)
        with pytest.raises(ValueError, match=problem):
            viz.publish(0, 0.0, positions, fields=fields, spacing_m=SPACING_M)
    finally:
        stats = viz.close()
    topics = [r.topic for r in read_log(tmp_path / "rec.mcap")]
    assert f"minority/{RUN}/chunk" not in topics and stats.particles_total == 0


def test_bad_arguments_name_the_problem(tmp_path):
    with pytest.raises(ValueError, match="rank must be an integer in"):
        connect(RUN, rank=2, ranks=2)
    with pytest.raises(ValueError, match="run must be 1-64 characters"):
        connect("bad/run")
    viz = connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",),
                         record=tmp_path / "r.mcap", log=io.StringIO())
    try:
        with pytest.raises(ValueError, match="spacing_m must be"):
            viz.publish(0, 0.0, np.zeros((1, 3)), spacing_m=0.0)
        with pytest.raises(ValueError, match="time_s must be"):
            viz.due(0, float("nan"))
        with pytest.raises(ValueError, match="ids must be"):
            viz.publish(0, 0.0, np.zeros((2, 3)), ids=np.zeros(3, int), spacing_m=0.01)
    finally:
        viz.close()
