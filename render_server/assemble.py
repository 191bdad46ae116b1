"""Step assembly: collect the chunks of one step from every rank, in bounded memory.

A step is complete when every rank named in its chunk headers has sent it, when the missing
ranks have ended or died, or `timeout_s` after its first chunk (then flagged incomplete).
It carries the fields every received chunk holds with one dtype and shape per particle.
At most `max_pending` steps and `max_pending_bytes` of their chunks are held; past that,
the oldest is released as incomplete. The bounds are generous because after a pause (a
stopped or slow server) each rank's backlog arrives one rank after the other: every step
must wait for its last rank's chunk.
Duplicates and chunks of steps already released are counted and dropped. "Released" is
known exactly for the last RELEASED_WINDOW steps; a chunk older than all of those is late
too. One chunk with an absurd step number therefore cannot hide the steps that follow it.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from minority.protocol.messages import Chunk

DEFAULT_TIMEOUT_S = 5.0
DEFAULT_MAX_PENDING = 256  # steps
DEFAULT_MAX_PENDING_BYTES = 1 << 30  # chunk payload bytes held in pending steps
RELEASED_WINDOW = 1024  # released step numbers remembered exactly


@dataclass
class PendingStep:
    step: int
    time_s: float
    ranks: int  # ranks named in the headers
    first_ns: int  # arrival of the first chunk, ns
    first_sent_ns: int = 0  # earliest sender stamp of the step's chunks, ns (0: none)
    last_ns: int = 0
    chunks: dict[int, Chunk] = field(default_factory=dict)
    nbytes: int = 0


@dataclass
class ChunkContext:
    """A chunk's update of the server's particle cache (render_server.particles)."""

    rank: int
    ids: np.ndarray  # [k] int64
    positions: np.ndarray  # [k, 3] float32, m
    fields: dict[str, np.ndarray]  # the step's merged fields, [k] or [k, c]
    evict: np.ndarray  # [e] int64
    reset: bool


@dataclass
class AssembledStep:
    """All particles of one step, merged over ranks (the fresh rows: context rows of the
    chunks are in `context`, for the particle cache)."""

    step: int
    time_s: float
    positions: np.ndarray  # [n, 3] float32, m
    fields: dict[str, np.ndarray]  # fields every received chunk carries, [n] or [n, k]
    spacing_m: float
    ranks_expected: int
    ranks_received: int
    nbytes: int
    receive_s: float  # earliest send of the step's chunks to assembled, s (see _release)
    incomplete: bool
    prev_time_s: float | None = None  # simulated time of the step before, s (None: unknown)
    # the simulation's domain (lo, hi corners, m): the union of the chunks' bounds
    bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    context: list[ChunkContext] = field(default_factory=list)
    tracked: bool = False  # every chunk keeps the cache (it may complete the step)
    # set by the particle cache: every particle present, those drawn from it, their age
    completed: bool = False
    cached: int = 0
    cache_age_s: float = 0.0  # simulated s since the oldest cached row was sent
    cache_age_steps: int = 0


@dataclass
class AssemblyStats:
    chunks: int = 0
    duplicates: int = 0
    late: int = 0  # chunks of steps already released
    timed_out: int = 0
    evicted: int = 0  # released early because too many steps were pending
    mismatched_fields: int = 0  # fields left out of a step: ranks sent other dtypes or shapes


class StepAssembler:
    def __init__(self, timeout_s: float = DEFAULT_TIMEOUT_S, max_pending: int = DEFAULT_MAX_PENDING,
                 max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES):
        self.timeout_ns = int(timeout_s * 1e9)
        self.max_pending = max_pending
        self.max_pending_bytes = max_pending_bytes
        self.pending: OrderedDict[int, PendingStep] = OrderedDict()
        self.pending_bytes = 0
        self._released: deque[int] = deque()  # the last RELEASED_WINDOW released steps
        self._released_set: set[int] = set()
        self._floor = -1  # steps below the oldest remembered release are late
        self.gone: set[int] = set()  # ranks that ended or died
        self.stats = AssemblyStats()

    def is_late(self, step: int) -> bool:
        """Whether chunks of `step` come after the step was released."""
        return step not in self.pending and (step in self._released_set or step < self._floor)

    def add(self, chunk: Chunk, recv_ns: int, nbytes: int) -> list[AssembledStep]:
        """Take one chunk; returns the steps it completes (or evicts), oldest first."""
        self.stats.chunks += 1
        if self.is_late(chunk.step):
            self.stats.late += 1
            return []
        p = self.pending.get(chunk.step)
        if p is None:
            p = self.pending[chunk.step] = PendingStep(chunk.step, chunk.time_s, chunk.ranks,
                                                       recv_ns)
        if chunk.rank in p.chunks:
            self.stats.duplicates += 1
            return []
        p.ranks = max(p.ranks, chunk.ranks)
        p.chunks[chunk.rank] = chunk
        if chunk.sent_ns > 0:
            p.first_sent_ns = min(p.first_sent_ns or chunk.sent_ns, chunk.sent_ns)
        p.last_ns = recv_ns
        p.nbytes += nbytes
        self.pending_bytes += nbytes
        done = self._release_complete(recv_ns)
        while len(self.pending) > self.max_pending or (
                len(self.pending) > 1 and self.pending_bytes > self.max_pending_bytes):
            step = next(iter(self.pending))
            self.stats.evicted += 1
            done.append(self._release(step, recv_ns, incomplete=True))
        return done

    def rank_gone(self, rank: int, now_ns: int) -> list[AssembledStep]:
        """A rank ended or died: it will send no more chunks."""
        self.gone.add(rank)
        return self._release_complete(now_ns)

    def expire(self, now_ns: int) -> list[AssembledStep]:
        """Release steps whose first chunk is older than the timeout (incomplete)."""
        out = []
        for step, p in list(self.pending.items()):
            if now_ns - p.first_ns >= self.timeout_ns:
                self.stats.timed_out += 1
                out.append(self._release(step, now_ns, incomplete=True))
        return out

    def drain(self, now_ns: int) -> list[AssembledStep]:
        """Release every pending step, oldest first (incomplete unless every rank sent)."""
        return [self._release(s, now_ns, incomplete=not self._complete(p))
                for s, p in sorted(self.pending.items())]

    def _complete(self, p: PendingStep) -> bool:
        """Every rank below p.ranks sent its chunk or is gone (O(chunks + gone), not
        O(p.ranks): a header may name up to MAX_RANKS ranks)."""
        if len(p.chunks) >= p.ranks:
            return True
        gone = sum(1 for r in self.gone if r < p.ranks and r not in p.chunks)
        return len(p.chunks) + gone >= p.ranks

    def _release_complete(self, now_ns: int) -> list[AssembledStep]:
        return [self._release(s, now_ns, incomplete=False)
                for s, p in list(self.pending.items()) if self._complete(p)]

    def _release(self, step: int, now_ns: int, incomplete: bool) -> AssembledStep:
        p = self.pending.pop(step)
        self.pending_bytes -= p.nbytes
        self._released.append(step)
        self._released_set.add(step)
        if len(self._released) > RELEASED_WINDOW:
            self._released_set.discard(self._released.popleft())
            self._floor = min(self._released_set)
        chunks = [p.chunks[r] for r in sorted(p.chunks)]
        names = set(chunks[0].fields)
        for c in chunks[1:]:
            names &= set(c.fields)
        names.discard("positions")
        # a field whose ranks disagree on dtype or components cannot be merged: left out
        clash = {k for k in names if len({(c.fields[k].dtype, c.fields[k].shape[1:])
                                          for c in chunks}) > 1}
        self.stats.mismatched_fields += len(clash)
        names -= clash
        def join(arrays: list[np.ndarray]) -> np.ndarray:
            return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)  # no copy for one

        merged = {k: join([c.fields[k][:c.fresh] for c in chunks]) for k in sorted(names)}
        context = [ChunkContext(c.rank, c.context_ids, c.positions[c.fresh:],
                                {k: c.fields[k][c.fresh:] for k in names},
                                c.evict_ids, c.context_reset)
                   for c in chunks if c.context_ids is not None and (
                       len(c.context_ids) or len(c.evict_ids) or c.context_reset)]
        # receive time from the senders' stamps (one host, or synchronized clocks); from the
        # first arrival when a stamp is missing or lies in the future (clock skew)
        start_ns = p.first_sent_ns if 0 < p.first_sent_ns <= p.first_ns else p.first_ns
        # every rank reports the same previous step time: rank 0's, else the first known
        prev = next((c.prev_time_s for c in chunks if c.prev_time_s is not None), None)
        lo = tuple(float(min(c.bounds_m[0][i] for c in chunks)) for i in range(3))
        hi = tuple(float(max(c.bounds_m[1][i] for c in chunks)) for i in range(3))
        return AssembledStep(
            step=step, time_s=p.time_s,
            positions=join([c.positions[:c.fresh] for c in chunks]), fields=merged,
            spacing_m=chunks[0].spacing_m, ranks_expected=p.ranks, ranks_received=len(chunks),
            nbytes=p.nbytes, receive_s=(now_ns - start_ns) * 1e-9,
            incomplete=incomplete or len(chunks) < p.ranks, prev_time_s=prev, bounds_m=(lo, hi),
            context=context, tracked=all(c.context_ids is not None for c in chunks))
