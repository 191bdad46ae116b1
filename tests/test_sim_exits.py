"""How `minority sim` ends: bad input is exit status 2 with one line naming the file or the
value (before any rank starts); a run stopped by SIGINT or SIGTERM stops at the next step,
sends each rank's rank_done, closes its MCAP records (summary and footer: every reader opens
them) and exits 130 or 143; a sim that reaches no server says so in a warning block at the
start and again at the end; the launcher of `--ranks N` removes the MPICH shared-memory
segments its killed ranks leave behind.

The runs are `python -m minority sim` subprocesses on a copy of the tiny scene that lasts
100 s of simulated time, so it is still stepping when the signal comes: each test waits for
the progress line of the second frame on stderr, not for a time."""

from __future__ import annotations

import mmap
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import h5py
import pytest
from conftest import free_port
from mcap.reader import make_reader

from minority.cli import main
from minority.protocol.log import LogDamagedWarning, LogTruncatedWarning, read_log
from minority.protocol.messages import Event, EventKind, Stats
from minority.sim import launcher
from minority.sim.launcher import StopSignals, stopped_status
from minority.sim.scene import SCENES_DIR

LINE_TIMEOUT_S = 240  # the first step compiles the kernels when numba's cache is cold
EXIT_TIMEOUT_S = 60
RUN = "stopped"


def run_cli(capsys, argv: list[str]) -> tuple[int, str]:
    """(exit status, stderr) of `minority ARGV` in this process."""
    status = main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return status, err


# --- bad input: 2, naming the problem ----------------------------------------------------
@pytest.fixture
def tiny(tmp_path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text((SCENES_DIR / "tiny.toml").read_text())
    return path


def test_a_binary_scene_file_is_bad_input_named(capsys, tmp_path):
    scene = tmp_path / "x.toml"
    scene.write_bytes(b"\xa9" + bytes(range(256)) * 2)
    status, err = run_cli(capsys, ["sim", str(scene), "-o", str(tmp_path / "x.h5"), "-q"])
    assert status == 2
    assert f"{scene}: not UTF-8 text (byte 0xa9 at offset 0)" in err
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("text, message", [
    ("name = [", "invalid TOML"),
    ("[domain]\nsize_m = 1.0\n", "domain"),
])
def test_a_bad_scene_file_names_the_file(capsys, tmp_path, text, message):
    scene = tmp_path / "bad.toml"
    scene.write_text(text)
    status, err = run_cli(capsys, ["sim", str(scene), "-o", str(tmp_path / "x.h5"), "-q"])
    assert status == 2
    assert re.search(rf"minority sim: error: {re.escape(str(scene))}: .*{message}", err), err


def test_a_missing_scene_file_or_a_directory_is_bad_input(capsys, tmp_path):
    for scene, why in ((tmp_path / "nope.toml", "No such file or directory"),
                       (tmp_path, "Is a directory")):
        status, err = run_cli(capsys, ["sim", str(scene), "-o", str(tmp_path / "x.h5"), "-q"])
        assert status == 2
        assert f"cannot read scene file {scene}: {why}" in err


@pytest.mark.parametrize("argv, message", [
    (["--run", ".."], "--run '..': a run id is"),
    (["--run=-x"], "--run '-x': a run id is"),
    (["--run", "a/b"], "--run 'a/b': a run id is"),
    (["--steps", "-1"], "--steps must be at least 0, got -1"),
    (["--ranks", "0"], "--ranks must be at least 1, got 0"),
    (["--threads", "0"], "--threads must be at least 1, got 0"),
    (["--rebalance-every", "-5"], "--rebalance-every must be at least 0, got -5"),
    (["--dt=-1e-4"], "--dt must be a finite time step > 0 s, got -0.0001"),
    (["--dt", "nan"], "--dt must be a finite time step > 0 s, got nan"),
    (["--wait", "-1"], "--wait must be a finite number of seconds >= 0, got -1.0"),
    (["--wait", "inf"], "--wait must be a finite number of seconds >= 0, got inf"),
    (["--stats-every-s", "-1"], "--stats-every-s must be a finite number of seconds >= 0, got -1.0"),
    (["--context-tolerance", "nan"],
     "--context-tolerance must be a finite number of metres >= 0, got nan"),
])
def test_a_bad_value_is_bad_input_naming_it(capsys, tmp_path, tiny, argv, message):
    out = tmp_path / "x.h5"
    status, err = run_cli(capsys, ["sim", str(tiny), "-o", str(out), "-q", "--connect",
                                   f"tcp/127.0.0.1:{free_port()}", "--no-auth", *argv])
    assert status == 2
    assert f"minority sim: error: {message}" in err
    assert not out.exists()


def test_a_missing_spec_or_an_existing_record_is_bad_input(capsys, tmp_path, tiny):
    spec, record = tmp_path / "nope.json", tmp_path / "old.mcap"
    status, err = run_cli(capsys, ["sim", str(tiny), "-o", str(tmp_path / "x.h5"), "-q",
                                   "--spec", str(spec)])
    assert status == 2 and str(spec) in err
    record.write_bytes(b"kept")
    status, err = run_cli(capsys, ["sim", str(tiny), "-o", str(tmp_path / "x.h5"), "-q",
                                   "--record", str(record)])
    assert status == 2 and f"--record {record}: the file exists" in err
    assert record.read_bytes() == b"kept"


# --- stopped by a signal: 128 + signal, complete records ---------------------------------
class Sim:
    """A `minority sim` subprocess whose stderr lines a thread collects."""

    def __init__(self, argv: list[str]):
        env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([sys.executable, "-m", "minority", "sim", *argv],
                                     stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                     text=True, env=env)
        self.lines: list[str] = []
        self._queue: queue.Queue = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self._queue.put(line)
        self._queue.put(None)

    def wait_for(self, pattern: str, timeout_s: float = LINE_TIMEOUT_S) -> str:
        """The first stderr line matching `pattern`; fails at the end of the output."""
        while True:
            try:
                line = self._queue.get(timeout=timeout_s)
            except queue.Empty:
                self.proc.kill()
                pytest.fail(f"no line matching {pattern!r} in {timeout_s} s: {self.lines}")
            if line is None:
                pytest.fail(f"the sim ended (status {self.proc.wait()}) before a line "
                            f"matching {pattern!r}: {''.join(self.lines)}")
            self.lines.append(line)
            if re.search(pattern, line):
                return line

    def end(self, timeout_s: float = EXIT_TIMEOUT_S) -> tuple[int, str]:
        """(exit status, all of stderr)."""
        try:
            status = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise
        self._reader.join(timeout=timeout_s)
        while (line := self._queue.get_nowait()) is not None:
            self.lines.append(line)
        return status, "".join(self.lines)


def test_stop_signals_keep_the_first_signal_and_restore_the_handlers():
    before = signal.getsignal(signal.SIGTERM)
    with StopSignals(repeat_ends=False) as stop:  # as on a rank under mpiexec
        assert stop() == 0
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)  # a repeat: ignored, not the end of pytest
        assert stop() == stop.signum == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before
    assert stopped_status(signal.SIGINT) == 130 and stopped_status(signal.SIGTERM) == 143


def long_scene(tmp_path: Path) -> Path:
    path = tmp_path / "long.toml"
    text = (SCENES_DIR / "tiny.toml").read_text()
    path.write_text(text.replace("duration_s = 0.2", "duration_s = 100.0"))
    return path


def complete_record(path: Path) -> list:
    """The messages of an MCAP record that every reader opens whole: it has its summary and
    footer, and reading it warns of no truncation or damage."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None, f"{path} has no summary"
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogTruncatedWarning)
        warnings.simplefilter("error", LogDamagedWarning)
        messages = [r.decode() for r in read_log(path)]
    assert summary.statistics.message_count == len(messages)
    return messages


def assert_stopped_cleanly(messages: list, rank: int, signame: str) -> None:
    done = [m for m in messages if isinstance(m, Event) and m.kind == EventKind.RANK_DONE]
    assert len(done) == 1 and done[0].rank == rank
    assert done[0].detail["stopped"] == signame and done[0].detail["steps"] > 0
    assert done[0].detail["recorded"] == len(messages) - 1  # all but rank_done itself
    assert any(isinstance(m, Stats) for m in messages)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signalled_sim_stops_at_a_step_and_closes_its_record(tmp_path, sig):
    record, out = tmp_path / "sim.mcap", tmp_path / "sim.h5"
    sim = Sim([str(long_scene(tmp_path)), "-o", str(out), "--threads", "1", "--run", RUN,
               "--record", str(record), "--connect", f"tcp/127.0.0.1:{free_port()}",
               "--no-auth"])
    sim.wait_for(r"^frame 2/")  # stepping
    sim.proc.send_signal(sig)
    status, err = sim.end()
    assert status == 128 + sig, err
    assert re.search(rf"\d+ steps \(stopped by {sig.name}\), \d+ frames", err), err
    assert "Traceback" not in err
    assert_stopped_cleanly(complete_record(record), 0, sig.name)
    with h5py.File(out) as f:  # the frames written so far are kept
        assert f["positions"].shape[0] >= 2


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signalled_launcher_stops_every_rank_and_closes_their_records(tmp_path, sig):
    """`--ranks 2`: a signal to the launcher (a terminal's Ctrl-C reaches only it: mpiexec
    runs in its own process group) reaches both ranks through mpiexec; they stop after the
    same step; both records are complete."""
    record = tmp_path / "sim.mcap"
    sim = Sim([str(long_scene(tmp_path)), "-o", str(tmp_path / "sim.h5"), "--ranks", "2",
               "--threads", "1", "--run", RUN, "--record", str(record),
               "--connect", f"tcp/127.0.0.1:{free_port()}", "--no-auth"])
    sim.wait_for(r"^frame 2/")
    sim.proc.send_signal(sig)
    status, err = sim.end()
    assert status == 128 + sig, err
    assert f"stopped by {sig.name}" in err and "Traceback" not in err
    steps = set()
    for rank, path in ((0, record), (1, tmp_path / "sim.rank1.mcap")):
        messages = complete_record(path)
        assert_stopped_cleanly(messages, rank, sig.name)
        steps |= {m.detail["steps"] for m in messages if isinstance(m, Event)
                  and m.kind == EventKind.RANK_DONE}
    assert len(steps) == 1  # the same step on both ranks


# --- no server: said loudly --------------------------------------------------------------
@pytest.mark.parametrize("wait_s", [0.0, 1.5])
def test_a_sim_without_a_server_says_it_was_not_observed(tmp_path, wait_s):
    port = free_port()
    sim = Sim([str(SCENES_DIR / "tiny.toml"), "-o", str(tmp_path / "t.h5"), "--threads", "1",
               "--steps", "3", "--run", RUN, "--connect", f"tcp/127.0.0.1:{port}", "--no-auth",
               "--wait", f"{wait_s:g}"])
    status, err = sim.end(LINE_TIMEOUT_S)
    assert status == 0, err
    lines = err.splitlines()
    warned = [i for i, line in enumerate(lines) if line.startswith("minority sim: WARNING")]
    start = lines.index(next(line for line in lines if line.startswith("sim: scene")))
    assert warned and warned[0] < start  # at the start, before the stepping
    text = "\n".join(lines[warned[0]:start])
    assert f"no zenoh server reachable at tcp/127.0.0.1:{port}" in text
    assert "this run is NOT published" in text
    tries = re.search(r"(\d+) connection attempts? in ([\d.]+) s", text)
    assert tries is not None, text
    if wait_s:
        assert int(tries.group(1)) >= 1 and float(tries.group(2)) >= wait_s - 0.1
        assert f"--wait {wait_s:g}: no server answered in that time" in text
    else:
        assert int(tries.group(1)) == 1
        assert "--wait 0: one try at start" in text
    summary = lines.index(next(line for line in lines if "3 steps" in line))
    end = "\n".join(lines[summary:])
    assert f"WARNING: this run was NOT published/observed: no zenoh server reachable at " \
           f"tcp/127.0.0.1:{port}" in end


# --- the launcher cleans what its ranks leave --------------------------------------------
def descendants(pid: int) -> list[int]:
    """The processes below `pid` (from /proc/*/stat's parent ids)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        ppid = int(text[text.rindex(")") + 2:].split()[1])
        children.setdefault(ppid, []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def mpich_segments_of(pid: int) -> set[Path]:
    maps = Path(f"/proc/{pid}/maps").read_text()
    return {Path(m) for m in re.findall(r"(/dev/shm/mpich_\S+)", maps)}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc")
def test_only_new_mpich_segments_that_no_process_holds_are_removed(tmp_path):
    names = ("mpich_shm_old_0", "mpich_shm_new_0", "mpich_vci_new_0", "mpich_shm_held_0",
             "mpich_shm_mapped_0", "other_0")
    for name in names:
        (tmp_path / name).write_bytes(b"\0" * 4096)
    before = {tmp_path / "mpich_shm_old_0"}
    assert launcher.mpich_segments(tmp_path) == {tmp_path / n for n in names[:5]}
    with open(tmp_path / "mpich_shm_mapped_0", "rb") as f:
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # the fd closes, the map stays
    with open(tmp_path / "mpich_shm_held_0", "rb"):
        removed = launcher.remove_orphan_segments(before, tmp_path)
    mapped.close()
    assert removed == [tmp_path / "mpich_shm_new_0", tmp_path / "mpich_vci_new_0"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["mpich_shm_old_0", "mpich_shm_held_0", "mpich_shm_mapped_0", "other_0"])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and /dev/shm")
def test_the_launcher_removes_the_segments_of_a_killed_rank(tmp_path):
    sim = Sim([str(long_scene(tmp_path)), "-o", str(tmp_path / "sim.h5"), "--ranks", "2",
               "--threads", "1", "--no-publish"])
    sim.wait_for(r"^frame 2/")
    ranks = [p for p in descendants(sim.proc.pid)  # not mpiexec nor hydra's proxy
             if Path(f"/proc/{p}/cmdline").read_text().split("\0")[0] == sys.executable]
    assert len(ranks) == 2, ranks
    segments = set().union(*(mpich_segments_of(p) for p in ranks))
    assert segments and all(s.exists() for s in segments)
    os.kill(ranks[1], signal.SIGKILL)
    status, err = sim.end()
    assert status != 0
    assert not any(s.exists() for s in segments), err
    assert "shared-memory segment(s) its ranks left behind" in err
