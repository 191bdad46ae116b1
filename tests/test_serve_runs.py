"""`minority serve` as a daemon: several runs at once on one server, and a server killed and
restarted with the same --out keeps the killed run's log (and `minority log repair` makes it
readable by mcap's own reader). Loopback only; waits are on messages, never on sleep."""

import signal
import subprocess
import sys
import warnings

from conftest import make_chunk
from mcap.reader import make_reader
from test_loopback import TIMEOUT_S, wait_until
from test_render_daemon import spec

from minority.protocol import Spec, keys
from minority.protocol.log import LogTruncatedWarning, read_log
from minority.protocol.session import LOSSLESS_QOS, Inbox, NetworkOptions, Role, open_session, put
from minority.render_server.daemon import RenderServer, ServerOptions


def spec_for(run: str) -> Spec:
    return Spec.from_dict({**spec().to_dict(), "run": run})


def send(session, run: str, step: int) -> None:
    put(session, keys.chunk(run, step, 0), make_chunk(n=30, step=step, ranks=1, run=run).encode(),
        LOSSLESS_QOS)


def test_two_runs_at_once_each_with_its_own_frames_and_log(server, client_factory, tmp_path):
    daemons = [RenderServer(server, ServerOptions(spec_for(run), tmp_path, tmp_path / f"{run}.mcap",
                                                  timeout_s=30.0)) for run in ("a", "b")]
    try:
        sim = client_factory()
        frames = {run: Inbox(sim, keys.frames(run)) for run in ("a", "b")}
        send(sim, "a", 0)
        send(sim, "b", 20)
        assert wait_until(lambda: all(f.received == 1 for f in frames.values()))
    finally:
        for d in daemons:
            d.close()
    assert (tmp_path / "a" / "side" / "000000.png").exists()
    assert (tmp_path / "b" / "side" / "000020.png").exists()
    for run, step in (("a", 0), ("b", 20)):
        chunks = [r.decode() for r in read_log(tmp_path / f"{run}.mcap", ["minority/*/chunk"])]
        assert [(c.run, c.step) for c in chunks] == [(run, step)]


def serve(endpoint: str, spec_path, out) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "minority", "serve", "--spec", str(spec_path),
                             "--out", str(out), "--listen", endpoint],
                            stderr=subprocess.PIPE, text=True)


def test_a_killed_server_restarted_keeps_the_killed_runs_log(endpoint, tmp_path):
    spec().save(tmp_path / "spec.json")
    out, run = tmp_path / "out", spec().run
    sim = None
    first = serve(endpoint, tmp_path / "spec.json", out)
    try:
        sim = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=30), Role.CLIENT)
        frames = Inbox(sim, keys.frames(run))
        assert wait_until(lambda: len(list(sim.get(keys.spec(run), timeout=1))) > 0)
        for k, step in enumerate((0, 20)):
            send(sim, run, step)
            assert wait_until(lambda k=k: frames.received == k + 1)

        def logged_frames() -> int:  # the server's log thread completes its chunks when idle
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LogTruncatedWarning)
                return sum(1 for r in read_log(out / f"{run}.mcap") if "/frame/" in r.topic)

        assert wait_until(lambda: logged_frames() == 2)
    finally:
        first.kill()  # SIGKILL: no summary, no footer
        first.communicate(timeout=TIMEOUT_S)
    killed_log = (out / f"{run}.mcap").read_bytes()
    second = serve(endpoint, tmp_path / "spec.json", out)
    try:
        assert wait_until(lambda: len(list(sim.get(keys.spec(run), timeout=1))) > 0)
        send(sim, run, 40)
        assert wait_until(lambda: frames.received == 3)
    finally:
        sim.close()
        second.send_signal(signal.SIGTERM)
        _, err = second.communicate(timeout=60)
    assert second.returncode == 0, err
    assert (out / f"{run}.mcap").read_bytes() == killed_log  # not truncated, not appended to
    assert sorted(p.name for p in (out / run / "side").iterdir()) == ["000000.png", "000020.png"]
    assert [p.name for p in (out / f"{run}.1" / "side").iterdir()] == ["000040.png"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the restarted server's log is complete
        steps = [r.decode().step for r in read_log(out / f"{run}.1.mcap", ["*/chunk"])]
    assert steps == [40]
    repaired = subprocess.run([sys.executable, "-m", "minority", "log", "repair",
                               str(out / f"{run}.mcap")], capture_output=True, text=True)
    assert repaired.returncode == 0, repaired.stderr
    with open(out / f"{run}.repaired.mcap", "rb") as f:
        topics = [channel.topic for _, channel, _ in make_reader(f).iter_messages()]
    assert topics.count(f"minority/{run}/frame/side") == 2
