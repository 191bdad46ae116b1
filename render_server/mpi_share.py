"""What render ranks tell each other, and how a rank builds and renders its share of a step
(render_server.serve_mpi: the server on N ranks; rank 0's side there, the others' in
render_server.mpi_worker).

Every rank subscribes only to the chunks of its sim ranks (owned_sim_ranks: sim rank r goes
to render rank r % N), keeps them (HeldChunks) and, on a rank k > 0, reports each to rank 0
(ChunkReport: metadata and field layout, never particles). Rank 0 tells every rank each
released step (Release); each rank builds its share (build_share: its chunks' fresh rows,
completed from its RankCache) and all render their shares together (render_share).

Tie keys: a particle's key orders it as its row in the one-process step: fresh rows by sim
rank then row (the step's offsets, from rank 0), then cached rows by (release sequence that
added them, sim rank, cache position): the order in which the one-process cache appends them.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass

import numpy as np

from minority.protocol import keys as keymod
from minority.protocol.messages import Chunk
from minority.protocol.spec import Spec
from minority.render_server.assemble import AssembledStep, ChunkContext
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


def empty_share(release: Release) -> Share:
    """A share without rows (a rank that holds nothing of the step, or missed its release)."""
    return build_share(release, [], RankCache())
