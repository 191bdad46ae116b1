"""Lent steps (`InSitu.publish(..., copy=False)`, minority.insitu.lend): the sender reads the
caller's arrays in place and calls its field functions; `reclaim` waits until it has; a bad
lent step is not sent and raises at the caller's next call; `minority sim` lends its
particle arrays and waits before writing them. Records only (no server), or loopback."""

import io
import json
import threading

import msgspec
import numpy as np
import pytest
from conftest import free_port
from test_insitu import DT_S, RUN, SPACING_M, block, fields_at, spec_dict

from minority.insitu import PublishOptions, connect
from minority.insitu.lend import BadStep
from minority.protocol import Chunk, Event, EventKind, Stats
from minority.protocol.log import read_log
from minority.sim.driver import Simulator
from minority.sim.publish import sim_fields
from minority.sim.scene import builtin_scene_path, load_scene

BOUNDS = ((0.0, 0.0, 0.0), (0.3, 0.1, 0.1))


def record(tmp_path, name: str, schedule=None, field="displacement", **kw):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec_dict(schedule or [{"every_steps": 1}], field)))
    return connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",), spec=spec_file,
                   record=tmp_path / name, log=io.StringIO(), report=False, **kw)


def messages(path) -> list:
    return [r.decode() for r in read_log(path) if r.topic != f"minority/{RUN}/spec"]


def payloads(path) -> list:
    """The chunks and Stats of a record, comparable: a chunk as its header and the bytes of
    its arrays (not its send time)."""
    out = []
    for m in messages(path):
        if isinstance(m, Chunk):
            arrays = {k: (v.dtype.str, v.shape, v.tobytes()) for k, v in m.fields.items()}
            ids = None if m.context_ids is None else m.context_ids.tobytes()
            out.append((m.meta(), arrays, ids))
        elif isinstance(m, Stats):
            out.append(msgspec.structs.replace(m, sent_ns=0))
    return out


def run_loop(viz, x0, steps: int, lend: bool, scratch: bool = False) -> None:
    """Publish a sliding block; with `scratch`, the caller overwrites the lent arrays with
    garbage right after each reclaim (what a solver's next step does)."""
    for step in range(steps):
        x, fields = fields_at(x0, step)
        if viz.due(step, step * DT_S):
            viz.publish(step, step * DT_S, x, fields=fields, spacing_m=SPACING_M,
                        bounds_m=BOUNDS, copy=not lend)
        viz.reclaim()
        viz.wait_sent(10.0)  # every step sent: none refused by a full outbox
        if scratch:
            x[:] = -1.0
            for values in fields.values():
                values[:] = np.nan


def test_a_lent_step_sends_what_a_copied_step_sends(tmp_path):
    """The same loop copied and lent (the lent arrays overwritten after each reclaim):
    byte-identical chunks and Stats in the records."""
    x0 = block(800)
    with record(tmp_path, "copied.mcap") as viz:
        run_loop(viz, x0, 6, lend=False)
    with record(tmp_path, "lent.mcap") as viz:
        run_loop(viz, x0, 6, lend=True, scratch=True)
    copied, lent = payloads(tmp_path / "copied.mcap"), payloads(tmp_path / "lent.mcap")
    assert len(copied) == 8 and lent == copied  # 6 chunks, the Stats of steps 0 and 5


def test_reclaim_waits_until_the_sender_has_read_the_arrays(tmp_path):
    """A field function that blocks the sender: reclaim waits for it (and times out while it
    blocks); once released, the message is built and reclaim returns at once."""
    gate, called = threading.Event(), []
    x0 = block(200)

    def velocity():
        called.append(threading.current_thread().name)
        gate.wait(10.0)
        return np.ones((200, 3))

    viz = record(tmp_path, "rec.mcap", field="velocity_magnitude")
    try:
        assert viz.due(0, 0.0)
        viz.publish(0, 0.0, x0, fields={"velocity": velocity, "unused": lambda: 1 / 0},
                    spacing_m=SPACING_M, copy=False)
        with pytest.raises(TimeoutError, match="still read lent arrays"):
            viz.reclaim(timeout_s=0.2)
        gate.set()
        assert viz.reclaim(timeout_s=10.0) >= 0.0
        assert viz.reclaim(timeout_s=0.0) == 0.0  # nothing lent any more
    finally:
        gate.set()
        stats = viz.close()
    assert called and called[0] != threading.main_thread().name  # called by the sender, once
    assert len(called) == 1 and stats.build_errors == 0  # `unused` is never called
    chunk, = [m for m in messages(tmp_path / "rec.mcap") if isinstance(m, Chunk)]
    assert np.array_equal(chunk.fields["velocity_magnitude"], np.full(200, np.sqrt(3.0),
                                                                      dtype=np.float32))


@pytest.mark.parametrize(("bad", "problem"), [
    ("positions", r"step 2: positions: particle 5 \(row 5\) is not finite"),
    ("field", r"step 2: field 'displacement': particle 5 .* not finite"),
    ("function", r"step 2: field 'displacement' must be \[n\] or \[n, k\] with n = 50"),
    ("ids", r"step 2: ids must be >= 0, got -3"),
])
def test_a_bad_lent_step_is_not_sent_and_raises_at_the_next_call(tmp_path, bad, problem):
    x0 = block(50)
    viz = record(tmp_path, "rec.mcap")
    try:
        for step in range(4):
            x, fields = fields_at(x0, step)
            ids = np.arange(50)
            if step == 2:
                if bad == "positions":
                    x[5, 1] = np.nan
                elif bad == "field":
                    fields["displacement"][5] = np.inf
                elif bad == "function":
                    fields["displacement"] = lambda: np.zeros((49, 3))
                else:
                    ids[7] = -3
            if step == 3:
                with pytest.raises(ValueError, match=problem):
                    viz.publish(step, step * DT_S, x, fields=fields, spacing_m=SPACING_M,
                                copy=False)
            assert viz.due(step, step * DT_S)
            viz.publish(step, step * DT_S, x, fields=fields, ids=ids, spacing_m=SPACING_M,
                        copy=False)
            if step == 2:
                viz.wait_sent(10.0)  # built (and refused) before step 3's publish
    finally:
        stats = viz.close()
    steps = [m.step for m in messages(tmp_path / "rec.mcap") if isinstance(m, Chunk)]
    assert steps == [0, 1, 3] and stats.bad_steps == 1 and stats.build_errors == 0
    assert stats.scheduled == 4 and stats.sent + stats.dropped == 4


def test_close_raises_a_bad_lent_step_and_records_it_before_rank_done(tmp_path):
    x0 = block(50)
    x0[3, 0] = np.nan
    viz = record(tmp_path, "rec.mcap")
    assert viz.due(0, 0.0)
    viz.publish(0, 0.0, x0, fields={"velocity": np.zeros((50, 3))}, spacing_m=SPACING_M,
                copy=False)
    with pytest.raises(BadStep, match="step 0: positions: particle 3"):
        viz.close()
    events = [m for m in messages(tmp_path / "rec.mcap") if isinstance(m, Event)]
    assert [e.kind for e in events] == [EventKind.ERROR, EventKind.RANK_DONE]
    assert "particle 3" in events[0].message and "particle 3" in events[1].detail["error"]
    assert not [m for m in messages(tmp_path / "rec.mcap") if isinstance(m, (Chunk, Stats))]


def test_the_sim_lends_its_arrays_and_sends_what_it_would_copy(tmp_path):
    """minority sim's way (sim_fields lazy, Simulator.before_write = reclaim) through 8 MPM
    steps of the small column (the sim writing its arrays right after), against the same
    steps copied: identical records."""
    scene = load_scene(builtin_scene_path("column_13k"))
    spec = {"version": 2, "run": RUN, "views": [{
        "name": "side", "camera": {"position": [0.3, -1.5, 0.1], "focal_point": [0.3, 0.05, 0.1]},
        "width": 64, "height": 48, "field": "displacement_magnitude", "range": [0.0, 0.01],
        "schedule": [{"every_steps": 1}]}]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    bounds = ((0.0, 0.0, 0.0), tuple(map(float, scene.size_m)))
    for lend in (False, True):
        sim = Simulator(scene, fixed_dt=2e-5, threads=1)
        with connect(RUN, connect=(f"tcp/127.0.0.1:{free_port()}",), spec=tmp_path / "spec.json",
                     record=tmp_path / f"{lend}.mcap", log=io.StringIO(), report=False,
                     options=PublishOptions(stats_every_s=4e-5)) as viz:
            sim.before_write = viz.reclaim
            for _ in range(8):
                ps = sim.particles
                if viz.due(sim.step_count, sim.time_s):
                    viz.publish(sim.step_count, sim.time_s, ps.x,
                                fields=sim_fields(ps, viz.wanted, lazy=lend), ids=ps.pid,
                                spacing_m=scene.particle_spacing_m, bounds_m=bounds,
                                copy=not lend)
                sim.step(sim.fixed_dt)
    copied, lent = payloads(tmp_path / "False.mcap"), payloads(tmp_path / "True.mcap")
    assert len(copied) > 8 and lent == copied  # 8 chunks and the Stats


def test_the_loan_ends_once_the_sender_has_copied_the_step_before_it_culls(tmp_path):
    """The sender copies a lent step first and culls and encodes the copy: reclaim returns
    while the chunk's build is still held up, and the caller's later writes do not reach it."""
    x0 = block(300)
    viz = record(tmp_path, "rec.mcap")
    gate = threading.Event()
    build = viz._pub._build_chunk

    def held(*args, **kw):
        gate.wait(10.0)
        return build(*args, **kw)

    viz._pub._build_chunk = held
    try:
        x, fields = fields_at(x0, 0)
        assert viz.due(0, 0.0)
        viz.publish(0, 0.0, x, fields=fields, spacing_m=SPACING_M, bounds_m=BOUNDS, copy=False)
        viz.reclaim(timeout_s=10.0)  # the build is still held: the copy was enough
        assert not gate.is_set() and viz._pub._loans.out == 0
        x[:] = 99.0
        gate.set()
        assert viz.wait_sent(10.0)
    finally:
        gate.set()
        viz.close()
    chunk, = [m for m in messages(tmp_path / "rec.mcap") if isinstance(m, Chunk)]
    assert np.array_equal(chunk.fields["positions"], x0.astype(np.float32))


def test_a_lent_step_no_message_reads_is_given_back_at_once(tmp_path):
    """Stats due without a velocity field (nothing is queued, the Stats counted dropped):
    the arrays are not held."""
    viz = record(tmp_path, "rec.mcap", schedule=[{"t_start_s": 1.0, "every_steps": 1}])
    try:
        assert viz.due(0, 0.0)  # the Stats cadence alone
        viz.publish(0, 0.0, block(20), spacing_m=SPACING_M, copy=False)
        assert viz.reclaim(timeout_s=0.0) == 0.0
    finally:
        stats = viz.close()
    assert stats.stats_dropped == 1 and stats.missing_fields == ["velocity"]
