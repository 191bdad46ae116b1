"""What the render server must not lose: a rank killed before its done event, names that
two servers (or a server and an earlier run) would share, a message that comes after a run
ended, chunks still queued when the server stops. Waits are on events and counts."""

import subprocess
import sys
import threading
import warnings

import pytest
from conftest import make_chunk
from test_loopback import TIMEOUT_S, wait_until
from test_render_daemon import RUN, done_event, send_step, spec

from minority.protocol import Event, EventKind, keys
from minority.protocol.log import read_log
from minority.protocol.session import LOSSLESS_QOS, NetworkOptions, Role, open_session, put
from minority.render_server.daemon import RenderServer, ServerOptions
from minority.render_server.runs import claim_frames_dir, open_writer


@pytest.fixture
def daemon(render_server_of):
    return render_server_of(spec())


def events_of(log) -> list[Event]:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the log is complete
        return [r.decode() for r in read_log(log, [keys.event(RUN)])]


def test_a_rank_that_vanishes_without_its_done_event_is_named_as_lost(daemon, client_factory,
                                                                       tmp_path):
    sim, doomed = client_factory(), client_factory()
    token0 = sim.liveliness().declare_token(keys.rank_token(RUN, 0))
    token1 = doomed.liveliness().declare_token(keys.rank_token(RUN, 1))
    send_step(sim, 0, ranks=2)
    assert wait_until(lambda: daemon.stats.chunks == 2)
    put(sim, keys.event(RUN), done_event(0, 1), LOSSLESS_QOS)  # rank 0 ends as it should
    token0.undeclare()
    del token1
    doomed.close()  # rank 1 is killed: its token vanishes, no done event
    assert daemon.finished.wait(TIMEOUT_S)
    assert daemon.summary()["ranks_lost"] == [1]
    assert daemon.failures() and "rank(s) 1 vanished" in daemon.failures()[0]
    daemon.close()
    events = events_of(tmp_path / "run.mcap")
    errors = [e for e in events if e.kind == EventKind.ERROR]
    assert any("rank 1" in e.message and "without its done event" in e.message for e in errors)
    end = events[-1]
    assert end.kind == EventKind.RUN_END and "failures" in end.message
    assert end.detail["ranks_lost"] == [1]


def test_a_run_whose_ranks_all_said_done_has_no_failures(daemon, client_factory):
    sim = client_factory()
    token = sim.liveliness().declare_token(keys.rank_token(RUN, 0))
    send_step(sim, 0, ranks=1)
    put(sim, keys.event(RUN), done_event(0, 1), LOSSLESS_QOS)
    token.undeclare()
    assert daemon.finished.wait(TIMEOUT_S)
    assert daemon.failures() == [] and daemon.summary()["ranks_lost"] == []


def test_record_file_is_honoured_whatever_frame_folders_exist(server, tmp_path):
    """A fresh server told --record FILE (no such file) writes FILE, even though the run's
    frame folder exists from an earlier server; the frames take the next free folder."""
    (tmp_path / "frames" / RUN).mkdir(parents=True)
    log = tmp_path / "second.mcap"
    d = RenderServer(server, ServerOptions(spec(), tmp_path / "frames", log))
    try:
        assert d.current.writer.path == log
        assert d.current.frames_dir == tmp_path / "frames" / f"{RUN}.1"
        assert d.current.name == f"{RUN}.1"
    finally:
        d.close()
    assert log.exists() and not (tmp_path / "second.1.mcap").exists()


def test_an_existing_record_file_is_kept_and_the_next_free_name_taken(server, tmp_path, capfd):
    log = tmp_path / "run.mcap"
    log.write_bytes(b"an earlier run's log")
    d = RenderServer(server, ServerOptions(spec(), tmp_path / "frames", log))
    try:
        assert d.current.writer.path == tmp_path / "run.1.mcap"
        assert d.current.frames_dir == tmp_path / "frames" / RUN  # free: taken as it is
    finally:
        d.close()
    assert log.read_bytes() == b"an earlier run's log"
    assert "run.1.mcap" in capfd.readouterr().err


def test_two_servers_without_a_log_on_one_out_write_separate_folders(server, tmp_path):
    out = tmp_path / "frames"
    a = RenderServer(server, ServerOptions(spec(), out, None))
    try:
        b = RenderServer(server, ServerOptions(spec(), out, None))
        b.close()
    finally:
        a.close()
    assert a.current.frames_dir != b.current.frames_dir
    assert {a.current.frames_dir.name, b.current.frames_dir.name} == {RUN, f"{RUN}.1"}


@pytest.mark.parametrize("claim", ["frames", "log"])
def test_names_claimed_at_the_same_instant_are_all_different(tmp_path, claim):
    """Eight threads claim at once (as eight servers started together): eight names, no
    FileExistsError, nothing shared."""
    start, got, errors = threading.Barrier(8), [], []

    def one():
        start.wait()
        try:
            if claim == "frames":
                got.append(claim_frames_dir(tmp_path / "out", RUN))
            else:
                w = open_writer(tmp_path / "run.mcap", RUN, RUN)
                got.append(w.path)
                w.close()
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(exc)

    threads = [threading.Thread(target=one) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(set(got)) == 8


def test_a_malformed_message_after_a_run_ended_is_not_written_to_its_closed_log(
        daemon, client_factory, tmp_path, capfd):
    sim = client_factory()
    send_step(sim, 0, ranks=1)
    put(sim, keys.event(RUN), done_event(0, 1), LOSSLESS_QOS)
    assert daemon.finished.wait(TIMEOUT_S)
    sim.put(keys.event(RUN), b"\x00garbage")  # after the run ended
    assert wait_until(lambda: daemon.between_runs == 1)
    daemon.close()
    err = capfd.readouterr().err
    assert "malformed event" in err and "closed file" not in err
    assert daemon.current.writer.failure == ""
    events = events_of(tmp_path / "run.mcap")
    assert events[-1].kind == EventKind.RUN_END  # the log ends with its run


def test_chunks_still_queued_at_a_stop_are_logged_and_counted(server, client_factory, tmp_path):
    """The receive thread is held while a rank's chunks arrive; the server then stops: every
    chunk the rank sent is in exactly one count, and the queued ones are in the log."""
    d = RenderServer(server, ServerOptions(spec(), tmp_path / "frames", tmp_path / "run.mcap",
                                           inbox_capacity=4))
    held, release = threading.Event(), threading.Event()
    receive = d._receive

    def held_receive(item):
        if item is not None and not release.is_set():
            held.set()
            release.wait(TIMEOUT_S)
        receive(item)

    d._receive = held_receive
    sim = client_factory()
    for step in range(10):
        put(sim, keys.chunk(RUN, step, 0), make_chunk(n=10, step=step, rank=0, ranks=1,
                                                      run=RUN).encode(), LOSSLESS_QOS)
    put(sim, keys.event(RUN), Event(RUN, EventKind.RANK_DONE, 0, "done", {"sent": 10}).encode(),
        LOSSLESS_QOS)
    assert held.wait(TIMEOUT_S)
    assert wait_until(lambda: d._inbox.received == 10)
    closing = threading.Thread(target=d.close)  # the stop comes while the thread is held
    closing.start()
    assert wait_until(d._stop.is_set)
    release.set()
    closing.join(TIMEOUT_S)
    assert not closing.is_alive()
    s = d.summary()
    assert s["queued_at_stop"] > 0
    assert s["chunks"] + s["inbox_dropped"] + s["queued_at_stop"] + s["lost_in_transit"] == 10
    logged = [r for r in read_log(tmp_path / "run.mcap") if r.topic.endswith("/chunk")]
    assert len(logged) == s["chunks"] + s["queued_at_stop"]


def test_serve_exit_when_done_exits_1_when_a_rank_was_killed(endpoint, tmp_path):
    """`minority serve --exit-when-done`, a rank that sends and then vanishes (its session
    closed without a done event, as a SIGKILL leaves it): the server exits 1 naming it."""
    spec().save(tmp_path / "spec.json")
    server = subprocess.Popen(
        [sys.executable, "-m", "minority", "serve", "--spec", str(tmp_path / "spec.json"),
         "--out", str(tmp_path / "out"), "--listen", endpoint, "--exit-when-done"],
        stderr=subprocess.PIPE, text=True)
    try:
        rank = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=30),
                            Role.CLIENT)
        assert wait_until(lambda: len(list(rank.get(keys.spec(RUN), timeout=1))) > 0)
        token = rank.liveliness().declare_token(keys.rank_token(RUN, 0))
        send_step(rank, 0, ranks=1)
        del token
        rank.close()  # killed: no done event
        _, err = server.communicate(timeout=60)
    finally:
        server.kill()
    assert server.returncode == 1, err
    assert "rank(s) 0 vanished without their done event" in err
    assert "every run has ended, not all as it should" in err
