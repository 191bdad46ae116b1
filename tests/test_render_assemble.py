"""Step assembly: complete, incomplete by death or timeout, bounded, duplicates and late."""

import numpy as np
from conftest import make_chunk

from minority.render_server.assemble import StepAssembler

MS = 1_000_000


def chunk(step, rank, ranks=3, n=10, sent_ns=0):
    c = make_chunk(n=n, step=step, rank=rank, ranks=ranks, seed=step * 10 + rank)
    c.sent_ns = sent_ns
    return c


def test_complete_when_every_rank_arrived():
    a = StepAssembler()
    assert a.add(chunk(20, 1), 0, 100) == []
    assert a.add(chunk(20, 0), 1 * MS, 100) == []
    (done,) = a.add(chunk(20, 2), 3 * MS, 100)
    assert done.step == 20 and not done.incomplete and done.ranks_received == 3
    assert done.positions.shape == (30, 3) and done.nbytes == 300
    assert abs(done.receive_s - 0.003) < 1e-12
    np.testing.assert_array_equal(done.positions[:10], chunk(20, 0).positions)  # rank order
    assert set(done.fields) == {"displacement", "velocity_magnitude", "material"}


def test_dead_rank_releases_incomplete_step():
    a = StepAssembler()
    a.add(chunk(40, 0), 0, 1)
    a.add(chunk(40, 1), 0, 1)
    (done,) = a.rank_gone(2, 5 * MS)
    assert done.incomplete and done.ranks_received == 2
    (later,) = a.add(chunk(60, 0), 6 * MS, 1) + a.add(chunk(60, 1), 6 * MS, 1)
    assert later.step == 60 and later.incomplete  # rank 2 is gone for good


def test_timeout_releases_incomplete():
    a = StepAssembler(timeout_s=1.0)
    a.add(chunk(20, 0), 0, 1)
    assert a.expire(999 * MS) == []
    (done,) = a.expire(1000 * MS)
    assert done.incomplete and a.stats.timed_out == 1


def test_bounded_pending_and_late_and_duplicates():
    a = StepAssembler(max_pending=2)
    a.add(chunk(1, 0), 0, 1)
    a.add(chunk(2, 0), 0, 1)
    (evicted,) = a.add(chunk(3, 0), 0, 1)
    assert evicted.step == 1 and evicted.incomplete and a.stats.evicted == 1
    assert a.add(chunk(1, 1), 0, 1) == [] and a.stats.late == 1
    assert a.add(chunk(2, 0), 0, 1) == [] and a.stats.duplicates == 1
    assert len(a.pending) == 2


def test_fields_missing_on_one_rank_are_left_out():
    a = StepAssembler()
    c0, c1 = chunk(5, 0, ranks=2), chunk(5, 1, ranks=2)
    del c1.fields["material"]
    a.add(c0, 0, 1)
    (done,) = a.add(c1, 0, 1)
    assert "material" not in done.fields and done.fields["displacement"].shape == (20, 3)


def test_receive_time_counts_from_the_earliest_send():
    a = StepAssembler()
    a.add(chunk(20, 0, ranks=2, sent_ns=10 * MS), 12 * MS, 1)
    (done,) = a.add(chunk(20, 1, ranks=2, sent_ns=9 * MS), 15 * MS, 1)
    assert abs(done.receive_s - 0.006) < 1e-12  # 15 ms - 9 ms
    (skewed,) = a.add(chunk(40, 0, ranks=1, sent_ns=99 * MS), 20 * MS, 1)  # future stamp: skew
    assert skewed.receive_s == 0.0  # falls back to the arrival time


def test_previous_step_time_is_carried():
    a = StepAssembler()
    first, second = chunk(20, 1, ranks=2), chunk(20, 0, ranks=2)
    first.prev_time_s = 0.0019  # every rank reports the same; one of them may not know it
    (done,) = a.add(first, 0, 1) + a.add(second, 0, 1)
    assert done.prev_time_s == 0.0019
    (done,) = a.add(chunk(40, 0, ranks=1), 0, 1)
    assert done.prev_time_s is None


def test_drain_releases_what_is_pending():
    a = StepAssembler()
    a.add(chunk(60, 0, ranks=2), 0, 1)
    a.add(chunk(40, 0, ranks=2), 0, 1)
    done = a.drain(0)
    assert [d.step for d in done] == [40, 60] and all(d.incomplete for d in done)
    assert a.pending == {}


def test_fields_whose_ranks_disagree_on_shape_or_dtype_are_left_out():
    a = StepAssembler()
    c0, c1 = chunk(5, 0, ranks=2), chunk(5, 1, ranks=2)
    c1.fields["displacement"] = np.ascontiguousarray(c1.fields["displacement"][:, 0])
    c1.fields["material"] = c1.fields["material"].astype(np.float64)
    a.add(c0, 0, 1)
    (done,) = a.add(c1, 0, 1)
    assert "displacement" not in done.fields and "material" not in done.fields
    assert done.positions.shape == (20, 3) and a.stats.mismatched_fields == 2


def test_an_absurd_step_does_not_hide_the_steps_after_it():
    a = StepAssembler(timeout_s=1.0)
    a.add(chunk(2**40, 0, ranks=1), 0, 1)  # released at once (one rank)
    for step in (0, 1, 2):
        (done,) = a.add(chunk(step, 0, ranks=1), MS, 1)
        assert done.step == step and not done.incomplete
    assert a.stats.late == 0
    assert a.add(chunk(1, 0, ranks=1), MS, 1) == [] and a.stats.late == 1  # released: late


def test_steps_older_than_the_remembered_releases_are_late():
    from minority.render_server.assemble import RELEASED_WINDOW

    a = StepAssembler()
    for step in range(10, 10 + RELEASED_WINDOW + 5):
        a.add(chunk(step, 0, ranks=1), 0, 1)
    assert a.add(chunk(3, 0, ranks=1), 0, 1) == [] and a.stats.late == 1
    assert a.is_late(14) and not a.is_late(10 + RELEASED_WINDOW + 5)


def test_a_backlog_arriving_one_rank_after_the_other_assembles_every_step():
    """After a pause each rank's backlog arrives separately: every step waits for its last
    rank instead of being released with one rank's particles."""
    a = StepAssembler()
    steps = range(0, 550, 10)  # 55 steps
    assert all(a.add(chunk(s, 0, ranks=2), 0, 1000) == [] for s in steps)
    done = [d for s in steps for d in a.add(chunk(s, 1, ranks=2), MS, 1000)]
    assert [d.step for d in done] == list(steps)
    assert not any(d.incomplete for d in done) and a.stats.evicted == 0


def test_pending_bytes_are_bounded():
    a = StepAssembler(max_pending_bytes=2500)
    a.add(chunk(1, 0), 0, 1000)
    a.add(chunk(2, 0), 0, 1000)
    (evicted,) = a.add(chunk(3, 0), 0, 1000)
    assert evicted.step == 1 and evicted.incomplete and a.pending_bytes == 2000

