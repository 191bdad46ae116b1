"""The `minority` command: help at every level, every subcommand built and dispatched."""

import json
import os
import subprocess
import sys

from minority.cli import build_parser, main


def test_network_flags_are_shared():
    parser = build_parser()
    for name, extra in [("serve", ["--spec", "s.json"]), ("record", []), ("replay", ["x.mcap"]),
                        ("sim", ["tiny"])]:
        args = parser.parse_args([name, *extra, "--connect", "tcp/127.0.0.1:1", "--listen",
                                  "tcp/127.0.0.1:2", "--config", "z.json5"])
        assert args.connect == ["tcp/127.0.0.1:1"] and args.listen == ["tcp/127.0.0.1:2"]
        assert str(args.config) == "z.json5"



def test_record_without_server_fails_clearly(tmp_path):
    """No password file for the endpoint: nothing is sent there; with --no-auth the client
    tries and says it cannot reach it."""
    argv = [sys.executable, "-m", "minority", "record", "--connect", "tcp/127.0.0.1:9",
            "--wait", "0", "-o", str(tmp_path / "x.mcap")]
    env = {**os.environ, "MINORITY_CREDENTIALS_DIR": str(tmp_path / "credentials")}
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 1
    assert "tcp/127.0.0.1:9: no password file" in proc.stderr
    proc = subprocess.run(argv + ["--no-auth"], capture_output=True, text=True, timeout=60,
                          env=env)
    assert proc.returncode == 1
    assert "cannot reach a zenoh peer at tcp/127.0.0.1:9" in proc.stderr


def test_sim_runs_a_shipped_scene(tmp_path, capsys):
    out = tmp_path / "tiny.h5"
    assert main(["sim", "tiny", "--out", str(out), "--quiet"]) == 0
    assert out.stat().st_size > 0
    assert "400 particles" in capsys.readouterr().err


def test_sim_bad_scene_and_unstable_dt_fail_clearly(tmp_path, capsys):
    assert main(["sim", "no_such_scene", "--quiet"]) == 2  # bad input
    assert "no shipped scene 'no_such_scene'" in capsys.readouterr().err
    assert main(["sim", "tiny", "--dt", "1", "--out", str(tmp_path / "x.h5"), "--quiet"]) == 1
    assert "exceeds the stable bound" in capsys.readouterr().err


def test_record_and_serve_say_when_they_cannot_write_their_log(tmp_path, capsys):
    from conftest import free_port

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"version": 1, "run": "r", "views": [{
        "name": "v", "camera": {"position": [0, -1, 0], "focal_point": [0, 0, 0]}}]}))
    assert main(["record", "--listen", f"tcp/127.0.0.1:{free_port()}", "-o",
                 str(blocker / "x.mcap"), "--duration", "1", "--quiet"]) == 1
    assert "cannot write" in capsys.readouterr().err
    assert main(["serve", "--spec", str(spec), "--listen", f"tcp/127.0.0.1:{free_port()}",
                 "--out", str(tmp_path / "frames"), "--record", str(blocker / "x.mcap")]) == 1
    err = capsys.readouterr().err
    assert "cannot start" in err and str(blocker) in err


def test_sim_without_an_mpi_library_names_the_fix(tmp_path):
    """No libmpi for mpi4py (a venv without the `mpi` extra, no system MPI): one line that
    says what to install, exit status 1, no traceback."""
    env = {**os.environ, "MPI4PY_LIBMPI": str(tmp_path / "libmpi.so.12")}  # not there
    proc = subprocess.run([sys.executable, "-m", "minority", "sim", "tiny", "--no-publish",
                           "--quiet", "-o", str(tmp_path / "x.h5")], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.startswith("minority sim: error: no MPI library")
    assert "minority[mpi]" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.h5").exists()


def test_a_stop_signal_ends_a_wait_in_the_main_thread():
    """The handler sets a flag the main thread's wait polls: no lock shared with the waiter
    (an Event's set, run by a handler inside Event.wait, waits for the lock wait holds)."""
    import os
    import signal
    import threading

    from minority.signals import SignalStop

    stop = SignalStop()
    assert stop.wait(0.01) is False
    previous = signal.signal(signal.SIGUSR2, lambda *_: stop.set())
    try:
        threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGUSR2)).start()
        assert stop.wait(30.0) is True and stop.is_set()
    finally:
        signal.signal(signal.SIGUSR2, previous)
