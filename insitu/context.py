"""Which particles outside the regions of interest a rank sends, so the render server can
draw complete pictures while the chunks carry only the regions (render_server.particles).

The server keeps the last state it received of every particle by id. A rank therefore
sends a particle outside the step's regions (a *context row*) only when the server's copy
is missing or stale: at the first due step, after a reset (a spec change, a dropped chunk),
and when the particle moved more than `tolerance_m` from where it was last sent (default 0:
any change of its position; fields that change at rest, such as pressure, show as of the
particle's last move). Particles
inside the regions travel in every due chunk as before; when one of them is still cached
(it entered a region), or a cached one left the rank (migration), its id is *evicted* so
the server never draws a particle twice.

State: dense arrays indexed by particle id (grown on demand): the position last sent
(NaN: not in the server's cache), 12 bytes per id.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_TOLERANCE_M = 0.0  # resend a context row whose position changed at all

@dataclass
class ContextSplit:
    """What one due chunk carries besides its fresh rows."""

    rows: np.ndarray  # [k] intp: rows of the rank's particle arrays to send as context
    evict: np.ndarray  # [e] int64: ids the server's cache must drop
    reset: bool  # the server drops every row this rank cached before applying the rest


class ContextTracker:
    """One rank's view of what the render server has cached from it."""

    def __init__(self, tolerance_m: float):
        if not (np.isfinite(tolerance_m) and tolerance_m >= 0.0):
            raise ValueError(f"context tolerance must be a finite length >= 0 m, got "
                             f"{tolerance_m}")
        self.tolerance_m = tolerance_m
        self._sent = np.full((0, 3), np.nan, dtype=np.float32)  # [ids, 3] m, NaN: not cached
        self._reset = True
        self._cached = 0  # ids whose row of _sent is not NaN
        self.context_rows = 0  # rows sent as context so far
        self.evicted = 0
        self.resets = 0

    def reset(self) -> None:
        """Forget what the server holds: the next split resends every outside particle."""
        self._reset = True

    def cached(self, pid: np.ndarray) -> np.ndarray:
        """[n] bool: which of the ids pid [n] the server holds from this rank (none while a
        reset is pending)."""
        if self._reset or not self._cached:
            return np.zeros(len(pid), dtype=bool)
        out = np.zeros(len(pid), dtype=bool)
        known = pid < len(self._sent)
        out[known] = ~np.isnan(self._sent[pid[known], 0])
        return out

    def split(self, pid: np.ndarray, x: np.ndarray, outside: np.ndarray,
              resend: bool = False) -> ContextSplit:
        """pid [n] int ids and x [n, 3] m of the rank's particles; outside [n] bool: the
        particles the server must draw from its cache at this step (outside every region of
        the request, and within its decimation stride). resend: every outside row goes as
        a context row, moved or not (a snapshot: every particle in the chunk, the cached
        ones kept cached rather than evicted). Returns the context rows, the evictions and
        the reset flag, and records them as sent."""
        reset, self._reset = self._reset, False
        if reset:
            self._sent[:] = np.nan
            self._cached = 0
            self.resets += 1
        if not self._cached and not outside.any():  # nothing cached, nothing to cache
            return ContextSplit(np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.int64), reset)
        top = int(pid.max()) + 1 if len(pid) else 0
        if top > len(self._sent):
            grown = np.full((max(top, 2 * len(self._sent)), 3), np.nan, dtype=np.float32)
            grown[:len(self._sent)] = self._sent
            self._sent = grown
        cached = ~np.isnan(self._sent[:, 0])  # [ids]
        here = np.zeros(len(self._sent), dtype=bool)
        here[pid] = True
        # cached ids that are no longer outside here: entered a region, or left the rank
        inside_ids = pid[~outside]
        gone = cached & ~here
        gone[inside_ids] |= cached[inside_ids]
        evict = np.flatnonzero(gone).astype(np.int64)
        self._sent[evict] = np.nan
        rows = np.flatnonzero(outside)
        last = self._sent[pid[rows]]  # [m, 3], NaN where not cached
        now = x[rows].astype(np.float32)  # as the wire carries them: float64 rounding is no move
        new = np.isnan(last[:, 0])  # not cached: sent whatever their position
        moved = new.copy()
        if resend:
            moved[:] = True
        elif self.tolerance_m > 0.0:
            step = (now - last).astype(np.float64)
            moved |= np.einsum("ij,ij->i", step, step) > self.tolerance_m ** 2
        else:
            moved |= np.any(now != last, axis=1)
        rows = rows[moved]
        self._sent[pid[rows]] = now[moved]
        self._cached += int(new.sum()) - len(evict)
        self.context_rows += len(rows)
        self.evicted += len(evict)
        return ContextSplit(rows, evict, reset)
