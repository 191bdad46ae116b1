"""Starting ranks: whether an MPI launcher started this process, and re-running a command
under the venv's mpiexec (what `minority sim --ranks N` and `serve --ranks N` do). Imports
nothing heavy, so a command can decide before it loads numba or zenoh."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

# Environment variables that MPI launchers set in the processes they start (MPICH/Hydra,
# PMIx launchers such as Open MPI's and Slurm's srun --mpi=pmix, Open MPI's own).
LAUNCHER_ENV = ("PMI_RANK", "PMI_SIZE", "PMIX_RANK", "OMPI_COMM_WORLD_SIZE")
# When we start mpiexec ourselves: MPICH polls in a busy loop while waiting; with more
# processes than free cores that starves the rank it waits for. Throttled polling sleeps a
# microsecond after 4096 idle polls (unless the user chose otherwise).
RELAUNCH_ENV = {"MPIR_CVAR_CH4_PROGRESS_THROTTLE": "1"}


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


def relaunch(ranks: int, argv: list[str]) -> int:
    """Run `python -m minority ARGV` under `mpiexec -n ranks`; returns its exit status."""
    mpiexec = mpiexec_path()
    if mpiexec is None:
        print("minority sim: error: --ranks needs mpiexec, none found next to "
              f"{sys.executable} or on PATH: pip install 'minority[mpi]' (the mpich wheel), or "
              "use the site's MPI (deploy/README.md, \"A cluster's own MPI\")", file=sys.stderr)
        return 1
    env = {**RELAUNCH_ENV, **os.environ}
    cmd = [str(mpiexec), "-n", str(ranks), sys.executable, "-m", "minority", *argv]
    return subprocess.call(cmd, env=env)
