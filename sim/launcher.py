"""Starting and stopping ranks: whether an MPI launcher started this process, re-running a
command under the venv's mpiexec (what `minority sim --ranks N` and `serve --ranks N` do)
and removing the shared-memory segments its ranks leave behind, and the stop that SIGINT
and SIGTERM ask for. Imports nothing heavy, so a command can decide before it loads numba
or zenoh."""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

# Environment variables that MPI launchers set in the processes they start (MPICH/Hydra,
# PMIx launchers such as Open MPI's and Slurm's srun --mpi=pmix, Open MPI's own).
LAUNCHER_ENV = ("PMI_RANK", "PMI_SIZE", "PMIX_RANK", "OMPI_COMM_WORLD_SIZE")
# When we start mpiexec ourselves: MPICH polls in a busy loop while waiting; with more
# processes than free cores that starves the rank it waits for. Throttled polling sleeps a
# microsecond after 4096 idle polls (unless the user chose otherwise).
RELAUNCH_ENV = {"MPIR_CVAR_CH4_PROGRESS_THROTTLE": "1"}
PR_SET_PDEATHSIG = 1  # prctl(2)
SHM_DIR = Path("/dev/shm")
# MPICH's (ch4, POSIX) shared-memory segments: "mpich_shm_{world id:x}_{node}" and
# "mpich_vci_..."; MPI_Finalize unlinks them, a rank that dies first leaves them behind
MPICH_SHM_PREFIXES = ("mpich_shm_", "mpich_vci_")
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def stopped_status(signum: int) -> int:
    """The exit status of a process stopped by signal `signum`: 128 + signum (the shell's
    convention: 130 for SIGINT, 143 for SIGTERM)."""
    return 128 + signum


class StopSignals:
    """While entered (`with StopSignals() as stop:`), the first SIGINT or SIGTERM asks for a
    clean stop (`stop()` and `signum` say which; the caller polls it); on exit the handlers
    before it are back. A handler only stores a number: it runs in the main thread between
    two bytecodes, wherever that thread is, so it must take no lock.

    repeat_ends: a second signal ends the process at once by that signal, as if no handler
    were set (a process alone: its user presses Ctrl-C again). Under an MPI launcher leave
    it False: a rank gets a terminal's Ctrl-C twice, from the terminal and from mpiexec,
    which forwards it, and mpiexec itself aborts every rank at a second Ctrl-C."""

    def __init__(self, repeat_ends: bool = True) -> None:
        self.signum = 0  # the first stop signal received; 0: none
        self.repeat_ends = repeat_ends
        self._before: dict[int, object] = {}

    def __enter__(self) -> StopSignals:
        for sig in STOP_SIGNALS:
            self._before[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._before.items():
            signal.signal(sig, handler)
        self._before.clear()

    def __call__(self) -> int:
        return self.signum

    def _handle(self, signum: int, _frame) -> None:
        if not self.signum:
            self.signum = signum
        elif self.repeat_ends:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)


def under_launcher() -> bool:
    """Whether this process was started by an MPI launcher (mpiexec, srun)."""
    return any(name in os.environ for name in LAUNCHER_ENV)


def mpiexec_path() -> Path | None:
    """The mpiexec next to this Python (the one of the `mpich` wheel), else on PATH."""
    here = Path(sys.executable).parent / "mpiexec"
    if here.exists():
        return here
    found = shutil.which("mpiexec")
    return Path(found) if found else None


def relaunch(ranks: int, argv: list[str], command: str = "sim",
             launcher_args: Callable[[Path], list[str]] | None = None) -> int:
    """`python -m minority ARGV` under `mpiexec -n ranks` (launcher_args(mpiexec): flags
    before -n); returns its exit status, or stopped_status(signal) when this process was
    signalled and mpiexec failed. mpiexec runs in its own process group, and this process
    passes SIGINT and SIGTERM on to it: a terminal's Ctrl-C reaches only this process's
    group, and hydra forwards the signal to every rank. mpiexec gets SIGTERM if this process
    dies (Linux). Afterwards the MPICH shared-memory segments that appeared while it ran and
    that no live process holds are removed (a rank killed before MPI_Finalize leaves its
    node's segment, MBs of /dev/shm, behind)."""
    mpiexec = mpiexec_path()
    if mpiexec is None:
        print(f"minority {command}: error: --ranks needs mpiexec, none found next to "
              f"{sys.executable} or on PATH: pip install 'minority[mpi]' (the mpich wheel), or "
              "use the site's MPI (deploy/README.md, \"A cluster's own MPI\")", file=sys.stderr)
        return 1
    cmd = [str(mpiexec), *(launcher_args(mpiexec) if launcher_args else []), "-n", str(ranks),
           sys.executable, "-m", "minority", *argv]
    before = mpich_segments()
    received = 0

    def forward(signum: int, _frame) -> None:
        nonlocal received
        received = received or signum
        proc.send_signal(signum)

    proc = subprocess.Popen(cmd, env={**RELAUNCH_ENV, **os.environ}, process_group=0,
                            preexec_fn=_term_with_parent if sys.platform == "linux" else None)
    for sig in STOP_SIGNALS:
        signal.signal(sig, forward)
    status = proc.wait()
    left = remove_orphan_segments(before)
    if left:
        print(f"minority {command}: removed {len(left)} shared-memory segment(s) its ranks "
              f"left behind: {', '.join(str(p) for p in left)}", file=sys.stderr)
    if received and status != 0:
        return stopped_status(received)
    return status if status >= 0 else stopped_status(-status)


def mpich_segments(shm_dir: Path = SHM_DIR) -> set[Path]:
    """The MPICH shared-memory segments in shm_dir owned by this user."""
    try:
        entries = list(shm_dir.iterdir())
    except OSError:
        return set()
    uid = os.getuid()
    found = set()
    for path in entries:
        if path.name.startswith(MPICH_SHM_PREFIXES):
            try:
                if path.lstat().st_uid == uid:
                    found.add(path)
            except OSError:  # removed meanwhile
                pass
    return found


def remove_orphan_segments(before: set[Path], shm_dir: Path = SHM_DIR) -> list[Path]:
    """Remove this user's MPICH segments in shm_dir that are not in `before` and that no
    live process maps or holds open (another job's segments are in use, so kept); returns
    the paths removed."""
    new = mpich_segments(shm_dir) - before
    if not new:
        return []
    held = _held_paths(shm_dir)
    removed = []
    for path in sorted(new - held):
        try:
            path.unlink()
            removed.append(path)
        except OSError:  # gone already, or not ours to remove
            pass
    return removed


def _held_paths(shm_dir: Path = SHM_DIR) -> set[Path]:
    """The files in shm_dir that live processes (those this user may inspect) map or hold
    open, from /proc/PID/maps and /proc/PID/fd."""
    held: set[Path] = set()
    prefix = str(shm_dir) + "/"
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            with open(proc / "maps") as maps:
                for line in maps:
                    at = line.find(prefix)
                    if at >= 0:
                        held.add(Path(line[at:].rstrip("\n").removesuffix(" (deleted)")))
            for fd in (proc / "fd").iterdir():
                target = os.readlink(fd)
                if target.startswith(prefix):
                    held.add(Path(target))
        except OSError:  # gone, or another user's
            continue
    return held


def _term_with_parent() -> None:
    """In mpiexec, before exec: SIGTERM when the process that started it dies."""
    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
