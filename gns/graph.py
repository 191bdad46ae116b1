"""Radius graph by a cell list (numba): every ordered pair (i, j), i != j, |x_i - x_j| <= r.

No cap on the neighbour count. Edges come sorted by receiver (then by sender's cell order), so
the message sum per receiver reads contiguous memory.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

MAX_CELLS = 64_000_000  # cell-list grid limit (start offsets: 8 bytes per cell)


@njit(cache=True)
def _cell_keys(pos, lo, inv_cell, dims):
    n = pos.shape[0]
    keys = np.empty(n, np.int64)
    for p in range(n):
        c0 = min(max(int((pos[p, 0] - lo[0]) * inv_cell), 0), dims[0] - 1)
        c1 = min(max(int((pos[p, 1] - lo[1]) * inv_cell), 0), dims[1] - 1)
        c2 = min(max(int((pos[p, 2] - lo[2]) * inv_cell), 0), dims[2] - 1)
        keys[p] = (c0 * dims[1] + c1) * dims[2] + c2
    return keys


@njit(cache=True)
def _cell_starts(sorted_keys, n_cells):
    start = np.zeros(n_cells + 1, np.int64)
    for k in sorted_keys:
        start[k + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    return start


@njit(parallel=True, cache=True)
def _pairs(pos, order, start, keys, dims, r2, counts, senders, fill):
    """fill=False: count neighbours per receiver into counts; fill=True: write senders at
    the offsets in counts (exclusive prefix sums)."""
    n = pos.shape[0]
    for i in prange(n):
        k = keys[i]
        c2 = k % dims[2]
        c1 = (k // dims[2]) % dims[1]
        c0 = k // (dims[1] * dims[2])
        out = counts[i] if fill else 0
        got = 0
        for a in range(max(c0 - 1, 0), min(c0 + 2, dims[0])):
            for b in range(max(c1 - 1, 0), min(c1 + 2, dims[1])):
                for c in range(max(c2 - 1, 0), min(c2 + 2, dims[2])):
                    cell = (a * dims[1] + b) * dims[2] + c
                    for s in range(start[cell], start[cell + 1]):
                        j = order[s]
                        if j == i:
                            continue
                        d0 = pos[j, 0] - pos[i, 0]
                        d1 = pos[j, 1] - pos[i, 1]
                        d2 = pos[j, 2] - pos[i, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                            if fill:
                                senders[out + got] = j
                            got += 1
        if not fill:
            counts[i] = got


def radius_graph(pos: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """pos [n, 3] (any float dtype, m); returns (senders, receivers) int64 [E], receivers
    ascending. Messages flow sender -> receiver."""
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    n = pos.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not np.isfinite(pos).all():
        raise ValueError("radius_graph: non-finite particle positions")
    lo = pos.min(axis=0)
    extent = pos.max(axis=0) - lo
    dims = np.maximum((extent / radius).astype(np.int64) + 1, 1)
    if int(np.prod(dims)) > MAX_CELLS:
        raise ValueError(f"radius_graph: particles span {extent.round(3).tolist()} m, "
                         f"{int(np.prod(dims))} cells of {radius} m (limit {MAX_CELLS})")
    keys = _cell_keys(pos, lo, 1.0 / radius, dims)
    order = np.argsort(keys, kind="stable").astype(np.int64)
    start = _cell_starts(keys[order], int(np.prod(dims)))
    counts = np.zeros(n, np.int64)
    dummy = np.zeros(0, np.int64)
    _pairs(pos, order, start, keys, dims, radius * radius, counts, dummy, False)
    offsets = np.zeros(n, np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    senders = np.empty(int(counts.sum()), np.int64)
    _pairs(pos, order, start, keys, dims, radius * radius, offsets, senders, True)
    receivers = np.repeat(np.arange(n, dtype=np.int64), counts)
    return senders, receivers
