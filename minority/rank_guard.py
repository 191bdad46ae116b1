"""A render rank's guard: under an MPI launcher, `minority serve` runs as a small parent
process (not an MPI process) and the server as its child, so that a rank killed by a signal
does not take the whole job with it.

Why: MPICH's hydra ends every rank at once (SIGKILL) when one of the processes it started
dies by a signal, `-disable-auto-cleanup` or not, before rank 0 can record anything. It
honours `-disable-auto-cleanup` for a process that exits with a status, though. The guard
waits for its child and turns "killed by signal S" into exit status 128 + S, so the other
ranks live on: rank 0's heartbeat watchdog (render_server.serve_mpi) then notices the silent
rank within --rank-timeout, records an error event, closes the log complete and ends the job
with MPI_Abort. The child dies with its guard (PR_SET_PDEATHSIG), so MPI_Abort, which kills
the guards, leaves no orphan; SIGINT, SIGTERM and SIGHUP sent to the guard are passed on.
SIGUSR1 (hydra's notice that a rank has ended) is not: it starts the grace period after
which a child that is still there (stopped, or stuck in a collective) is killed.

Linux only (prctl); elsewhere the server runs unguarded, as before.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
from typing import NoReturn

GUARDED_ENV = "MINORITY_RANK_GUARDED"  # set in the child: it is the guarded server
PR_SET_PDEATHSIG = 1
SIZE_ENV = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "SLURM_NTASKS")


def wanted() -> bool:
    """Whether this process (started by an MPI launcher) should guard a child server: on
    Linux, not already the guarded child, and one of several ranks (or a count unknown)."""
    if not sys.platform.startswith("linux") or os.environ.get(GUARDED_ENV):
        return False
    sizes = [os.environ[k] for k in SIZE_ENV if os.environ.get(k, "").isdigit()]
    return not sizes or int(sizes[0]) > 1


def _die_with_parent(parent: int) -> None:
    """In the child, before exec: SIGKILL when the guard dies (also if it already has)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        os._exit(70)
    if os.getppid() != parent:
        os._exit(70)
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)  # hydra's notice reaches the group too


def _end_stuck(child: subprocess.Popen) -> None:
    if child.poll() is None:
        print(f"minority serve: render rank {_rank()} (pid {child.pid}) did not end after "
              "another rank did: killed", file=sys.stderr, flush=True)
        child.kill()


def _rank() -> str:
    return os.environ.get("PMI_RANK") or os.environ.get("PMIX_RANK") or "?"


def run(argv: list[str], grace_s: float) -> NoReturn:
    """`python -m minority ARGV` as the guarded child; exits with its status, or 128 + S
    when a signal S killed it (reported on stderr with the rank and pid). grace_s: how long
    the child may outlive another rank's end (its watchdog's timeout and some)."""
    parent = os.getpid()
    child = subprocess.Popen([sys.executable, "-m", "minority", *argv],
                             env={**os.environ, GUARDED_ENV: "1"},
                             close_fds=False,  # the launcher's PMI descriptor, as exec keeps it
                             preexec_fn=lambda: _die_with_parent(parent))
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda s, _: child.send_signal(s))
    # hydra's notice that another rank has ended (-disable-auto-cleanup): the default action
    # would end this rank at once; the server's own watchdog ends it within its rank timeout
    # (MPI_Abort), and the guard kills it after grace_s in case it cannot (stopped, stuck)
    deadline = threading.Timer(grace_s, _end_stuck, (child,))
    deadline.daemon = True
    signal.signal(signal.SIGUSR1, lambda s, _: deadline.is_alive() or deadline.start())
    status = child.wait()  # retried by Python when a handler interrupts it (PEP 475)
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    if status < 0:
        name = signal.Signals(-status).name
        print(f"minority serve: render rank {_rank()} (pid {child.pid}) was killed by {name}",
              file=sys.stderr, flush=True)
    sys.stdout.flush()
    # now, not through the interpreter's shutdown, which restores SIGUSR1's default action
    # while the other ranks' guards may still be exiting (each exit is a notice)
    os._exit(status if status >= 0 else 128 - status)
