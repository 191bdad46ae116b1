"""Step assembly: collect the chunks of one step from every rank, in bounded memory.

A step is complete when every rank named in its chunk headers has sent it, when the missing
ranks have ended or died, or `timeout_s` after its first chunk (then flagged incomplete).
It carries the fields every received chunk holds with one dtype and shape per particle.
At most `max_pending` steps are held; past that, the oldest is released as incomplete.
Duplicates and chunks of steps already released are counted and dropped.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from protocol.messages import Chunk

DEFAULT_TIMEOUT_S = 5.0
DEFAULT_MAX_PENDING = 8


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
class AssembledStep:
    """All particles of one step, merged over ranks."""

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


@dataclass
class AssemblyStats:
    chunks: int = 0
    duplicates: int = 0
    late: int = 0  # chunks of steps already released
    timed_out: int = 0
    evicted: int = 0  # released early because too many steps were pending
    mismatched_fields: int = 0  # fields left out of a step: ranks sent other dtypes or shapes


class StepAssembler:
    def __init__(self, timeout_s: float = DEFAULT_TIMEOUT_S, max_pending: int = DEFAULT_MAX_PENDING):
        self.timeout_ns = int(timeout_s * 1e9)
        self.max_pending = max_pending
        self.pending: OrderedDict[int, PendingStep] = OrderedDict()
        self.released_up_to = -1  # highest step released
        self.gone: set[int] = set()  # ranks that ended or died
        self.stats = AssemblyStats()

    def add(self, chunk: Chunk, recv_ns: int, nbytes: int) -> list[AssembledStep]:
        """Take one chunk; returns the steps it completes (or evicts), oldest first."""
        self.stats.chunks += 1
        if chunk.step <= self.released_up_to and chunk.step not in self.pending:
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
        done = self._release_complete(recv_ns)
        while len(self.pending) > self.max_pending:
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
        return all(r in p.chunks or r in self.gone for r in range(p.ranks))

    def _release_complete(self, now_ns: int) -> list[AssembledStep]:
        return [self._release(s, now_ns, incomplete=False)
                for s, p in list(self.pending.items()) if self._complete(p)]

    def _release(self, step: int, now_ns: int, incomplete: bool) -> AssembledStep:
        p = self.pending.pop(step)
        self.released_up_to = max(self.released_up_to, step)
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

        merged = {k: join([c.fields[k] for c in chunks]) for k in sorted(names)}
        # receive time from the senders' stamps (one host, or synchronized clocks); from the
        # first arrival when a stamp is missing or lies in the future (clock skew)
        start_ns = p.first_sent_ns if 0 < p.first_sent_ns <= p.first_ns else p.first_ns
        # every rank reports the same previous step time: rank 0's, else the first known
        prev = next((c.prev_time_s for c in chunks if c.prev_time_s is not None), None)
        return AssembledStep(
            step=step, time_s=p.time_s,
            positions=join([c.positions for c in chunks]), fields=merged,
            spacing_m=chunks[0].spacing_m, ranks_expected=p.ranks, ranks_received=len(chunks),
            nbytes=p.nbytes, receive_s=(now_ns - start_ns) * 1e-9,
            incomplete=incomplete or len(chunks) < p.ranks, prev_time_s=prev)
