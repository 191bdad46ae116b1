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
same metadata and zero rows), so steps complete, time out, and settle dead sim ranks as
today. For each released step (in release order) rank 0 tells every rank which sim ranks'
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
shard and calls MPI_Abort. A rank killed with SIGKILL is another matter with MPICH (measured
with the mpich wheel's hydra, with and without -disable-auto-cleanup): the library aborts the
job at once, every rank is SIGKILLed within about a second, before any heartbeat is missed,
and the logs end at their last complete MCAP chunk (the writers complete one at least every
0.5 s; `minority log repair` makes indexed copies). Not -disable-auto-cleanup: with it MPICH
still kills the job when a rank is killed, and MPI_Abort leaves a stuck rank running.
"""

from __future__ import annotations

import dataclasses
import queue
import signal
import sys
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from minority.protocol import keys as keymod
from minority.protocol.errors import ProtocolError
from minority.protocol.log import LogWriter
from minority.protocol.messages import Chunk, decode_as
from minority.protocol.session import Inbox
from minority.protocol.shards import shard_path
from minority.protocol.spec import Spec
from minority.render_server.assemble import AssembledStep, ChunkContext, StepAssembler
from minority.render_server.particles import ParticleCache
from minority.render_server.render_mpi import Layers, render_views_distributed

HEARTBEAT_S = 0.5  # every rank sends one this often
DEFAULT_RANK_TIMEOUT_S = 5.0  # no heartbeat this long: the rank is dead
DEFAULT_MAX_SIM_RANKS = 256  # sim ranks whose chunk keys the render ranks subscribe to
POLL_S = 0.005  # the MPI threads look for messages this often
HELD_BYTES = 1 << 30  # chunk payload bytes a rank holds for unreleased steps
TAG_UP, TAG_DOWN = 11, 12  # worker -> rank 0 (reports, beats), rank 0 -> worker (commands)
# cached rows' keys: flag bit, release sequence, sim rank, position in the rank's cache
_CACHED, _SEQ_BITS, _RANK_BITS, _POS_BITS = 1 << 62, 21, 14, 27


def owned_sim_ranks(rank: int, size: int, max_sim_ranks: int) -> list[int]:
    """The sim ranks whose chunks render rank `rank` of `size` receives."""
    return list(range(rank, max_sim_ranks, size))


def chunk_keys(run: str, rank: int, size: int, max_sim_ranks: int) -> list[str]:
    """Key expressions of the chunks render rank `rank` subscribes to."""
    return [keymod.chunk(run, "*", r) for r in owned_sim_ranks(rank, size, max_sim_ranks)]


# --- what a rank tells rank 0 about a chunk -------------------------------------------
@dataclass(frozen=True)
class ChunkReport:
    """One received chunk, as rank 0's assembler needs it (no particle data)."""

    step: int
    time_s: float
    sim_rank: int
    ranks: int
    spacing_m: float
    bounds_m: tuple
    prev_time_s: float | None
    sent_ns: int
    recv_ns: int
    nbytes: int
    schema: tuple  # ((name, dtype str, trailing shape), ...) of every field, positions too
    tracked: bool  # the chunk keeps the cache (has a context count)
    fresh: int  # its fresh rows

    @classmethod
    def of(cls, chunk: Chunk, recv_ns: int, nbytes: int) -> ChunkReport:
        return cls(chunk.step, chunk.time_s, chunk.rank, chunk.ranks, chunk.spacing_m,
                   chunk.bounds_m, chunk.prev_time_s, chunk.sent_ns, recv_ns, nbytes,
                   tuple((k, v.dtype.str, v.shape[1:]) for k, v in chunk.fields.items()),
                   chunk.context_ids is not None, chunk.fresh)

    def stub(self, run: str) -> Chunk:
        """A chunk with this metadata and field layout and no rows."""
        fields = {k: np.zeros((0, *shape), np.dtype(dt)) for k, dt, shape in self.schema}
        empty = np.zeros(0, np.int64) if self.tracked else None
        return Chunk(run, self.step, self.time_s, self.sim_rank, self.ranks, self.spacing_m,
                     self.bounds_m, fields, self.sent_ns, self.prev_time_s, empty, empty, False)


# --- the chunks a rank holds, and its share of a step ---------------------------------
class HeldChunks:
    """Chunks received and not yet released, by step and sim rank (the first of duplicates);
    chunks of steps released lately are not kept. At most HELD_BYTES (oldest steps go)."""

    def __init__(self, max_bytes: int = HELD_BYTES):
        self._steps: OrderedDict[int, dict[int, tuple[Chunk, int]]] = OrderedDict()
        self._released: deque[int] = deque(maxlen=1024)
        self._bytes, self._max = 0, max_bytes
        self._lock = threading.Lock()

    def add(self, chunk: Chunk, nbytes: int) -> None:
        with self._lock:
            if chunk.step in self._released:
                return
            step = self._steps.setdefault(chunk.step, {})
            if chunk.rank in step:
                return
            step[chunk.rank] = (chunk, nbytes)
            self._bytes += nbytes
            while self._bytes > self._max and len(self._steps) > 1:
                for _, n in self._steps.popitem(last=False)[1].values():
                    self._bytes -= n

    def take(self, step: int, sim_ranks: list[int]) -> list[Chunk]:
        """The chunks of `step` from `sim_ranks` (sorted), forgetting the step."""
        with self._lock:
            held = self._steps.pop(step, {})
            self._released.append(step)
            self._bytes -= sum(n for _, n in held.values())
        return [held[r][0] for r in sorted(sim_ranks) if r in held]


class RankCache(ParticleCache):
    """The particle cache of one render rank's sim ranks, with each row's release sequence
    number (the one-process cache appends rows in (release, sim rank, row) order)."""

    def _clear(self) -> None:
        super()._clear()
        self.seq = np.zeros(0, np.int64)

    def _keep(self, keep: np.ndarray) -> None:
        super()._keep(keep)
        self.seq = self.seq[keep]

    def apply_at(self, step: AssembledStep, seq: int) -> None:
        self.apply(step)
        added = len(self) - len(self.seq)
        if added:
            self.seq = np.concatenate([self.seq, np.full(added, seq, np.int64)])

    def keys(self) -> np.ndarray:
        """Tie keys [m] int64 of the cached rows (above every fresh row's key)."""
        n = len(self)
        if n and (int(self.seq.max()) >> _SEQ_BITS or int(self.rank.max()) >> _RANK_BITS
                  or n >> _POS_BITS):
            raise ValueError(f"the cache outgrew its tie keys: {n} rows (at most "
                             f"{1 << _POS_BITS}), sim ranks below {1 << _RANK_BITS}, releases "
                             f"below {1 << _SEQ_BITS}")
        return (_CACHED | self.seq << (_RANK_BITS + _POS_BITS)
                | self.rank.astype(np.int64) << _POS_BITS | np.arange(n, dtype=np.int64))


@dataclass(frozen=True)
class Release:
    """What every rank needs to build its share of a released step (sent by rank 0)."""

    seq: int  # release sequence number in the run
    step: int
    time_s: float
    prev_time_s: float | None
    spacing_m: float
    bounds_m: tuple | None
    sim_ranks: tuple[int, ...]  # whose chunks the step holds
    offsets: dict  # sim rank -> its first fresh row in the one-process step
    schema: tuple  # ((name, dtype, trailing shape), ...) of the step's merged fields
    tracked: bool


@dataclass
class Share:
    """This rank's part of a released step, completed from its cache."""

    step: int
    release: Release
    local: AssembledStep  # fresh rows, then the cached rows when cache_ok
    keys: np.ndarray  # [rows] int64
    fresh: int
    cache_ok: bool  # the cache is empty or holds the step's fields
    cached: int
    oldest_time_s: float
    oldest_step: int
    meta: AssembledStep | None = None  # rank 0: the assembled step (counts, times, flags)


def build_share(release: Release, chunks: list[Chunk], cache: RankCache) -> Share:
    """This rank's share of a released step from its chunks (sorted by sim rank), with the
    cache updated and the share completed from it (as assemble and particles do)."""
    names = [k for k, _, _ in release.schema]

    def join(arrays, empty):
        return empty if not arrays else arrays[0] if len(arrays) == 1 else np.concatenate(arrays)

    fields = {k: join([c.fields[k][:c.fresh] for c in chunks], np.zeros((0, *shape), dt))
              for k, dt, shape in release.schema}
    positions = join([c.positions[:c.fresh] for c in chunks], np.zeros((0, 3), np.float32))
    context = [ChunkContext(c.rank, c.context_ids, c.positions[c.fresh:],
                            {k: c.fields[k][c.fresh:] for k in names}, c.evict_ids,
                            c.context_reset)
               for c in chunks if c.context_ids is not None and (
                   len(c.context_ids) or len(c.evict_ids) or c.context_reset)]
    fresh_keys = [release.offsets[c.rank] + np.arange(c.fresh, dtype=np.int64) for c in chunks]
    local = AssembledStep(release.step, release.time_s, positions, fields, release.spacing_m,
                          0, 0, 0, 0.0, False, release.prev_time_s, release.bounds_m, context,
                          release.tracked)
    cache.apply_at(local, release.seq)
    local.context = []
    n = len(cache)
    ok = not n or sorted((k, v.dtype.str, v.shape[1:]) for k, v in fields.items()) == sorted(
        (k, v.dtype.str, v.shape[1:]) for k, v in cache.fields.items())
    keys = np.concatenate(fresh_keys) if fresh_keys else np.zeros(0, np.int64)
    fresh = len(positions)
    if ok and n and release.tracked:
        local.positions = np.concatenate([positions, cache.positions])
        local.fields = {k: np.concatenate([v, cache.fields[k]]) for k, v in fields.items()}
        keys = np.concatenate([keys, cache.keys()])
    return Share(release.step, release, local, keys, fresh, ok, n if release.tracked else 0,
                 float(cache.time_s.min()) if n else 0.0, int(cache.step.min()) if n else 0)


@dataclass
class Totals:
    """The step as one process would have counted it (for its Timing)."""

    particles: int
    completed: bool
    cached: int
    cache_age_s: float
    cache_age_steps: int


def render_share(comm, share: Share, spec: Spec, canvases: dict, layers: Layers):
    """Every rank (collective): agree whether the step is completed from the caches, then
    render_views_distributed on the shares. Returns rank 0's RenderedViews, this rank's
    PhaseTimes and the step's Totals."""
    info = comm.allgather((share.cache_ok, share.cached, share.oldest_time_s,
                           share.oldest_step, share.fresh))
    completed = share.release.tracked and all(ok for ok, *_ in info)
    local = share.local
    n = len(local.positions) if completed else share.fresh
    if n != len(local.positions):
        local = dataclasses.replace(local, positions=local.positions[:n],
                                    fields={k: v[:n] for k, v in local.fields.items()})
    local = dataclasses.replace(local, completed=completed)
    results, times = render_views_distributed(comm, local, spec, canvases, keys=share.keys[:n],
                                              layers=layers)
    cached = sum(c for _, c, *_ in info) if completed else 0
    holding = [i for i in info if i[1]]
    age_s = max(0.0, share.release.time_s - min(i[2] for i in holding)) if cached else 0.0
    age_steps = max(0, share.step - min(i[3] for i in holding)) if cached else 0
    return results, times, Totals(sum(i[4] for i in info) + cached, completed, cached, age_s,
                                  age_steps)


def _empty_share(release: Release) -> Share:
    """A share without rows (a rank that holds nothing of the step, or missed its release)."""
    return build_share(release, [], RankCache())


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


# --- ranks k > 0 -----------------------------------------------------------------------
class Worker:
    """A render rank k > 0: receives its sim ranks' chunks, logs them to its shard, reports
    them to rank 0, and renders its share of the steps rank 0 names."""

    def __init__(self, ctl, draw, session, run: str, spec: Spec,
                 max_sim_ranks: int = DEFAULT_MAX_SIM_RANKS,
                 rank_timeout_s: float = DEFAULT_RANK_TIMEOUT_S):
        self.ctl, self.draw, self.run, self.spec = ctl, draw, run, spec
        self.rank = ctl.rank
        self.rank_timeout_s = rank_timeout_s
        self.held = HeldChunks()
        self.commands: queue.SimpleQueue = queue.SimpleQueue()
        self._inbox = Inbox(session, chunk_keys(run, self.rank, ctl.size, max_sim_ranks),
                            256, 1 << 30)
        self._writer: LogWriter | None = None
        self._unlogged: list = []  # chunks that came while no shard was open
        self._send_lock = threading.Lock()
        self.received = self.rejected = 0

    def _up(self, message) -> None:
        with self._send_lock:
            self.ctl.send(message, dest=0, tag=TAG_UP)

    def _io(self) -> None:
        """Chunks from zenoh, commands and beats from rank 0, beats to rank 0, the watchdog."""
        last_seen = last_beat = time.monotonic()
        while True:
            item = self._inbox.get(timeout=POLL_S)
            if item is not None:
                self._chunk(item)
            while self.ctl.iprobe(source=0, tag=TAG_DOWN):
                message = self.ctl.recv(source=0, tag=TAG_DOWN)
                last_seen = time.monotonic()
                kind = message[0]
                if kind == "open":
                    self._open(message[1])
                elif kind == "close":
                    self._close()
                elif kind != "beat":
                    self.commands.put(message)
                if kind == "stop":
                    return
            now = time.monotonic()
            if now - last_beat >= HEARTBEAT_S:
                self._up(("beat",))
                last_beat = now
                if self._writer is not None:
                    self._writer.keep(self._writer.flush)
            if now - last_seen > self.rank_timeout_s:
                print(f"minority serve: render rank {self.rank}: nothing from rank 0 for "
                      f"{self.rank_timeout_s:g} s: it died; this rank stops", file=sys.stderr,
                      flush=True)
                self._close()
                self.ctl.Abort(1)  # ends every rank (rank 0 too, if it is stuck)

    def _chunk(self, item) -> None:
        try:
            chunk = decode_as(item.payload, Chunk)
        except ProtocolError as exc:
            chunk = None
            self.rejected += 1
            self._up(("report", f"render rank {self.rank}: rejected chunk on {item.key}: {exc}"))
        self._log(item.key, item.payload, item.recv_ns, chunk)
        if chunk is not None:
            self.received += 1
            self.held.add(chunk, len(item.payload))
            self._up(("report", ChunkReport.of(chunk, item.recv_ns, len(item.payload))))

    def _log(self, key, payload, recv_ns, chunk) -> None:
        if self._writer is None:
            if len(self._unlogged) < 256:
                self._unlogged.append((key, payload, recv_ns, chunk))
            return
        self._writer.keep(self._writer.write_payload, key, payload, recv_ns, chunk)

    def _open(self, path: str | None) -> None:
        self._close()
        self.commands.put(("open",))  # the main loop starts a new cache
        if path is None:
            self._unlogged.clear()
            return
        shard = shard_path(path, self.rank)
        try:
            self._writer = LogWriter(shard, metadata={"run": self.run, "side": "server",
                                                      "render_rank": str(self.rank)})
            self._writer.flush()  # the header on disk: a killed rank leaves a readable shard
        except OSError as exc:
            self._up(("report", f"render rank {self.rank}: cannot open its log {shard}: {exc}"))
            return
        for args in self._unlogged:
            self._log(*args)
        self._unlogged.clear()

    def _close(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._writer = None

    def serve(self) -> int:
        """Until rank 0 says stop. Returns the exit status."""
        io = threading.Thread(target=self._io, name="minority-mpi", daemon=True)
        io.start()
        cache, pending, canvases, layers = RankCache(), {}, {}, Layers()
        while True:
            message = self.commands.get()
            kind = message[0]
            if kind == "stop":
                break
            if kind == "open":
                cache, pending = RankCache(), {}
            elif kind == "release":
                release = message[1]
                chunks = self.held.take(release.step, list(release.sim_ranks))
                pending[release.seq] = build_share(release, chunks, cache)
            elif kind == "drop":
                pending.pop(message[1], None)
            elif kind == "render":
                release, spec_payload = message[1], message[2]
                if spec_payload is not None:
                    self.spec = decode_as(spec_payload, Spec)
                share = pending.pop(release.seq, None) or _empty_share(release)
                for seq in [s for s in pending if s < release.seq]:
                    del pending[seq]  # replaced at rank 0 before it was rendered
                render_share(self.draw, share, self.spec, canvases, layers)
        io.join()
        self._close()
        self._inbox.close()
        return 0


def ignore_stop_signals() -> None:
    """Ranks k > 0 end when rank 0 says so (or dies), not on the launcher's SIGINT/SIGTERM:
    rank 0 receives those, finishes its collective and stops them."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


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
