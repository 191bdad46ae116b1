"""Complete pictures under region culling: context rows on the wire (protocol), what a rank
sends (insitu.context), the server's cache (render_server.particles), end to end."""

import io

import numpy as np
import pytest
from conftest import make_chunk
from test_loopback import wait_until
from test_sim_publish import RUN, config, spec_dict

from minority.insitu.context import ContextTracker
from minority.protocol import Chunk, ProtocolError, Spec, Timing, decode_as, keys
from minority.protocol.session import Inbox
from minority.protocol.spec import inside_mask
from minority.render_server.assemble import StepAssembler
from minority.render_server.daemon import RenderServer, ServerOptions
from minority.render_server.particles import ParticleCache, complete_step
from minority.sim.ranks import run_ranks


def chunk_with_context(n=10, context=4, evict=(7, 9), reset=True) -> Chunk:
    c = make_chunk(n, ranks=1)
    c.context_ids = np.arange(100, 100 + context, dtype=np.int64)
    c.evict_ids = np.array(evict, dtype=np.int64)
    c.context_reset = reset
    return c


def test_context_rows_round_trip():
    c = chunk_with_context()
    back = decode_as(bytes(c.encode()), Chunk)
    assert back.count == 10 and back.fresh == 6 and back.context_reset
    assert back.context_ids.tolist() == [100, 101, 102, 103]
    assert back.evict_ids.tolist() == [7, 9]
    assert set(back.fields) == set(c.fields)  # the id arrays are not fields
    plain = make_chunk(10, ranks=1)
    decoded = decode_as(bytes(plain.encode()), Chunk)
    assert decoded.context_ids is None and decoded.fresh == 10


@pytest.mark.parametrize("damage, problem", [
    (lambda c: setattr(c, "context_ids", np.arange(11)), "context ids for 10 rows"),
])
def test_a_chunk_with_more_context_ids_than_rows_is_refused_at_encode(damage, problem):
    c = make_chunk(10, ranks=1)
    damage(c)
    with pytest.raises(ProtocolError, match=problem):
        c.encode()


def test_context_headers_that_disagree_with_the_arrays_are_refused():
    from minority.protocol import wire
    from minority.protocol.messages import CONTEXT_ID

    c = chunk_with_context(evict=())
    env = wire.decode(bytes(c.encode()))
    for meta, arrays, problem in [
        ({"context": 11}, {}, "chunk.context 11 exceeds chunk.count 10"),
        ({"context": 5}, {}, r"context_id must be \[5\] int64"),
        ({"evicted": 2}, {}, "counts 2 evict_id but the array is missing"),
        ({"context": None}, {}, "no chunk.context count"),
        ({}, {CONTEXT_ID: np.arange(4, dtype=np.int32)}, r"context_id must be \[4\] int64"),
    ]:
        m = {**env.meta, **meta}
        payload = wire.encode(Chunk.KIND, m, {**env.arrays, **arrays}, None)
        with pytest.raises(ProtocolError, match=problem):
            decode_as(bytes(payload), Chunk)


def test_a_rank_sends_the_outside_once_then_only_what_moved_and_evicts_what_entered():
    rng = np.random.default_rng(1)
    pid = rng.permutation(50).astype(np.int64)
    x = rng.uniform(0.0, 1.0, (50, 3)).astype(np.float32)
    outside = x[:, 0] < 0.5
    t = ContextTracker(tolerance_m=0.01)
    first = t.split(pid, x, outside)
    assert first.reset and sorted(first.rows.tolist()) == np.flatnonzero(outside).tolist()
    assert len(first.evict) == 0
    again = t.split(pid, x, outside)
    assert not again.reset and len(again.rows) == 0 and len(again.evict) == 0
    out_rows = np.flatnonzero(outside)
    x[out_rows[0], 2] += 0.005  # within the tolerance: not resent
    x[out_rows[1], 2] += 0.02  # beyond it: resent
    moved = t.split(pid, x, outside)
    assert moved.rows.tolist() == [out_rows[1]] and len(moved.evict) == 0
    outside[out_rows[2]] = False  # entered a region: the server must forget it
    entered = t.split(pid, x, outside)
    assert entered.evict.tolist() == [pid[out_rows[2]]] and len(entered.rows) == 0
    keep = np.ones(50, bool)
    keep[out_rows[3]] = False  # left the rank (migrated): forgotten here too
    left = t.split(pid[keep], x[keep], outside[keep])
    assert left.evict.tolist() == [pid[out_rows[3]]]
    t.reset()
    again = t.split(pid, x, outside)
    assert again.reset and len(again.rows) == outside.sum()


def test_float64_positions_at_rest_are_not_resent():
    """The wire carries float32: positions given in float64 that did not move are not sent
    again at tolerance 0 (their float32 rounding is no motion)."""
    x = np.random.default_rng(4).uniform(0.0, 1.0, (30, 3))  # float64
    pid = np.arange(30, dtype=np.int64)
    t = ContextTracker(tolerance_m=0.0)
    assert len(t.split(pid, x, np.ones(30, bool)).rows) == 30
    assert len(t.split(pid, x.copy(), np.ones(30, bool)).rows) == 0
    x[3, 1] += 1e-3
    assert t.split(pid, x, np.ones(30, bool)).rows.tolist() == [3]


def steps_through_the_wire(states, box, tolerance_m=0.0):
    """Chunks of one rank for each state (positions [n, 3]): the fresh rows inside `box`, the
    context rows from a tracker; assembled and completed as the server does."""
    tracker, assembler, cache = ContextTracker(tolerance_m), StepAssembler(), ParticleCache()
    pid = np.arange(len(states[0]), dtype=np.int64)
    out = []
    for step, x in enumerate(states):
        inside = inside_mask(x, (box,))
        split = tracker.split(pid, x, ~inside)
        rows = np.concatenate([np.flatnonzero(inside), split.rows])
        d = np.linalg.norm(x - states[0], axis=1).astype(np.float32)
        c = Chunk(RUN, step, 0.01 * step, 0, 1, 0.01, ((0, 0, 0), (1, 1, 1)),
                  {"positions": x[rows], "displacement_magnitude": d[rows]},
                  context_ids=pid[split.rows], evict_ids=split.evict,
                  context_reset=split.reset)
        c = decode_as(bytes(c.encode()), Chunk)
        for s in assembler.add(c, 0, 0):
            out.append(complete_step(cache, s))
    return out


def rows_of(step) -> set:
    return {tuple(r) for r in np.round(step.positions, 6).tolist()}


def test_completed_steps_hold_every_particle_once_while_the_outside_rests():
    rng = np.random.default_rng(2)
    x0 = rng.uniform(0.0, 1.0, (200, 3)).astype(np.float32)
    from minority.protocol.spec import Region

    box = Region("front", (0.5, 0.0, 0.0), (1.0, 1.0, 1.0))
    states = [x0.copy()]
    for _ in range(4):  # the particles in the box move, and some move out of or into it
        x = states[-1].copy()
        inside = inside_mask(x, (box,))
        x[inside, 0] += rng.uniform(-0.1, 0.05, inside.sum()).astype(np.float32)
        states.append(x)
    steps = steps_through_the_wire(states, box)
    assert len(steps) == 5
    for s, x in zip(steps, states, strict=True):
        assert s.completed and len(s.positions) == 200  # once each: nothing drawn twice
        assert rows_of(s) == {tuple(r) for r in np.round(x, 6).tolist()}
        assert len(s.fields["displacement_magnitude"]) == 200
    assert steps[0].cached == 0 or steps[0].cache_age_steps == 0
    assert steps[-1].cached > 0 and steps[-1].cache_age_steps > 0


def test_a_later_step_released_first_is_not_undone_by_an_older_one():
    cache = ParticleCache()
    assembler = StepAssembler()

    def step_of(step, pos):
        c = Chunk(RUN, step, 0.1 * step, 0, 1, 0.01, ((0, 0, 0), (1, 1, 1)),
                  {"positions": np.array([pos], np.float32)},
                  context_ids=np.array([5]), evict_ids=np.zeros(0, np.int64))
        return assembler.add(c, 0, 0)[0]

    newer, older = step_of(2, [0.2, 0.2, 0.2]), step_of(1, [0.1, 0.1, 0.1])
    cache.apply(newer)
    cache.apply(older)
    assert cache.positions.tolist() == [[pytest.approx(0.2)] * 3] and cache.step.tolist() == [2]


def test_a_reset_drops_only_the_resetting_ranks_rows():
    cache = ParticleCache()
    assembler = StepAssembler()
    for rank in (0, 1):
        c = Chunk(RUN, 0, 0.0, rank, 2, 0.01, ((0, 0, 0), (1, 1, 1)),
                  {"positions": np.full((2, 3), 0.1 * rank, np.float32)},
                  context_ids=np.array([10 * rank, 10 * rank + 1]),
                  evict_ids=np.zeros(0, np.int64))
        for s in assembler.add(c, 0, 0):
            cache.apply(s)
    assert sorted(cache.ids.tolist()) == [0, 1, 10, 11]
    for rank in (0, 1):
        c = Chunk(RUN, 1, 0.1, rank, 2, 0.01, ((0, 0, 0), (1, 1, 1)),
                  {"positions": np.zeros((0, 3), np.float32)},
                  context_ids=np.zeros(0, np.int64), evict_ids=np.zeros(0, np.int64),
                  context_reset=rank == 1)
        for s in assembler.add(c, 0, 0):
            cache.apply(s)
    assert sorted(cache.ids.tolist()) == [0, 1]


def test_a_step_without_context_is_drawn_as_before():
    cache, assembler = ParticleCache(), StepAssembler()
    (s,) = assembler.add(make_chunk(30, ranks=1), 0, 0)
    done = complete_step(cache, s)
    assert done is s and not done.completed and done.cached == 0


def test_the_server_draws_the_outside_from_its_cache_and_says_so(server, endpoint, tmp_path):
    """A tiny run with a region, the context sent once (a tolerance no motion reaches):
    every rendered frame draws the whole scene, fresh and cached, and its Timing says how
    many came from the cache and that they are as old as the first step."""
    spec = Spec.from_dict(spec_dict(every_steps=20))
    daemon = RenderServer(server, ServerOptions(spec, tmp_path / "frames", None, timeout_s=30.0,
                                                write_png=False))
    timings = Inbox(server, keys.timing(RUN))
    try:
        summary = run_ranks(config(endpoint, tmp_path, 60, context_tolerance_m=1.0),
                            stream=io.StringIO())
        p = summary.publish
        assert p["sent"] == 4 and p["context_resets"] == 1
        assert 0 < p["context_rows"] < summary.particles  # the outside at step 0, once
        assert wait_until(lambda: daemon.finished.is_set())
        got = [decode_as(timings.get(1).payload, Timing) for _ in range(timings.received)]
        later = [t for t in got if t.step > 0]
        assert later, "no frame after the first step rendered"
        for t in got:
            assert t.particles == summary.particles  # fresh + cached: the whole scene
        for t in later:
            assert t.cached > 0
            assert t.cache_age_steps == t.step and t.cache_age_s == pytest.approx(t.time_s)
        last = max(later, key=lambda t: t.step)  # what the rank evicted by then, all of it
        assert last.cached == p["context_rows"] - p["context_evicted"]
    finally:
        timings.close()
        daemon.close()
