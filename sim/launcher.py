"""Starting ranks: whether an MPI launcher started this process, and re-running a command
under the venv's mpiexec (what `minority sim --ranks N` and `serve --ranks N` do). Imports
nothing heavy, so a command can decide before it loads numba or zenoh."""

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
    before -n); returns its exit status. mpiexec runs in its own process group, and this
    process passes SIGINT and SIGTERM on to it once: a terminal's Ctrl-C reaches only this
    process's group, and a second SIGINT would make hydra abort the ranks at once. mpiexec
    gets SIGTERM if this process dies (Linux)."""
    mpiexec = mpiexec_path()
    if mpiexec is None:
        print(f"minority {command}: error: --ranks needs mpiexec, none found next to "
              f"{sys.executable} or on PATH: pip install 'minority[mpi]' (the mpich wheel), or "
              "use the site's MPI (deploy/README.md, \"A cluster's own MPI\")", file=sys.stderr)
        return 1
    cmd = [str(mpiexec), *(launcher_args(mpiexec) if launcher_args else []), "-n", str(ranks),
           sys.executable, "-m", "minority", *argv]
    proc = subprocess.Popen(cmd, env={**RELAUNCH_ENV, **os.environ}, process_group=0,
                            preexec_fn=_term_with_parent if sys.platform == "linux" else None)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda s, _: proc.send_signal(s))
    return proc.wait()


def _term_with_parent() -> None:
    """In mpiexec, before exec: SIGTERM when the process that started it dies."""
    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
