"""`minority serve` on N MPI render ranks (render_server.serve_mpi, minority/serve_ranks.py):
a real `minority sim tiny` on 2 ranks against `minority serve --ranks N` on loopback, frames
pixel-identical to one process (N = 1, 2, 3) on every step both rendered, the sharded log
replayed identically to the one-process log; a stuck render rank (SIGSTOP: rank 0 records an
error event, closes its log complete and ends the job), a killed render rank (SIGKILL:
its guard keeps the job alive, rank 0 records the error and closes its log complete) and a
killed rank 0 (the others close their shards and end the job); the
pieces (shard paths and merging, tie keys, shares) in one process.

Each server and sim is a subprocess with bounded waits (process exits, its "serving" line).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_SPEC, free_port, make_chunk, make_spec
from PIL import Image

from minority.protocol.log import LogTruncatedWarning, LogWriter, read_log
from minority.protocol.shards import shard_path, shard_paths
from minority.render_server.assemble import AssembledStep
from minority.render_server.serve_mpi import RankCache, Release, build_share, chunk_keys

TIMEOUT_S = 300
ENV = {**os.environ, "NUMBA_NUM_THREADS": "1"}
SPEC = TINY_SPEC


def start_server(tmp: Path, ranks: int, port: int, *extra: str) -> tuple[subprocess.Popen, str]:
    """`minority serve` (on `ranks` render ranks when > 1), its stderr file, once it serves."""
    (tmp / "spec.json").write_text(json.dumps(SPEC))
    err = tmp / "serve.err"
    cmd = [sys.executable, "-m", "minority", "serve", "--spec", str(tmp / "spec.json"),
           "--out", str(tmp / "out"), "--timeout", "30", "--listen", f"tcp/127.0.0.1:{port}",
           *(["--ranks", str(ranks)] if ranks > 1 else []), *extra]
    proc = subprocess.Popen(cmd, stderr=err.open("w"), env=ENV, start_new_session=True)
    deadline = time.monotonic() + TIMEOUT_S
    while "serving run" not in err.read_text():
        assert proc.poll() is None, err.read_text()[-3000:]
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.2)
    return proc, err.read_text()


def stop(proc: subprocess.Popen) -> None:
    """SIGKILL what is left of a server's process group (mpiexec and its ranks)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def run_sim(tmp: Path, port: int) -> None:
    proc = subprocess.run([sys.executable, "-m", "minority", "sim", "tiny", "--ranks", "2",
                           "--run", "tiny", "--out", str(tmp / "tiny.h5"), "--quiet",
                           "--connect", f"tcp/127.0.0.1:{port}", "--wait", "30"],
                          capture_output=True, text=True, timeout=TIMEOUT_S, env=ENV)
    assert proc.returncode == 0, proc.stderr[-3000:]


def frames(out: Path) -> dict[str, np.ndarray]:
    return {str(p.relative_to(out)): np.asarray(Image.open(p)) for p in out.rglob("*.png")}


@pytest.fixture(scope="module")
def served(tmp_path_factory) -> dict[int, Path]:
    """The same sim run served on 1, 2 and 3 render ranks: each server's directory."""
    runs = {}
    for ranks in (1, 2, 3):
        tmp = tmp_path_factory.mktemp(f"serve{ranks}")
        port = free_port()
        proc, _ = start_server(tmp, ranks, port, "--exit-when-done")
        try:
            run_sim(tmp, port)
            assert proc.wait(TIMEOUT_S) == 0, (tmp / "serve.err").read_text()[-3000:]
        finally:
            stop(proc)
        runs[ranks] = tmp
    return runs


def test_frames_on_2_and_3_ranks_are_pixel_identical_to_one_process(served):
    one = frames(served[1] / "out" / "tiny")
    for ranks in (2, 3):
        got = frames(served[ranks] / "out" / "tiny")
        common = sorted(set(one) & set(got))
        assert common, f"{ranks} ranks rendered no step the one-process server rendered"
        assert any(k.endswith("000000.png") for k in common)
        for name in common:
            diff = np.any(one[name] != got[name], axis=-1)
            assert not diff.any(), f"{ranks} ranks, {name}: {diff.sum()} pixels differ"
        assert all(len(np.unique(f.reshape(-1, 3), axis=0)) > 3 for f in got.values())


def test_rank_0_logs_its_share_and_each_rank_its_shard_read_as_one(served):
    log1, log3 = served[1] / "out" / "tiny.mcap", served[3] / "out" / "tiny.mcap"
    assert shard_paths(log3) == [shard_path(log3, 1), shard_path(log3, 2)]
    assert shard_paths(log1) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every file is complete
        chunks = [r.decode() for r in read_log(log3, ["minority/*/chunk"])]
        own = [r.decode() for r in read_log(shard_path(log3, 1), ["minority/*/chunk"])]
        one = sorted((c.step, c.rank) for c in (r.decode() for r in read_log(
            log1, ["minority/*/chunk"])))
    assert sorted((c.step, c.rank) for c in chunks) == one  # every chunk, once
    assert own and {c.rank % 3 for c in own} == {1}  # render rank 1: sim rank 1's chunks
    timing = [r.decode() for r in read_log(log3, ["minority/*/timing"])]
    assert timing and all(t.ranks_received == 2 and not t.incomplete for t in timing)
    particles = {t.step: t.particles for t in (r.decode() for r in read_log(
        log1, ["minority/*/timing"]))}
    assert all(particles[t.step] == t.particles for t in timing if t.step in particles)


def test_replay_of_the_sharded_log_equals_replay_of_the_one_process_log(served, tmp_path):
    outs = {}
    for ranks in (1, 3):
        outs[ranks] = tmp_path / f"replay{ranks}"
        proc = subprocess.run([sys.executable, "-m", "minority", "replay",
                               str(served[ranks] / "out" / "tiny.mcap"), "--out",
                               str(outs[ranks])], capture_output=True, text=True,
                              timeout=TIMEOUT_S, env=ENV)
        assert proc.returncode == 0, proc.stderr[-3000:]
    one, three = frames(outs[1]), frames(outs[3])
    assert len(one) > 20 and sorted(one) == sorted(three)
    assert all(np.array_equal(one[k], three[k]) for k in one)


def pid_of(text: str, rank: int) -> int:
    pattern = r"rank 0: pid (\d+)" if rank == 0 else rf"render rank {rank}: pid (\d+)"
    return int(re.search(pattern, text).group(1))


def test_a_stuck_render_rank_ends_the_run_with_an_error_event_and_a_complete_log(tmp_path):
    proc, text = start_server(tmp_path, 2, free_port(), "--rank-timeout", "2")
    worker = pid_of(text, 1)
    try:
        os.kill(worker, signal.SIGSTOP)
        status = proc.wait(60)
    finally:
        stop(proc)
    assert status != 0
    assert "render rank 1 sent nothing for 2 s" in (tmp_path / "serve.err").read_text()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        events = [r.decode() for r in read_log(tmp_path / "out" / "tiny.mcap",
                                               ["minority/*/event"])]
    # rank 0's log is complete (only the stuck rank's shard may be cut short)
    assert not [w for w in caught if "tiny.mcap:" in str(w.message)]
    kinds = [e.kind for e in events]
    assert kinds[0] == "run_start" and kinds[-1] == "run_end" and "error" in kinds
    assert any("render rank 1" in e.message for e in events if e.kind == "error")


def kill_when_logging(tmp: Path, victim: int, *extra: str):
    """A 2-rank server, SIGKILL to render rank `victim` once rank 0's log holds the spec;
    the server's exit status, its stderr and both ranks' pids."""
    proc, text = start_server(tmp, 2, free_port(), "--rank-timeout", "2", *extra)
    log = tmp / "out" / "tiny.mcap"
    pids = {rank: pid_of(text, rank) for rank in (0, 1)}
    try:
        deadline = time.monotonic() + 60
        while not logged_specs(log):  # the writer completes its first MCAP chunk (0.5 s)
            assert time.monotonic() < deadline
            time.sleep(0.1)
        os.kill(pids[victim], signal.SIGKILL)
        status = proc.wait(60)
    finally:
        stop(proc)
    for pid in pids.values():  # no rank outlives the job (nor a guarded server its guard)
        assert not Path(f"/proc/{pid}").exists() or "Z" in Path(
            f"/proc/{pid}/stat").read_text().split()[2]
    return status, (tmp / "serve.err").read_text()


def test_a_killed_render_rank_is_recorded_by_rank_0_in_a_complete_log(tmp_path):
    """SIGKILL to rank 1: its guard exits with 137 instead of dying, hydra keeps rank 0
    alive (-disable-auto-cleanup), rank 0's watchdog records the error and closes its log."""
    status, err = kill_when_logging(tmp_path, 1)
    assert status != 0
    assert re.search(r"render rank 1 \(pid \d+\) was killed by SIGKILL", err)
    assert "render rank 1 sent nothing for 2 s" in err
    log = tmp_path / "out" / "tiny.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        events = [r.decode() for r in read_log(log, ["minority/*/event"])]
    assert not [w for w in caught if "tiny.mcap:" in str(w.message)]  # rank 0's log complete
    kinds = [e.kind for e in events]
    assert kinds[0] == "run_start" and kinds[-1] == "run_end"
    assert any("render rank 1" in e.message for e in events if e.kind == "error")


def test_a_killed_rank_0_ends_the_others_and_their_shards_are_complete(tmp_path):
    """SIGKILL to rank 0: rank 1 hears nothing for --rank-timeout, closes its shard and ends
    the job; rank 0's own log reads to its last complete MCAP chunk."""
    status, err = kill_when_logging(tmp_path, 0)
    assert status != 0
    assert re.search(r"render rank 0 \(pid \d+\) was killed by SIGKILL", err)
    log = tmp_path / "out" / "tiny.mcap"
    assert logged_specs(log) == 1
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        list(read_log(shard_path(log, 1)))
    assert not caught, [str(w.message) for w in caught]


def logged_specs(log: Path) -> int:
    if not log.exists():
        return 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LogTruncatedWarning)
        return sum(1 for _ in read_log(log, ["minority/*/spec"]))


# --- the pieces, in one process ------------------------------------------------------
def test_shard_paths_name_the_render_ranks_files_only(tmp_path):
    log = tmp_path / "run.mcap"
    assert shard_path(log, 2) == tmp_path / "run.render2.mcap"
    with pytest.raises(ValueError, match="rank 0 writes the log"):
        shard_path(log, 0)
    for name in ("run.render1.mcap", "run.render10.mcap", "run.render2.mcap",
                 "run.1.render1.mcap", "run.renderx.mcap", "run.render0.mcap"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in shard_paths(log)] == ["run.render1.mcap", "run.render2.mcap",
                                                  "run.render10.mcap"]
    assert shard_paths(tmp_path / "run.1.mcap") == [tmp_path / "run.1.render1.mcap"]


def test_a_log_and_its_shard_read_as_one_in_log_time_order(tmp_path):
    log = tmp_path / "run.mcap"
    with LogWriter(log) as main, LogWriter(shard_path(log, 1)) as shard:
        main.write(make_spec("test-run"), log_ns=10)
        main.write(make_chunk(step=20, rank=0), log_ns=30)
        shard.write(make_chunk(step=20, rank=1), log_ns=20)
        shard.write(make_chunk(step=40, rank=1), log_ns=40)
    got = [(r.log_ns, r.topic) for r in read_log(log)]
    assert [t for t, _ in got] == [10, 20, 30, 40]
    assert [(c.step, c.rank) for c in (r.decode() for r in read_log(
        log, ["minority/*/chunk"]))] == [(20, 1), (20, 0), (40, 1)]


def test_each_render_rank_subscribes_to_its_sim_ranks():
    assert chunk_keys("r", 1, 3, 8) == ["minority/r/chunk/*/1", "minority/r/chunk/*/4",
                                        "minority/r/chunk/*/7"]


def _release(seq: int, step: int, sim_ranks, offsets) -> Release:
    schema = (("displacement", "<f4", (3,)),)
    return Release(seq, step, step * 1e-3, None, 0.01, None, tuple(sim_ranks), offsets, schema,
                   True)


def test_shares_and_keys_follow_the_one_process_rows():
    """Fresh rows keyed by their one-process row; cached rows after every fresh row, in the
    order the one-process cache appends them (release, sim rank, row)."""
    def chunk(rank: int, step: int, n: int, ids: list[int]) -> object:
        c = make_chunk(n=n, step=step, rank=rank, ranks=4, seed=rank + step)
        c.fields = {"positions": c.fields["positions"], "displacement": c.fields["displacement"]}
        c.context_ids = np.array(ids, np.int64)  # the last len(ids) rows are context rows
        c.evict_ids = np.zeros(0, np.int64)
        return c

    cache_a, cache_b = RankCache(), RankCache()  # render rank A: sim ranks 0, 2; B: 1, 3
    first = [chunk(r, 20, 5, [10 * r + 1, 10 * r + 2]) for r in range(4)]
    offsets = {r: 3 * r for r in range(4)}
    a = build_share(_release(0, 20, range(4), offsets), [first[0], first[2]], cache_a)
    b = build_share(_release(0, 20, range(4), offsets), [first[1], first[3]], cache_b)
    assert a.fresh == 6 and list(a.keys[:6]) == [0, 1, 2, 6, 7, 8]
    assert list(b.keys[:6]) == [3, 4, 5, 9, 10, 11]
    second = [chunk(r, 40, 3, [10 * r + 3]) for r in (1, 2)]
    a2 = build_share(_release(1, 40, [1, 2], {1: 0, 2: 2}), [second[1]], cache_a)
    b2 = build_share(_release(1, 40, [1, 2], {1: 0, 2: 2}), [second[0]], cache_b)
    ids = np.concatenate([cache_a.ids, cache_b.ids])
    order = np.argsort(np.concatenate([a2.keys[a2.fresh:], b2.keys[b2.fresh:]]))
    # one process: step 20's context of sim ranks 0..3, then step 40's of sim ranks 1, 2
    assert list(ids[order]) == [1, 2, 11, 12, 21, 22, 31, 32, 13, 23]
    assert min(a2.keys[a2.fresh:]) > 1 << 40 and a2.cached == 5 and b2.cached == 5
    assert isinstance(a2.local, AssembledStep) and len(a2.local.positions) == 2 + 5


def test_a_rank_is_guarded_only_under_a_launcher_of_several_ranks(monkeypatch):
    from minority import rank_guard

    for name in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "SLURM_NTASKS", rank_guard.GUARDED_ENV):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("PMI_SIZE", "1")
    assert not rank_guard.wanted()
    monkeypatch.setenv("PMI_SIZE", "3")
    assert rank_guard.wanted() == sys.platform.startswith("linux")
    monkeypatch.setenv(rank_guard.GUARDED_ENV, "1")  # the guarded child itself
    assert not rank_guard.wanted()


@pytest.mark.parametrize("text, endpoints", [
    ('{mode: "peer", listen: {endpoints: ["tcp/127.0.0.1:17001"]}}', ["tcp/127.0.0.1:17001"]),
    ('{mode: "client", connect: {endpoints: ["tls/head:7448"]}}', []),  # a router's client
])
def test_rank_0_listens_where_its_config_file_says(tmp_path, text, endpoints):
    from minority.protocol.session import NetworkOptions
    from minority.serve_ranks import _config_listen

    (tmp_path / "c.json5").write_text(text)
    assert _config_listen(NetworkOptions(config=tmp_path / "c.json5")) == endpoints


FAILING_RANK = """
import sys
from mpi4py import MPI
import minority.render_server.daemon as daemon
def warm_up():
    if MPI.COMM_WORLD.Get_rank() == 1:
        raise RuntimeError("a fault injected on rank 1")
daemon.warm_up = warm_up
from minority.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_an_unexpected_error_on_one_rank_ends_every_rank(tmp_path):
    """Rank 1 raises before the first barrier: it says so and MPI_Abort ends the job (rank 0
    would otherwise wait for it forever)."""
    from minority.sim.launcher import mpiexec_path

    (tmp_path / "spec.json").write_text(json.dumps(SPEC))
    (tmp_path / "failing.py").write_text(FAILING_RANK)
    env = {**ENV, "MINORITY_RANK_GUARDED": "1"}  # the ranks themselves, no guard
    proc = subprocess.run(
        # -disable-auto-cleanup as `serve --ranks` runs it: hydra alone would not end rank 0
        [str(mpiexec_path()), "-disable-auto-cleanup", "-n", "2", sys.executable,
         str(tmp_path / "failing.py"), "serve",
         "--spec", str(tmp_path / "spec.json"), "--out", str(tmp_path / "out"),
         "--listen", f"tcp/127.0.0.1:{free_port()}"],
        capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode != 0
    assert "a fault injected on rank 1" in proc.stderr
    assert "render rank 1 failed (above): ending every rank" in proc.stderr


@pytest.mark.parametrize("to_group", [False, True])
def test_ctrl_c_stops_every_rank_cleanly(tmp_path, to_group):
    """SIGINT to `serve --ranks 2`, or to its process group as a terminal's Ctrl-C does
    (mpiexec is in a group of its own: a second SIGINT would make hydra abort the ranks):
    passed on through mpiexec and each rank's guard; rank 0 stops the others, every log
    closes complete, exit status 0."""
    proc, text = start_server(tmp_path, 2, free_port())
    try:
        if to_group:
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGINT)
        status = proc.wait(60)
    finally:
        stop(proc)
    assert status == 0, (tmp_path / "serve.err").read_text()[-3000:]
    log = tmp_path / "out" / "tiny.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        kinds = [r.decode().kind for r in read_log(log, ["minority/*/event"])]
    assert not caught, [str(w.message) for w in caught]
    assert kinds[0] == "run_start" and kinds[-1] == "run_end"


def test_a_config_listening_on_port_0_is_refused_on_several_ranks(tmp_path):
    """Rank 0's config listens on an ephemeral port the other ranks cannot know."""
    (tmp_path / "peer.json5").write_text('{mode: "peer", listen: {endpoints: ["tcp/127.0.0.1:0"]},'
                                         ' scouting: {multicast: {enabled: false}}}')
    (tmp_path / "spec.json").write_text(json.dumps(SPEC))
    proc = subprocess.run(
        [sys.executable, "-m", "minority", "serve", "--spec", str(tmp_path / "spec.json"),
         "--out", str(tmp_path / "out"), "--config", str(tmp_path / "peer.json5"),
         "--ranks", "2"], capture_output=True, text=True, timeout=TIMEOUT_S, env=ENV)
    assert proc.returncode != 0
    assert "tcp/127.0.0.1:0 names no port: give --listen with a port" in proc.stderr
