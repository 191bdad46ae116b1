"""Repartition a step's particles across MPI render ranks: one count-balanced k-d brick each.

Every rank holds some of the step's particles (as they arrived). The ranks agree on a k-d
tree with one leaf per rank, chosen on a sample gathered from all of them (a global stride,
so each rank contributes in proportion to its count; at most SAMPLE particles), then move
every particle to the rank of its leaf with one Alltoallv per array. The split rule is the
one of render_server.bricks (each node split along its sample's longest axis), generalized
to any rank count: a node for k ranks puts floor(k / 2) / k of its sample on the low side.
Planes compare (coordinate, key), so particles lying on a plane (a lattice layer) are split
by key and the bricks stay balanced to the sampling error even on lattices.

No ghosts: primary visibility is composited by depth across ranks (render_server.composite),
so a sphere crossing a brick face is drawn whole by the one rank that holds it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from minority.render_server.bricks import _sort_by_leaf, as_positions, extent
from numba import njit, prange

SAMPLE = 1 << 16  # particles, over all ranks, that choose the split planes
LEAF = -1  # axis of a leaf node


@dataclass
class KdTree:
    """Nodes in build order, root first; a leaf names the rank that owns its brick."""

    axis: np.ndarray  # [nodes] int64: split axis 0..2, LEAF for a leaf
    plane: np.ndarray  # [nodes] float64, m: low side is x < plane or (x == plane, key < pkey)
    pkey: np.ndarray  # [nodes] int64: the key threshold on the plane
    low: np.ndarray  # [nodes] int64: child nodes (-1 for a leaf)
    high: np.ndarray  # [nodes] int64
    rank: np.ndarray  # [nodes] int64: the owner of a leaf (-1 for an inner node)
    boxes: np.ndarray  # [ranks, 2, 3] float64, m: each rank's brick (lo, hi corners)


@dataclass
class Partition:
    """This rank's particles after the exchange, and what the exchange found."""

    positions: np.ndarray  # [m, 3], the input's dtype, m
    fields: dict[str, np.ndarray]  # [m] or [m, k], as given
    keys: np.ndarray  # [m] int64: each particle's tie-break key (its global row)
    counts: np.ndarray  # [ranks] int64: particles each rank holds after the exchange
    tree: KdTree
    sample_s: float  # counting, sampling and agreeing on the tree, s
    exchange_s: float  # classification and the Alltoallv of every array, s


def build_tree(sample: np.ndarray, sample_keys: np.ndarray, ranks: int, lo: np.ndarray,
               hi: np.ndarray) -> KdTree:
    """A k-d tree with `ranks` leaves over sample positions [m, 3] (m) with keys [m] int64,
    inside the box lo..hi [3] (m). Leaf ranks are in tree order (low side first)."""
    axis, plane, pkey, low, high, rank, boxes = [], [], [], [], [], [], {}

    def node(index: np.ndarray, k: int, first: int, box_lo: np.ndarray, box_hi: np.ndarray) -> int:
        me = len(axis)
        axis.append(LEAF)
        plane.append(0.0)
        pkey.append(0)
        low.append(-1)
        high.append(-1)
        rank.append(-1)
        if k == 1:
            rank[me] = first
            boxes[first] = (box_lo, box_hi)
            return me
        pts = sample[index]
        span = pts.max(axis=0) - pts.min(axis=0) if len(index) > 1 else box_hi - box_lo
        a = int(np.argmax(span))  # longest axis (first on ties), as bricks._kd_level
        k_low = k // 2
        c = len(index) * k_low // k  # sample particles on the low side
        if c == 0 or c == len(index):  # too few samples: the middle of the box, by coordinate
            p, pk = 0.5 * (box_lo[a] + box_hi[a]), np.iinfo(np.int64).min
            go_low = pts[:, a] < p
        else:
            order = np.lexsort((sample_keys[index], pts[:, a]))
            t = index[order[c]]
            p, pk = float(sample[t, a]), int(sample_keys[t])
            go_low = np.zeros(len(index), bool)
            go_low[order[:c]] = True
        axis[me], plane[me], pkey[me] = a, p, pk
        split_hi, split_lo = box_hi.copy(), box_lo.copy()
        split_hi[a] = split_lo[a] = min(max(p, box_lo[a]), box_hi[a])
        low[me] = node(index[go_low], k_low, first, box_lo, split_hi)
        high[me] = node(index[~go_low], k - k_low, first + k_low, split_lo, box_hi)
        return me

    node(np.arange(len(sample)), ranks, 0, np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    return KdTree(np.array(axis, np.int64), np.array(plane, np.float64), np.array(pkey, np.int64),
                  np.array(low, np.int64), np.array(high, np.int64), np.array(rank, np.int64),
                  np.array([boxes[r] for r in range(ranks)], np.float64).reshape(ranks, 2, 3))


@njit(parallel=True, cache=True, nogil=True)
def _classify(positions, keys, axis, plane, pkey, low, high, rank, dest):
    """dest[p]: the rank whose brick holds particle p (descend the tree from the root)."""
    for p in prange(positions.shape[0]):
        node = 0
        while axis[node] >= 0:
            x = positions[p, axis[node]]
            if x < plane[node] or (x == plane[node] and keys[p] < pkey[node]):
                node = low[node]
            else:
                node = high[node]
        dest[p] = rank[node]


def classify(positions: np.ndarray, keys: np.ndarray, tree: KdTree) -> np.ndarray:
    """The owner rank [n] int64 of each of positions [n, 3] (m) with keys [n] int64."""
    dest = np.empty(len(positions), np.int64)
    _classify(as_positions(positions), keys, tree.axis, tree.plane, tree.pkey, tree.low,
              tree.high, tree.rank, dest)
    return dest


def global_rows(comm, n: int) -> np.ndarray:
    """Default keys: each particle's row in the concatenation of every rank's particles in
    rank order (rank 0's first), the order a one-process render would see them in."""
    from mpi4py import MPI

    offset = comm.exscan(n, op=MPI.SUM) if comm.size > 1 else 0
    return np.arange(n, dtype=np.int64) + (offset or 0)


def _alltoallv_rows(comm, send: np.ndarray, send_counts: np.ndarray,
                    recv_counts: np.ndarray) -> np.ndarray:
    """Exchange rows of send [n, ...] (grouped by destination rank, send_counts [ranks] rows
    each); returns the received rows [sum(recv_counts), ...], grouped by source rank. Counts
    are in rows of a contiguous MPI type, so no count overflows int32 below 2^31 rows."""
    from mpi4py import MPI

    send = np.ascontiguousarray(send)
    row_bytes = send[:1].nbytes if len(send) else int(np.prod(send.shape[1:], dtype=np.int64)
                                                       * send.dtype.itemsize)
    recv = np.empty((int(recv_counts.sum()), *send.shape[1:]), send.dtype)
    if row_bytes == 0:
        return recv
    row = MPI.BYTE.Create_contiguous(row_bytes).Commit()
    try:
        sd = np.concatenate([[0], np.cumsum(send_counts)[:-1]])
        rd = np.concatenate([[0], np.cumsum(recv_counts)[:-1]])
        comm.Alltoallv([send.view(np.uint8).reshape(-1), (send_counts, sd), row],
                       [recv.view(np.uint8).reshape(-1), (recv_counts, rd), row])
    finally:
        row.Free()
    return recv


def agree_tree(comm, positions: np.ndarray, keys: np.ndarray, sample: int = SAMPLE) -> KdTree:
    """The ranks' common k-d tree: a sample of every rank's particles gathered on rank 0,
    split there, broadcast (collective)."""
    from mpi4py import MPI

    n = len(positions)
    total = comm.allreduce(n, op=MPI.SUM)
    if total == 0:
        raise ValueError("no particles to repartition on any rank")
    stride = max(1, total // sample)
    lo, hi = extent(positions) if n else (np.full(3, np.inf), np.full(3, -np.inf))
    comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
    comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
    mine = np.ascontiguousarray(positions[::stride], np.float64)
    mine_keys = np.ascontiguousarray(keys[::stride])
    sizes = np.array(comm.gather(len(mine), root=0) or [], np.int64)
    gathered = gathered_keys = None
    if comm.rank == 0:
        gathered = np.empty((int(sizes.sum()), 3))
        gathered_keys = np.empty(int(sizes.sum()), np.int64)
        displ = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        comm.Gatherv(mine, [gathered, (sizes * 3, displ * 3), MPI.DOUBLE], root=0)
        comm.Gatherv(mine_keys, [gathered_keys, (sizes, displ), MPI.INT64_T], root=0)
    else:
        comm.Gatherv(mine, None, root=0)
        comm.Gatherv(mine_keys, None, root=0)
    tree = build_tree(gathered, gathered_keys, comm.size, lo, hi) if comm.rank == 0 else None
    return comm.bcast(tree, root=0)


def exchange(comm, positions: np.ndarray, fields: dict[str, np.ndarray],
             keys: np.ndarray | None = None, sample: int = SAMPLE) -> Partition:
    """Move this rank's particles (positions [n, 3] m, fields [n] or [n, k]) to the ranks
    whose bricks hold them (collective: every rank calls it, with the same field names).
    keys [n] int64: distinct tie-break keys, default `global_rows`. Within one source rank,
    particles keep their order."""
    from mpi4py import MPI

    t0 = time.perf_counter()
    n = len(positions)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must be [n, 3], got shape {positions.shape}")
    for name, values in fields.items():
        if len(values) != n:
            raise ValueError(f"field {name!r} has {len(values)} rows for {n} particles")
    names = sorted(fields)
    every = comm.allgather(names)
    if any(other != names for other in every):
        raise ValueError(f"ranks disagree on the fields to exchange: {every}")
    keys = global_rows(comm, n) if keys is None else np.ascontiguousarray(keys, np.int64)
    if keys.shape != (n,):
        raise ValueError(f"keys must be [{n}], got shape {keys.shape}")
    if comm.size == 1:  # one brick: nothing to agree on or move
        lo, hi = extent(as_positions(positions)) if n else (np.zeros(3), np.zeros(3))
        none = np.array([-1], np.int64)
        tree = KdTree(np.array([LEAF], np.int64), np.zeros(1), np.zeros(1, np.int64), none,
                      none, np.zeros(1, np.int64), np.array([[lo, hi]], np.float64))
        t1 = time.perf_counter()
        return Partition(positions, {k: fields[k] for k in names}, keys, np.array([n]), tree,
                         t1 - t0, 0.0)
    tree = agree_tree(comm, positions, keys, sample)
    t1 = time.perf_counter()
    dest = classify(positions, keys, tree)
    order, bounds = np.empty(n, np.int64), np.empty(comm.size + 1, np.int64)
    _sort_by_leaf(dest, comm.size, order, bounds)  # stable counting sort by destination
    send_counts = np.diff(bounds)
    recv_counts = np.empty(comm.size, np.int64)
    comm.Alltoall([send_counts, MPI.INT64_T], [recv_counts, MPI.INT64_T])
    out_pos = _alltoallv_rows(comm, positions[order], send_counts, recv_counts)
    out_keys = _alltoallv_rows(comm, keys[order], send_counts, recv_counts)
    out_fields = {k: _alltoallv_rows(comm, fields[k][order], send_counts, recv_counts)
                  for k in names}
    counts = np.array(comm.allgather(len(out_pos)), np.int64)
    return Partition(out_pos, out_fields, out_keys, counts, tree, t1 - t0,
                     time.perf_counter() - t1)
