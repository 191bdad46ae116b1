"""The render server over loopback: spec served, steps assembled and rendered, frames and
timing published and logged; malformed and degenerate input counted, never fatal; a rank
killed mid-step releases the step as incomplete. Waits are on message counts."""

import queue
import threading
import warnings

import numpy as np
import pytest
from conftest import make_chunk
from test_loopback import TIMEOUT_S, wait_until

from minority.protocol import Frame, Spec, Timing, decode_as, keys
from minority.protocol.log import read_log
from minority.protocol.session import LOSSLESS_QOS, Inbox, put
from minority.render_server.daemon import RenderServer, ServerOptions

RUN = "test-run"


class EveryStep:
    """A mailbox for the daemon's render thread that keeps every step, in order (tests that
    need every frame swap it in for the newest-wins `LatestStep`)."""

    replaced = 0

    def __init__(self):
        self._queue = queue.Queue()

    def put(self, step) -> None:
        self._queue.put(step)

    def take(self, timeout: float):
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def empty(self) -> bool:
        return self._queue.empty()


def spec() -> Spec:
    return Spec.from_dict({"version": 1, "run": RUN, "views": [{
        "name": "side", "camera": {"position": [0.5, -2.0, 0.5], "focal_point": [0.5, 0.5, 0.5]},
        "width": 64, "height": 48, "field": "displacement", "range": [0, 1], "every_steps": 20}]})


@pytest.fixture
def daemon(render_server_of):
    return render_server_of(spec())


def send_step(session, step, ranks=2, n=50, **kw):
    for rank in range(ranks):
        chunk = make_chunk(n=n, step=step, rank=rank, ranks=ranks, seed=step + rank, run=RUN, **kw)
        put(session, keys.chunk(RUN, step, rank), chunk.encode(), LOSSLESS_QOS)


def test_spec_frames_timing_and_log(daemon, client_factory, tmp_path):
    sim = client_factory()
    replies = list(sim.get(keys.spec(RUN), timeout=10))
    assert decode_as(replies[0].ok.payload.to_bytes(), Spec) == spec()
    frames, timing = Inbox(sim, keys.frames(RUN)), Inbox(sim, keys.timing(RUN))
    for k, step in enumerate([0, 20, 40]):
        send_step(sim, step)
        assert wait_until(lambda k=k: frames.received == k + 1)
    send_step(sim, 50)  # not scheduled: assembled, not rendered
    assert wait_until(lambda: timing.received == 3)
    got = [decode_as(frames.get(1).payload, Frame) for _ in range(3)]
    assert [f.step for f in got] == [0, 20, 40] and all(f.view == "side" for f in got)
    t = decode_as(timing.get(1).payload, Timing)
    assert t.particles == 100 and t.ranks_received == 2 and not t.incomplete and t.render_s > 0
    assert sorted(p.name for p in (tmp_path / "frames" / RUN / "side").iterdir()) == \
        ["000000.png", "000020.png", "000040.png"]
    assert wait_until(lambda: daemon.stats.chunks == 8)
    daemon.close()
    topics = [r.topic for r in read_log(tmp_path / "run.mcap")]
    assert topics.count(f"minority/{RUN}/chunk") == 8
    assert topics.count(f"minority/{RUN}/frame/side") == 3
    assert topics.count(f"minority/{RUN}/timing") == 3
    events = [r.decode().kind for r in read_log(tmp_path / "run.mcap", [f"minority/{RUN}/event"])]
    assert events[0] == "run_start" and events[-1] == "run_end"


def test_bad_and_degenerate_input_is_survived(daemon, client_factory):
    sim = client_factory()
    frames = Inbox(sim, keys.frames(RUN))
    sim.put(keys.chunk(RUN, 20, 0), b"not a chunk at all")  # a raw, hostile sender
    nan = make_chunk(n=10, step=20, rank=0, ranks=1, run=RUN)
    nan.fields["positions"][3] = np.nan
    put(sim, keys.chunk(RUN, 20, 0), nan.encode(), LOSSLESS_QOS)
    assert wait_until(lambda: daemon.stats.rejected == 2)
    send_step(sim, 20, ranks=1, n=0)  # zero particles: the view's background
    assert wait_until(lambda: frames.received == 1)  # (newest wins: one step at a time)
    send_step(sim, 40, ranks=1, n=1)  # one particle
    assert wait_until(lambda: frames.received == 2)
    same = make_chunk(n=30, step=60, rank=0, ranks=1, run=RUN)
    same.fields["positions"][:] = 0.5  # every particle at one point
    put(sim, keys.chunk(RUN, 60, 0), same.encode(), LOSSLESS_QOS)
    assert wait_until(lambda: frames.received == 3)
    assert daemon.stats.steps_rendered == 3 and daemon.stats.rejected == 2
    assert daemon.stats.view_errors == 0


def test_rank_killed_mid_step_releases_incomplete_step(daemon, client_factory):
    sim, doomed = client_factory(), client_factory()
    timing = Inbox(sim, keys.timing(RUN))
    token = doomed.liveliness().declare_token(keys.rank_token(RUN, 1))
    send_step(sim, 20, ranks=2)  # both ranks' chunks: complete
    assert wait_until(lambda: timing.received == 1)
    chunk = make_chunk(n=40, step=40, rank=0, ranks=2, run=RUN)
    put(sim, keys.chunk(RUN, 40, 0), chunk.encode(), LOSSLESS_QOS)
    assert wait_until(lambda: daemon.stats.chunks == 3)
    del token
    doomed.close()  # rank 1 dies before sending step 40
    assert wait_until(lambda: timing.received == 2)
    t = [decode_as(timing.get(1).payload, Timing) for _ in range(2)]
    assert not t[0].incomplete and t[1].incomplete and t[1].ranks_received == 1
    assert t[1].particles == 40


def test_minority_serve_runs_until_sigterm(endpoint, tmp_path):
    import signal
    import subprocess
    import sys

    from minority.protocol.session import NetworkOptions, Role, open_session

    spec().save(tmp_path / "spec.json")
    proc = subprocess.Popen([sys.executable, "-m", "minority", "serve", "--spec",
                             str(tmp_path / "spec.json"), "--out", str(tmp_path / "out"),
                             "--listen", endpoint], stderr=subprocess.PIPE, text=True)
    sim = None
    try:
        sim = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=30), Role.CLIENT)
        frames = Inbox(sim, keys.frames(RUN))
        assert wait_until(lambda: len(list(sim.get(keys.spec(RUN), timeout=1))) > 0)
        send_step(sim, 20)
        assert wait_until(lambda: frames.received == 1)
    finally:
        if sim is not None:
            sim.close()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "'frames': 1" in err
    assert (tmp_path / "out" / RUN / "side" / "000020.png").exists()
    log = tmp_path / "out" / f"{RUN}.mcap"
    assert sum(1 for r in read_log(log) if r.topic.endswith("/frame/side")) == 1


def test_newest_step_wins_when_rendering_falls_behind(server, client_factory, tmp_path):
    every_step = Spec.from_dict({**spec().to_dict(),
                                 "views": [{**spec().views[0].to_dict(),
                                            "schedule": [{"every_steps": 1}]}]})
    daemon = RenderServer(server, ServerOptions(every_step, tmp_path, None, timeout_s=30.0,
                                                write_png=False))
    gate = threading.Event()  # holds the render thread, as a slow render would
    render_step = daemon.render_step

    def slow_render(step):
        gate.wait(TIMEOUT_S)
        render_step(step)

    daemon.render_step = slow_render
    try:
        sim = client_factory()
        for step in range(1, 31):
            send_step(sim, step, ranks=1, n=20)
        assert wait_until(lambda: daemon.stats.chunks == 30)
        gate.set()
        assert wait_until(lambda: daemon.summary()["steps_rendered"]
                          + daemon.summary()["steps_skipped"] == 30)
        s = daemon.summary()
        # the step the render thread held, then only the newest: 28 or 29 skipped
        assert s["steps_rendered"] in (1, 2) and s["inbox_dropped"] == 0
        assert daemon.stats.frames == s["steps_rendered"]
    finally:
        daemon.close()


def test_every_s_schedule_uses_the_chunks_previous_step_time(server, client_factory, tmp_path):
    timed = Spec.from_dict({**spec().to_dict(),
                            "views": [{**spec().views[0].to_dict(),
                                       "schedule": [{"every_s": 0.01}]}]})
    daemon = RenderServer(server, ServerOptions(timed, tmp_path, None, timeout_s=30.0))
    daemon._latest = EveryStep()  # no step may be skipped here
    try:
        sim = client_factory()
        timing = Inbox(sim, keys.timing(RUN))
        dt = 0.003
        for step in range(1, 9):  # t = 0.003 .. 0.024 s: the instants 0.01 and 0.02 s
            chunk = make_chunk(n=20, step=step, rank=0, ranks=1, run=RUN)
            chunk.time_s, chunk.prev_time_s = step * dt, (step - 1) * dt
            put(sim, keys.chunk(RUN, step, 0), chunk.encode(), LOSSLESS_QOS)
        assert wait_until(lambda: timing.received == 2)
        steps = sorted(decode_as(timing.get(1).payload, Timing).step for _ in range(2))
        assert steps == [4, 7]  # 0.012 s from 0.009 s, 0.021 s from 0.018 s
    finally:
        daemon.close()


def test_finished_after_every_rank_is_done_and_the_last_step_rendered(daemon, client_factory):
    from minority.protocol import Event, EventKind

    sim = client_factory()
    frames, timing = Inbox(sim, keys.frames(RUN)), Inbox(sim, keys.timing(RUN))
    send_step(sim, 0)
    assert wait_until(lambda: frames.received == 1)
    send_step(sim, 20, ranks=2)
    chunk = make_chunk(n=50, step=40, rank=0, ranks=2, seed=1, run=RUN)  # rank 1 never sends it
    put(sim, keys.chunk(RUN, 40, 0), chunk.encode(), LOSSLESS_QOS)
    assert wait_until(lambda: daemon.stats.chunks == 5)
    assert not daemon.finished.is_set()
    put(sim, keys.event(RUN), Event(RUN, EventKind.RANK_DONE, 0, "done").encode(), LOSSLESS_QOS)
    assert not daemon.finished.wait(0.3)  # rank 1 is still running
    put(sim, keys.event(RUN), Event(RUN, EventKind.RANK_DONE, 1, "done").encode(), LOSSLESS_QOS)
    assert daemon.finished.wait(TIMEOUT_S)
    assert wait_until(lambda: timing.received >= 2)
    last = [decode_as(timing.get(1).payload, Timing) for _ in range(timing.received)][-1]
    assert last.step == 40 and last.incomplete and last.ranks_received == 1


def test_a_done_event_that_overtakes_the_ranks_last_chunk_waits_for_it(daemon, client_factory):
    """rank_done travels at a higher priority than the chunks: the rank counts as gone only
    once the chunks its event counts have arrived, so its last step is rendered whole."""
    from minority.protocol import Event, EventKind

    sim = client_factory()
    timing = Inbox(sim, keys.timing(RUN))
    send_step(sim, 0)
    assert wait_until(lambda: timing.received == 1)
    one = make_chunk(n=50, step=20, rank=1, ranks=2, seed=21, run=RUN)
    put(sim, keys.chunk(RUN, 20, 1), one.encode(), LOSSLESS_QOS)
    put(sim, keys.event(RUN), Event(RUN, EventKind.RANK_DONE, 0, "done", {"sent": 2}).encode(),
        LOSSLESS_QOS)  # rank 0 says it sent 2 chunks; the server has 1 of them so far
    assert wait_until(lambda: daemon.stats.chunks == 3)
    assert timing.received == 1  # step 20 still waits for rank 0
    zero = make_chunk(n=50, step=20, rank=0, ranks=2, seed=20, run=RUN)
    put(sim, keys.chunk(RUN, 20, 0), zero.encode(), LOSSLESS_QOS)
    assert wait_until(lambda: timing.received == 2)
    timing.get(1)
    t = decode_as(timing.get(1).payload, Timing)
    assert t.step == 20 and t.ranks_received == 2 and not t.incomplete and t.particles == 100


def test_ranks_disagreeing_on_a_field_and_an_unwritable_frame_dir_are_survived(
        server, client_factory, tmp_path):
    blocker = tmp_path / "frames"
    blocker.write_text("a file where the frame directory should be")
    d = RenderServer(server, ServerOptions(spec(), blocker, None, timeout_s=30.0))
    try:
        sim = client_factory()
        frames = Inbox(sim, keys.frames(RUN))
        for rank in range(2):  # rank 1 sends displacement as [n], rank 0 as [n, 3]
            c = make_chunk(n=50, step=20, rank=rank, ranks=2, seed=rank, run=RUN)
            if rank == 1:
                c.fields["displacement"] = np.ascontiguousarray(c.fields["displacement"][:, 0])
            put(sim, keys.chunk(RUN, 20, rank), c.encode(), LOSSLESS_QOS)
        assert wait_until(lambda: d.stats.view_errors == 1)  # left out: the view cannot draw
        send_step(sim, 40)
        assert wait_until(lambda: frames.received == 1)  # published, its PNG not written
        assert d.stats.write_errors == 1 and d.summary()["mismatched_fields"] == 1
        assert d.stats.frames == 1 and "cannot write" in d.stats.last_error
    finally:
        d.close()


def test_an_older_step_never_replaces_a_newer_one_waiting():
    from minority.render_server.daemon import LatestStep

    slot = LatestStep()
    newer, older = make_step(11), make_step(10)
    slot.put(newer)
    slot.put(older)  # released late by another thread
    assert slot.take(0.1) is newer and slot.replaced == 1
    slot.put(older)
    slot.put(newer)
    assert slot.take(0.1) is newer and slot.replaced == 2


def make_step(step: int):
    from minority.render_server.assemble import AssembledStep

    return AssembledStep(step, 0.001 * step, np.zeros((1, 3), np.float32), {}, 0.01, 1, 1, 0,
                         0.0, False)


def done_event(rank: int, sent: int | None = None) -> bytearray:
    from minority.protocol import Event, EventKind

    return Event(RUN, EventKind.RANK_DONE, rank, "done",
                 {} if sent is None else {"sent": sent}).encode()


def test_the_same_run_id_runs_again_with_its_own_state_log_and_frames(daemon, client_factory,
                                                                       tmp_path):
    """A run that ended (every rank done) and a second run with the same id: the second is
    rendered from step 0 (its steps are not 'late'), into frames/{run}.1/ and run.1.mcap."""
    daemon._latest = EveryStep()  # every frame counted
    sim = client_factory()
    timing = Inbox(sim, keys.timing(RUN))
    for step in (0, 20, 2**40):  # an absurd step in the first run hides nothing after it
        send_step(sim, step, ranks=1)
    for rank in (0,):
        put(sim, keys.event(RUN), done_event(rank, 3), LOSSLESS_QOS)
    assert daemon.finished.wait(TIMEOUT_S)
    assert wait_until(lambda: timing.received >= 2)
    first = daemon.summary()
    for step in (0, 20):
        send_step(sim, step, ranks=1)
    assert wait_until(lambda: daemon.stats.chunks == 2 and daemon.stats.frames == 2), \
        daemon.summary()
    second = daemon.summary()
    assert first["name"] == RUN and second["name"] == f"{RUN}.1"
    assert second["late"] == 0 and second["rejected"] == 0
    put(sim, keys.event(RUN), done_event(0, 2), LOSSLESS_QOS)
    assert daemon.finished.wait(TIMEOUT_S)
    daemon.close()
    frames = tmp_path / "frames"
    assert sorted(p.name for p in (frames / f"{RUN}.1" / "side").iterdir()) == \
        ["000000.png", "000020.png"]
    assert (frames / RUN / "side" / "000000.png").exists()
    for log, chunks in ((tmp_path / "run.mcap", 3), (tmp_path / "run.1.mcap", 2)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # complete, undamaged
            records = list(read_log(log))
        topics = [r.topic for r in records]
        assert topics[0] == f"minority/{RUN}/spec" and topics.count(f"minority/{RUN}/chunk") == chunks
        events = [r.decode() for r in records if r.topic.endswith("/event")]
        assert [e.kind for e in events] == ["run_start", "rank_done", "run_end"]
        assert events[-1].detail["lost_in_transit"] == 0


def test_chunks_a_rank_sent_that_never_came_are_counted_lost(daemon, client_factory):
    sim = client_factory()
    send_step(sim, 0, ranks=1)
    assert wait_until(lambda: daemon.stats.chunks == 1)
    token = sim.liveliness().declare_token(keys.rank_token(RUN, 0))
    put(sim, keys.event(RUN), done_event(0, 5), LOSSLESS_QOS)  # says 5, the server has 1
    token.undeclare()  # it is gone: the server waits timeout_s for the 4 others, then ends
    daemon.options.timeout_s = 0.1
    assert daemon.finished.wait(TIMEOUT_S)
    s = daemon.summary()
    assert s["lost_in_transit"] == 4 and s["missing_by_rank"] == {"0": 4}


def test_frames_and_timing_forged_by_another_peer_are_not_logged(daemon, client_factory,
                                                                 tmp_path):
    sim, forger = client_factory(), client_factory()
    frames = Inbox(sim, keys.frames(RUN))
    forged = Timing(RUN, 99, "side", render_s=1e6)
    put(forger, keys.timing(RUN), forged.encode(), LOSSLESS_QOS)
    send_step(sim, 0)
    assert wait_until(lambda: frames.received == 1)
    daemon.close()
    steps = [r.decode().step for r in read_log(tmp_path / "run.mcap", [f"minority/{RUN}/timing"])]
    assert steps == [0]


def test_an_idle_server_does_not_revisit_every_rank_a_header_named(daemon, client_factory):
    """One valid chunk naming 2**20 ranks: each idle poll must not build a set of them."""
    import tracemalloc

    sim = client_factory()
    chunk = make_chunk(n=5, step=1, rank=0, ranks=2**20, run=RUN)
    put(sim, keys.chunk(RUN, 1, 0), chunk.encode(), LOSSLESS_QOS)
    assert wait_until(lambda: daemon.stats.chunks == 1)
    tracemalloc.start()
    try:
        for _ in range(20):
            daemon._receive(None)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20  # bytes; a set of 2**20 ranks is over 32 MiB


def test_warm_up_compiles_the_kernels_a_large_step_needs():
    """A step large enough for several bricks runs the k-d split kernels; the server's warm-up
    runs them too, so its first large step does not pay numba's compile (5.8 s at 100k)."""
    from minority.render_server import bricks
    from minority.render_server.daemon import warm_up

    warm_up()
    for kernel in (bricks._kd_level, bricks._classify, bricks._sort_by_leaf):
        assert kernel.signatures, kernel.__name__
