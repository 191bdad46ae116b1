"""Soak (slow): one render server, 5 runs at once, then 50 runs of one run id in a row, with
hostile input interleaved — fuzzed chunks, a rank killed mid-run, a peer without the
server's password, names that would escape --out, a server restart (a killed one:
tests/test_serve_runs.py). Afterwards every log opens with mcap's own
reader, every run has each scheduled frame or a counted reason (an incomplete step, with the
ranks it lacked), traced memory is back at its baseline, and nothing was written outside
--out. Then what the daemon must not lose: two servers on one --out, a flood of idle
connections, a squatter on an endpoint without a password file, killed ranks, a full disk;
afterwards every log opens with mcap's reader and every chunk sent is in exactly one count.
Loopback only; waits are on messages and events, never on sleep."""

import json
import random
import socket
import tracemalloc

import pytest
import zenoh
from conftest import fill, free_port, make_chunk
from mcap.reader import make_reader
from test_auth import Squatter
from test_loopback import TIMEOUT_S, wait_until
from test_render_daemon import EveryStep, spec

from minority.protocol import Event, EventKind, Spec, Timing, keys
from minority.protocol.auth import CredentialsError
from minority.protocol.session import LOSSLESS_QOS, NetworkOptions, Role, open_session, put
from minority.render_server.daemon import RenderServer, ServerOptions

pytestmark = pytest.mark.slow

STEPS = (0, 20, 40)  # scheduled (every_steps 20)
RANKS = 2


def spec_for(run: str) -> Spec:
    return Spec.from_dict({**spec().to_dict(), "run": run})


def one_run(sim, run: str, rng: random.Random | None, kill_rank: bool, n: int = 40) -> int:
    """A 2-rank run: its tokens, its chunks of n particles (rank 1 dies before its last one
    when `kill_rank`), fuzzed chunks in between (none without `rng`), done events with the
    counts sent. Returns the chunks the ranks sent."""
    tokens = [sim.liveliness().declare_token(keys.rank_token(run, r)) for r in range(RANKS)]
    sent = [0] * RANKS
    for step in STEPS:
        for rank in range(RANKS):
            if kill_rank and rank == 1 and step == STEPS[-1]:
                continue
            chunk = make_chunk(n=n, step=step, rank=rank, ranks=RANKS, seed=step + rank, run=run)
            put(sim, keys.chunk(run, step, rank), chunk.encode(), LOSSLESS_QOS)
            sent[rank] += 1
        if rng is None:
            continue
        payload = bytearray(make_chunk(n=10, step=step, rank=0, ranks=RANKS, run=run).encode())
        for _ in range(3):
            payload[rng.randrange(len(payload))] ^= 1 << rng.randrange(8)
        sim.put(keys.chunk(run, step, 0), bytes(payload))  # fuzzed: rejected or a duplicate
    for rank in range(RANKS):
        if kill_rank and rank == 1:
            tokens[rank].undeclare()  # died: no done event
            continue
        put(sim, keys.event(run), Event(run, EventKind.RANK_DONE, rank, "done",
                                        {"sent": sent[rank]}).encode(), LOSSLESS_QOS)
        tokens[rank].undeclare()
    return sum(sent)


def check_log(path, kill_rank: bool) -> None:
    with open(path, "rb") as f:
        reader = make_reader(f)
        records = [(channel.topic, message.data) for _, channel, message in
                   reader.iter_messages()]
    frames = [t for t, _ in records if "/frame/" in t]
    assert len(frames) == len(STEPS), path
    timing = [Timing.from_json(json.loads(d)) for t, d in records if t.endswith("/timing")]
    assert [t.incomplete for t in timing] == [False, False, kill_rank], path
    end = [d for t, d in records if t.endswith("/event") and b"run_end" in d]
    assert len(end) == 1, path


def test_one_server_many_runs_hostile_peers(server, client_factory, endpoint, tmp_path):
    out = tmp_path / "out"
    rng = random.Random(7)
    sim = client_factory()

    # 5 runs at once
    daemons = [RenderServer(server, ServerOptions(spec_for(f"at-once-{k}"), out,
                                                  out / f"at-once-{k}.mcap", timeout_s=2.0))
               for k in range(5)]
    for k, d in enumerate(daemons):
        d._latest = _every_step()
        one_run(sim, f"at-once-{k}", rng, kill_rank=(k == 3))
    assert all(d.finished.wait(TIMEOUT_S) for d in daemons)
    for d in daemons:
        d.close()

    # 50 runs of one run id in a row
    daemon = RenderServer(server, ServerOptions(spec_for("seq"), out, out / "seq.mcap",
                                                timeout_s=2.0))
    daemon._latest = _every_step()
    baseline = None
    try:
        for k in range(50):
            if k == 5:
                tracemalloc.start()
                baseline = tracemalloc.get_traced_memory()[0]
            if k % 10 == 4:  # a peer without the password: refused at the link
                with pytest.raises(zenoh.ZError):
                    open_session(NetworkOptions(connect=[endpoint], credentials_file=_wrong(
                        tmp_path)), Role.CLIENT)
            if k % 10 == 6:  # a chunk naming run "..": rejected, it never reaches a path
                escape = make_chunk(n=5, step=0, rank=0, ranks=RANKS, run="..")
                put(sim, keys.chunk("seq", 0, 0), escape.encode(), LOSSLESS_QOS)
            if k == 25:  # a server restart with the same --out and log: nothing overwritten
                daemon.close()
                daemon = RenderServer(server, ServerOptions(spec_for("seq"), out,
                                                            out / "seq.mcap", timeout_s=2.0))
                daemon._latest = _every_step()
            one_run(sim, "seq", rng, kill_rank=(k % 7 == 3))
            assert wait_until(lambda k=k, d=daemon: d.finished.is_set()
                              and d.current.name == ("seq" if k == 0 else f"seq.{k}"))
        current = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
        daemon.close()
    assert current - baseline < 2 << 20, (baseline, current)  # bytes: runs leave nothing behind
    assert rejected_total(out) >= 5

    for k in range(5):
        check_log(out / f"at-once-{k}.mcap", kill_rank=(k == 3))
    for k in range(50):
        check_log(out / ("seq.mcap" if k == 0 else f"seq.{k}.mcap"), kill_rank=(k % 7 == 3))
    outside = {p.name for p in tmp_path.iterdir()} - {"out", "wrong"}
    assert not outside and all(p.resolve().is_relative_to(out) for p in out.rglob("*"))


def served(session, run: str, out, record, timeout_s: float = 2.0) -> RenderServer:
    d = RenderServer(session, ServerOptions(spec_for(run), out, record, timeout_s=timeout_s))
    d._latest = _every_step()
    return d


def accounted(d: RenderServer, sent: int) -> None:
    """Every chunk the ranks sent is in exactly one of the run's counts."""
    s = d.summary()
    assert s["chunks"] + s["inbox_dropped"] + s["queued_at_stop"] + s["lost_in_transit"] \
        == sent, s


def every_log_opens(where) -> int:
    """Each MCAP file under `where` opens with mcap's reader, summary included; the count."""
    logs = sorted(where.rglob("*.mcap"))
    for path in logs:
        with open(path, "rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None, path
            sum(1 for _ in reader.iter_messages())
    return len(logs)


def test_what_the_daemon_must_not_lose(server, client_factory, endpoint, tmp_path, disk):
    out = tmp_path / "out"
    sim = client_factory()

    # two servers on one --out, without a log: each its own folder, every frame kept
    twins = [served(server, "twin", out, None) for _ in range(2)]
    sent = one_run(sim, "twin", None, kill_rank=False)
    assert all(d.finished.wait(TIMEOUT_S) for d in twins)
    for d in twins:
        d.close()
        accounted(d, sent)
    assert {d.current.frames_dir.name for d in twins} == {"twin", "twin.1"}
    for d in twins:
        assert len(list((d.current.frames_dir / "side").iterdir())) == len(STEPS)

    # a flood of idle connections while a rank is killed: the client still gets in
    host, port = endpoint.split("/")[1].rsplit(":", 1)
    flood = [socket.create_connection((host, int(port)), timeout=5) for _ in range(150)]
    try:
        late = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=5.0),
                            Role.CLIENT)
        d = served(server, "flood", out, out / "flood.mcap")
        sent = one_run(late, "flood", None, kill_rank=True)
        assert d.finished.wait(TIMEOUT_S)
        d.close()
        late.close()
    finally:
        for sock in flood:
            sock.close()
    assert d.summary()["ranks_lost"] == [1] and d.failures()
    accounted(d, sent)

    # a squatter on an endpoint without a password file: refused before anything is sent
    squat = f"tcp/127.0.0.1:{free_port()}"
    squatter = Squatter(squat)
    try:
        with pytest.raises(CredentialsError):
            open_session(NetworkOptions(connect=[squat]), Role.CLIENT)
        assert squatter.heard == [] and squatter.peers() == []
    finally:
        squatter.close()

    # a full disk under a server's --out: runs go on, logs end cleanly, nothing uncounted
    fill(disk, leave=48 << 10)
    d = served(server, "full", disk / "out", disk / "out" / "full.mcap")
    failed = []
    try:
        for k in range(6):
            sent = one_run(sim, "full", None, kill_rank=(k == 2), n=400)
            assert wait_until(lambda k=k: d.finished.is_set()
                              and d.current.name == ("full" if k == 0 else f"full.{k}"))
            accounted(d, sent)
            failed += d.failures()
    finally:
        d.close()
    assert any("ends early" in f and "ENOSPC" in f for f in failed), failed
    assert any("was not logged" in f for f in failed), failed  # a run opened on the full disk
    assert every_log_opens(disk) >= 1
    assert every_log_opens(out) == 1  # flood.mcap


def rejected_total(out) -> int:
    """Messages of the 'seq' runs' logs that went to the rejected topic (fuzzed, escaping)."""
    total = 0
    for path in out.glob("seq*.mcap"):
        with open(path, "rb") as f:
            total += sum(1 for _, channel, _ in make_reader(f).iter_messages()
                         if channel.topic == "minority/_rejected")
    return total


def _wrong(tmp_path):
    path = tmp_path / "wrong"
    path.write_text("minority:guess\n")
    path.chmod(0o600)
    return path


def _every_step():
    return EveryStep()
