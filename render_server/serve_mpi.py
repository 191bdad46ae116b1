"""`minority serve` on N MPI render ranks: who receives what, how rank 0 assembles steps it
does not hold, how every rank renders its share, and what happens when a rank dies.

Rank 0 runs the RenderServer (render_server.daemon) as one process does: it serves the spec,
decides runs, assembles and releases steps, renders, publishes frames, timing and events,
and writes the run's log. Every rank, rank 0 included, subscribes only to the chunks of its
sim ranks (sim rank r goes to render rank r % N; keys `minority/{run}/chunk/*/{r}` for r
below `max_sim_ranks`), decodes and keeps them. A rank k > 0 writes its chunks to its own log
shard (protocol.shards: `run.render{k}.mcap`, opened and closed with each run) and reports
each chunk to rank 0 over MPI: step, sim rank, counts, bytes, times and field layout, never
its particles. Rank 0 feeds its assembler a row-less stub per chunk (messages.Chunk with the
same metadata and zero rows), so steps complete, time out, and settle dead sim ranks as in
one process. For each released step (in release order) rank 0 tells every rank which sim ranks'
chunks it holds; each rank builds its share of the step (the fresh rows of its chunks),
applies its chunks' context rows to its own particle cache and completes the share from it
(the one-process server's cache, split by sim rank). When rank 0's render thread takes a
step, it tells the others, and all call render_views_distributed on their shares.

Tie keys: a particle's key orders it as its row in the one-process step: fresh rows by sim
rank then row (the step's offsets, from rank 0), then cached rows by (release sequence that
added them, sim rank, cache position): the order in which the one-process cache appends them.

Faults: every rank sends a heartbeat every HEARTBEAT_S on a thread that never renders. Rank 0
declares a rank dead after `rank_timeout_s` without one: it publishes an error event, ends
the run (run_end, the log closed complete) and ends the job without waiting for the
collective its render thread may be stuck in, through MPI_Abort, which ends every rank (a
stuck one too). A rank k > 0 that hears nothing from rank 0 for `rank_timeout_s` closes its
shard and calls MPI_Abort. A rank killed by a signal is noticed the same way: under a
launcher each rank is a guard process with the server as its child (minority/rank_guard.py),
so hydra (with -disable-auto-cleanup) or srun (--kill-on-bad-exit=0) sees an exit status,
not a signal, and does not end the other ranks before rank 0 has recorded the failure.

The pieces: render_server.mpi_share (the messages, held chunks, the rank cache and a
rank's share of a step), render_server.mpi_worker (ranks k > 0), and here rank 0's
Coordinator and the start-up.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from pathlib import Path

import numpy as np

from minority.protocol.messages import Chunk
from minority.protocol.spec import Spec
from minority.render_server.assemble import AssembledStep, StepAssembler
from minority.render_server.mpi_share import (
    DEFAULT_MAX_SIM_RANKS,
    DEFAULT_RANK_TIMEOUT_S,
    HEARTBEAT_S,
    POLL_S,
    TAG_DOWN,
    TAG_UP,
    ChunkReport,
    HeldChunks,
    RankCache,
    Release,
    Share,
    build_share,
    chunk_keys,
    render_share,
)
from minority.render_server.mpi_worker import Worker, ignore_stop_signals
from minority.render_server.render_mpi import Layers

__all__ = ["Coordinator", "RankCache", "Release", "Worker", "build_share", "chunk_keys",
           "ignore_stop_signals", "warm_up_distributed", "worker_network"]


# --- rank 0 --------------------------------------------------------------------------
class Coordinator:
    """Rank 0's side: its own chunks, the other ranks' reports, releases, the collective
    render, heartbeats and the watchdog. The daemon calls it from its receive and render
    threads; its own thread does the MPI receiving."""

    def __init__(self, ctl, draw, run: str, max_sim_ranks: int = DEFAULT_MAX_SIM_RANKS,
                 rank_timeout_s: float = DEFAULT_RANK_TIMEOUT_S):
        self.ctl, self.draw, self.run = ctl, draw, run
        self.size = ctl.size
        self.max_sim_ranks = max_sim_ranks
        self.rank_timeout_s = rank_timeout_s
        self.held = HeldChunks()
        self.reports: queue.SimpleQueue = queue.SimpleQueue()  # ChunkReport or error text
        self._fresh: dict[int, dict[int, int]] = {}  # step -> sim rank -> fresh rows
        self._seq = 0
        self.cache = RankCache()
        self.layers = Layers()
        self._spec_sent: Spec | None = None
        self._send_lock = threading.Lock()
        self.failed = threading.Event()  # a rank died (self.failure says which)
        self.aborted = threading.Event()  # ... and on_failure has returned: exit now
        self.failure = ""
        self.on_failure = None  # called once with the failure text (the daemon's abort)
        self._last_seen = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="minority-mpi", daemon=True)
        self.too_many_sim_ranks = False

    def chunk_keys(self) -> list[str]:
        return chunk_keys(self.run, 0, self.size, self.max_sim_ranks)

    def start(self) -> None:
        now = time.monotonic()
        self._last_seen = {k: now for k in range(1, self.size)}
        self._thread.start()

    def _send(self, message) -> None:
        if self.failed.is_set():
            return  # a dead rank may never take it
        with self._send_lock:
            for k in range(1, self.size):
                self.ctl.send(message, dest=k, tag=TAG_DOWN)

    def _loop(self) -> None:
        last_beat = 0.0
        while not self._stop.is_set():
            got = False
            while self.ctl.iprobe(tag=TAG_UP):
                status = _status()
                message = self.ctl.recv(tag=TAG_UP, status=status)
                self._last_seen[status.Get_source()] = time.monotonic()
                if message[0] != "beat":
                    self.reports.put(message[1])
                got = True
            now = time.monotonic()
            if now - last_beat >= HEARTBEAT_S:
                self._send(("beat",))
                last_beat = now
            dead = [k for k, t in self._last_seen.items() if now - t > self.rank_timeout_s]
            if dead:
                self.failure = (f"render rank {dead[0]} sent nothing for "
                                f"{self.rank_timeout_s:g} s (killed or stuck): the server stops")
                self.failed.set()
                if self.on_failure is not None:
                    self.on_failure(self.failure)
                self.aborted.set()
                return
            if not got:
                time.sleep(POLL_S)

    # --- the daemon's hooks ---
    def local(self, chunk: Chunk, recv_ns: int, nbytes: int) -> ChunkReport:
        """Keep one of rank 0's own chunks; its report for the assembler."""
        self.held.add(chunk, nbytes)
        return ChunkReport.of(chunk, recv_ns, nbytes)

    def admit(self, assembler: StepAssembler, report: ChunkReport) -> Chunk:
        """Note a chunk's fresh rows (unless the assembler will drop it: late or a
        duplicate); returns the stub to add."""
        if report.ranks > self.max_sim_ranks:
            self.too_many_sim_ranks = True
        pending = assembler.pending.get(report.step)
        if not assembler.is_late(report.step) and (pending is None
                                                   or report.sim_rank not in pending.chunks):
            self._fresh.setdefault(report.step, {})[report.sim_rank] = report.fresh
        return report.stub(self.run)

    def open_instance(self, path: Path | None) -> None:
        self.cache = RankCache()
        self._seq = 0
        self._send(("open", None if path is None else str(path)))

    def close_instance(self) -> None:
        self._send(("close",))

    def release(self, step: AssembledStep) -> Share:
        """A released step: tell every rank, build rank 0's share (every step, in order)."""
        fresh = self._fresh.pop(step.step, {})
        sim_ranks = tuple(sorted(fresh))
        offsets, total = {}, 0
        for r in sim_ranks:
            offsets[r], total = total, total + fresh[r]
        schema = tuple((k, v.dtype.str, v.shape[1:]) for k, v in step.fields.items())
        release = Release(self._seq, step.step, step.time_s, step.prev_time_s, step.spacing_m,
                          step.bounds_m, sim_ranks, offsets, schema, step.tracked)
        self._seq += 1
        self._send(("release", release))
        share = build_share(release, self.held.take(step.step, list(sim_ranks)), self.cache)
        share.meta = step
        return share

    def dropped(self, share: Share) -> None:
        """A released step that will not be rendered (a newer one replaced it)."""
        self._send(("drop", share.release.seq))

    def render(self, share: Share, spec: Spec, canvases: dict):
        """Rank 0's part of the collective render (the others follow its command)."""
        new_spec = None if spec is self._spec_sent else bytes(spec.encode())
        self._spec_sent = spec
        self._send(("render", share.release, new_spec))
        return render_share(self.draw, share, spec, canvases, self.layers)

    def stop(self) -> None:
        """End the other ranks' loops (after the last render) and this thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        if not self.failed.is_set():
            self._send(("stop",))


def _status():
    from mpi4py import MPI

    return MPI.Status()


# --- start-up ---------------------------------------------------------------------------
def warm_up_distributed(draw) -> None:
    """Every rank (collective): run the exchange and compositing kernels once on a tiny step,
    so numba compiles (or loads) them before the heartbeats start."""
    from minority.protocol.spec import Camera, View
    from minority.render_server.render_mpi import render_step_distributed

    view = View("warm-up", Camera((0.0, -1.0, 0.0), (0.0, 0.0, 0.0)), 8, 8)
    rng = np.random.default_rng(draw.rank)
    positions = rng.random((8, 3)).astype(np.float32) * 0.1
    render_step_distributed(draw, positions, {view.field: np.zeros(8, np.float32)}, 0.01, [view])


def worker_network(opts, listening: list[str], same_host: bool, host: str):
    """The zenoh options of a rank k > 0: never listening; connected where --connect says, or
    else to rank 0's listening endpoints (loopback on rank 0's host, its host name from
    others). `listening`: rank 0's listen endpoints."""
    here = "127.0.0.1" if same_host else host
    connect = list(opts.connect) or [
        e.replace("0.0.0.0", here).replace("[::]", here if not same_host else "[::1]")
        for e in listening]
    return dataclasses.replace(opts, listen=[], connect=connect,
                               connect_timeout_s=max(opts.connect_timeout_s, 30.0))
