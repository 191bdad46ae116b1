"""Repartition a step's particles across MPI render ranks: one count-balanced k-d brick each.

Every rank holds some of the step's particles (as they arrived). The ranks agree on a k-d
tree with one leaf per rank and move every particle to the rank of its leaf.

The tree: if the ranks already hold balanced slabs in rank order along an axis (a sim's
slab decomposition, its ranks' chunks in order), the planes between them, and nothing
moves. Otherwise it is chosen on a sample gathered from all ranks (a global stride, so each
rank contributes in proportion to its count; at most SAMPLE particles); the split rule is
the one of render_server.bricks (each node split along its sample's longest axis),
generalized to any rank count (a node for k ranks puts floor(k / 2) / k of its sample on
the low side), except that a node splits along another axis when that keeps notably more
particles on the rank they are on. Planes compare (coordinate, key), so particles lying on
a plane (a lattice layer) are split by key and the bricks stay balanced to the sampling
error even on lattices.

The move: rounds of one Alltoallv each, of packed rows (position, key, fields side by
side) built by numba passes over the particles that leave; those that stay are copied
straight into the result (a Pool keeps it from step to step). A round sends at most
ROUND_BYTES, so the send and receive buffers stay small.

No ghosts: primary visibility is composited by depth across ranks (render_server.composite),
so a sphere crossing a brick face is drawn whole by the one rank that holds it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from minority.render_server.bricks import as_positions, extent

SAMPLE = 1 << 16  # particles, over all ranks, that choose the split planes
LEAF = -1  # axis of a leaf node
KEEP_MARGIN = 0.05  # fraction of a node's sample an axis must keep in place to beat the longest
SLAB_BALANCE = 1.05  # most particles a rank may hold, over the mean, for its slab to stay as is
CHUNKS = 64  # particle chunks of the parallel grouping passes
ROUND_BYTES = 16 << 20  # most bytes a rank sends (and receives) in one exchange round


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


def _axis_choice(pts: np.ndarray, src: np.ndarray | None, c: int, first: int, k_low: int,
                 longest: int) -> int:
    """The split axis of a node: the longest one, unless another keeps notably more sample
    particles on the rank they came from (src [m]: each sample's source rank; the low side
    goes to ranks first .. first + k_low - 1). Slabs the ranks already hold stay put."""
    if src is None or c == 0 or c == len(pts):
        return longest
    mine_low = (src >= first) & (src < first + k_low)
    stays = np.empty(3, np.int64)
    for a in range(3):
        threshold = np.partition(pts[:, a], c)[c]  # the c-th coordinate: ties go either way
        below = pts[:, a] < threshold
        stays[a] = np.count_nonzero(below & mine_low) + np.count_nonzero(~below & ~mine_low)
    best = int(np.argmax(stays))
    return best if stays[best] - stays[longest] > KEEP_MARGIN * len(pts) else longest


def build_tree(sample: np.ndarray, sample_keys: np.ndarray, ranks: int, lo: np.ndarray,
               hi: np.ndarray, sources: np.ndarray | None = None) -> KdTree:
    """A k-d tree with `ranks` leaves over sample positions [m, 3] (m) with keys [m] int64,
    inside the box lo..hi [3] (m). Leaf ranks are in tree order (low side first). With
    sources [m] int64 (the rank each sample particle is on now), a node splits along the
    axis that keeps the most particles where they are when that beats the longest axis by
    more than KEEP_MARGIN of the node's sample (see _axis_choice)."""
    t = _TreeBuilder()

    def node(index: np.ndarray, k: int, first: int, box_lo: np.ndarray, box_hi: np.ndarray) -> int:
        me = t.add(k, first, box_lo, box_hi)
        if k == 1:
            return me
        pts = sample[index]
        span = pts.max(axis=0) - pts.min(axis=0) if len(index) > 1 else box_hi - box_lo
        k_low = k // 2
        c = len(index) * k_low // k  # sample particles on the low side
        a = _axis_choice(pts, None if sources is None else sources[index], c, first, k_low,
                         int(np.argmax(span)))  # longest axis (first on ties), as bricks
        if c == 0 or c == len(index):  # too few samples: the middle of the box, by coordinate
            p, pk = 0.5 * (box_lo[a] + box_hi[a]), np.iinfo(np.int64).min
            go_low = pts[:, a] < p
        else:
            order = np.lexsort((sample_keys[index], pts[:, a]))
            i = index[order[c]]
            p, pk = float(sample[i, a]), int(sample_keys[i])
            go_low = np.zeros(len(index), bool)
            go_low[order[:c]] = True
        split_hi, split_lo = t.split(me, a, p, pk, box_lo, box_hi)
        t.low[me] = node(index[go_low], k_low, first, box_lo, split_hi)
        t.high[me] = node(index[~go_low], k - k_low, first + k_low, split_lo, box_hi)
        return me

    node(np.arange(len(sample)), ranks, 0, np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    return t.tree(ranks)


class _TreeBuilder:
    """A KdTree's node lists as the tree is built, root first."""

    def __init__(self):
        self.axis, self.plane, self.pkey, self.low, self.high, self.rank = [], [], [], [], [], []
        self.boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, k: int, first: int, box_lo: np.ndarray, box_hi: np.ndarray) -> int:
        """A new node for ranks first..first+k-1 in the box [box_lo, box_hi]: rank first's
        leaf when k == 1. Returns its index."""
        me = len(self.axis)
        self.axis.append(LEAF)
        self.plane.append(0.0)
        self.pkey.append(0)
        self.low.append(-1)
        self.high.append(-1)
        self.rank.append(first if k == 1 else -1)
        if k == 1:
            self.boxes[first] = (box_lo, box_hi)
        return me

    def split(self, me: int, a: int, p: float, pk: int, box_lo: np.ndarray,
              box_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node `me` splits along axis a at (p, pk); returns (the low side's box_hi, the high
        side's box_lo)."""
        self.axis[me], self.plane[me], self.pkey[me] = a, p, pk
        split_hi, split_lo = box_hi.copy(), box_lo.copy()
        split_hi[a] = split_lo[a] = min(max(p, box_lo[a]), box_hi[a])
        return split_hi, split_lo

    def tree(self, ranks: int) -> KdTree:
        return KdTree(np.array(self.axis, np.int64), np.array(self.plane, np.float64),
                      np.array(self.pkey, np.int64), np.array(self.low, np.int64),
                      np.array(self.high, np.int64), np.array(self.rank, np.int64),
                      np.array([self.boxes[r] for r in range(ranks)],
                               np.float64).reshape(ranks, 2, 3))


@njit(parallel=True, cache=True, nogil=True)
def _first_last(positions, keys, out_coord, out_key):
    """Per axis a, the lexicographically first and last (coordinate, key) of the particles:
    out_coord [3, 2] float64, out_key [3, 2] int64 (column 0 first, 1 last; inf / -inf when
    there are none). Chunks in parallel, then combined."""
    n, n_chunks = positions.shape[0], CHUNKS
    coord = np.empty((n_chunks, 3, 2))
    key = np.zeros((n_chunks, 3, 2), np.int64)
    for c in prange(n_chunks):
        for a in range(3):
            lo_x, lo_k, hi_x, hi_k = np.inf, 0, -np.inf, 0
            for p in range(c * n // n_chunks, (c + 1) * n // n_chunks):
                x, k = float(positions[p, a]), keys[p]
                if x < lo_x or (x == lo_x and k < lo_k):
                    lo_x, lo_k = x, k
                if x > hi_x or (x == hi_x and k > hi_k):
                    hi_x, hi_k = x, k
            coord[c, a, 0], coord[c, a, 1], key[c, a, 0], key[c, a, 1] = lo_x, hi_x, lo_k, hi_k
    for a in range(3):
        lo_x, lo_k, hi_x, hi_k = np.inf, 0, -np.inf, 0
        for c in range(n_chunks):
            x, k = coord[c, a, 0], key[c, a, 0]
            if x < lo_x or (x == lo_x and k < lo_k):
                lo_x, lo_k = x, k
            x, k = coord[c, a, 1], key[c, a, 1]
            if x > hi_x or (x == hi_x and k > hi_k):
                hi_x, hi_k = x, k
        out_coord[a, 0], out_coord[a, 1], out_key[a, 0], out_key[a, 1] = lo_x, hi_x, lo_k, hi_k


def slab_tree(coord: np.ndarray, key: np.ndarray, counts: np.ndarray, lo: np.ndarray,
              hi: np.ndarray) -> KdTree | None:
    """The tree that leaves every particle where it is, if the ranks already hold slabs:
    along some axis a, rank r's particles all come before rank r + 1's in (coordinate, key)
    order, and no rank holds more than SLAB_BALANCE times the mean. coord [ranks, 3, 2]
    float64 and key [ranks, 3, 2] int64: each rank's first and last (coordinate, key) per
    axis (_first_last); counts [ranks]. None when no axis qualifies."""
    ranks = len(counts)
    if counts.min() == 0 or counts.max() > SLAB_BALANCE * counts.mean():
        return None
    for a in range(3):
        last = list(zip(coord[:-1, a, 1], key[:-1, a, 1], strict=True))
        first = list(zip(coord[1:, a, 0], key[1:, a, 0], strict=True))
        if all(b > e for e, b in zip(last, first, strict=True)):
            break
    else:
        return None
    t = _TreeBuilder()

    def node(k: int, first: int, box_lo: np.ndarray, box_hi: np.ndarray) -> int:
        me = t.add(k, first, box_lo, box_hi)
        if k == 1:
            return me
        k_low = k // 2
        # the high side starts at rank first + k_low's first particle
        p, pk = float(coord[first + k_low, a, 0]), int(key[first + k_low, a, 0])
        split_hi, split_lo = t.split(me, a, p, pk, box_lo, box_hi)
        t.low[me] = node(k_low, first, box_lo, split_hi)
        t.high[me] = node(k - k_low, first + k_low, split_lo, box_hi)
        return me

    node(ranks, 0, np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    return t.tree(ranks)


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


def classify(positions: np.ndarray, keys: np.ndarray, tree: KdTree, dtype=np.int64
             ) -> np.ndarray:
    """The owner rank [n] (int64, or `dtype`) of each of positions [n, 3] (m) with keys [n]
    int64."""
    dest = np.empty(len(positions), dtype)
    _classify(as_positions(positions), keys, tree.axis, tree.plane, tree.pkey, tree.low,
              tree.high, tree.rank, dest)
    return dest


def global_rows(comm, n: int) -> np.ndarray:
    """Default keys: each particle's row in the concatenation of every rank's particles in
    rank order (rank 0's first), the order a one-process render would see them in."""
    from mpi4py import MPI

    offset = comm.exscan(n, op=MPI.SUM) if comm.size > 1 else 0
    return np.arange(n, dtype=np.int64) + (offset or 0)


class Pool:
    """Buffers an exchange reuses from step to step, by name: once grown, a step's result
    costs no page faults (a quarter more than asked is allocated, so slowly growing steps do
    not reallocate every time)."""

    def __init__(self):
        self.buffers: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple, dtype) -> np.ndarray:
        nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        buf = self.buffers.get(name)
        if buf is None or len(buf) < nbytes:
            self.buffers.pop(name, None)  # free the old one before allocating
            buf = self.buffers[name] = np.empty(max(nbytes + nbytes // 4, 64), np.uint8)
        return buf[:nbytes].view(dtype).reshape(shape)

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self.buffers.values())


def _word(*row_bytes: int) -> type:
    """The widest unsigned integer whose size divides every row's byte count."""
    for word in (np.uint64, np.uint32, np.uint16):
        if all(b % np.dtype(word).itemsize == 0 for b in row_bytes):
            return word
    return np.uint8


def _rows(array: np.ndarray, word) -> np.ndarray:
    """A C-contiguous array [n, ...] seen as words [n, row bytes / word size] (no copy when
    already contiguous)."""
    array = np.ascontiguousarray(array)
    width = int(np.prod(array.shape[1:], dtype=np.int64)) * array.dtype.itemsize
    return array.view(np.uint8).reshape(len(array), width).view(word)


@njit(parallel=True, cache=True, nogil=True)
def _chunk_counts(dest, counts):
    """counts[c, r]: particles of chunk c (of counts.shape[0] equal chunks) bound for rank r."""
    n_chunks, n = counts.shape[0], dest.shape[0]
    for c in prange(n_chunks):
        for p in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            counts[c, dest[p]] += 1


@njit(parallel=True, cache=True, nogil=True)
def _order(dest, offsets, order):
    """order[offsets[c, r] + i]: the i-th particle of chunk c bound for rank r (a stable
    counting sort by destination, chunks in parallel)."""
    n_chunks, n = offsets.shape[0], dest.shape[0]
    for c in prange(n_chunks):
        fill = offsets[c].copy()
        for p in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            order[fill[dest[p]]] = p
            fill[dest[p]] += 1


@njit(parallel=True, cache=True, nogil=True)
def _pack_rows(src, order, starts, counts, at, dst, col):
    """For every group g: dst[at[g] + i, col:col + k] = src[order[starts[g] + i]] for
    i < counts[g] (src [n, k] words)."""
    k = src.shape[1]
    for g in range(starts.shape[0]):
        for i in prange(counts[g]):
            p = order[starts[g] + i]
            for j in range(k):
                dst[at[g] + i, col + j] = src[p, j]


@njit(parallel=True, cache=True, nogil=True)
def _unpack_rows(src, col, starts, counts, at, dst):
    """For every group g: dst[at[g] + i] = src[starts[g] + i, col:col + k] for i <
    counts[g] (dst [m, k] words)."""
    k = dst.shape[1]
    for g in range(starts.shape[0]):
        for i in prange(counts[g]):
            for j in range(k):
                dst[at[g] + i, j] = src[starts[g] + i, col + j]


def alltoallv_rows(comm, send: np.ndarray, send_counts: np.ndarray, recv: np.ndarray,
                   recv_counts: np.ndarray) -> None:
    """Exchange rows of send [k, w] (grouped by destination rank, send_counts [ranks] rows
    each) into recv [sum(recv_counts), w], grouped by source rank. Counts are in rows of a
    contiguous MPI type, so no count overflows int32 below 2^31 rows."""
    from mpi4py import MPI

    row = MPI.BYTE.Create_contiguous(send.shape[1] * send.itemsize).Commit()
    try:
        comm.Alltoallv([send.view(np.uint8).reshape(-1),
                        (send_counts, np.cumsum(send_counts) - send_counts), row],
                       [recv.view(np.uint8).reshape(-1),
                        (recv_counts, np.cumsum(recv_counts) - recv_counts), row])
    finally:
        row.Free()


def agree_tree(comm, positions: np.ndarray, keys: np.ndarray, sample: int = SAMPLE
               ) -> tuple[KdTree, bool]:
    """The ranks' common k-d tree (collective), and whether it keeps every particle where it
    is. If the ranks already hold balanced slabs in
    rank order along an axis (slab_tree), the tree that keeps them; otherwise a sample of
    every rank's particles gathered on rank 0, split there (keeping particles where they
    are when an axis allows it: build_tree's sources), broadcast."""
    from mpi4py import MPI

    n = len(positions)
    counts = np.array(comm.allgather(n), np.int64)
    total = int(counts.sum())
    if total == 0:
        raise ValueError("no particles to repartition on any rank")
    coord, key = np.empty((3, 2)), np.zeros((3, 2), np.int64)
    _first_last(as_positions(positions), keys, coord, key)  # also the extent: coordinates
    lo, hi = coord[:, 0].copy(), coord[:, 1].copy()
    comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
    comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
    coords, firsts = np.empty((comm.size, 3, 2)), np.empty((comm.size, 3, 2), np.int64)
    comm.Allgather(coord, coords)
    comm.Allgather(key, firsts)
    slabs = slab_tree(coords, firsts, counts, lo, hi)  # the same answer on every rank
    if slabs is not None:
        return slabs, True
    stride = max(1, total // sample)
    mine = np.ascontiguousarray(positions[::stride], np.float64)
    mine_keys = np.ascontiguousarray(keys[::stride])
    sizes = np.array(comm.gather(len(mine), root=0) or [], np.int64)
    tree = None
    if comm.rank == 0:
        gathered = np.empty((int(sizes.sum()), 3))
        gathered_keys = np.empty(int(sizes.sum()), np.int64)
        displ = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        comm.Gatherv(mine, [gathered, (sizes * 3, displ * 3), MPI.DOUBLE], root=0)
        comm.Gatherv(mine_keys, [gathered_keys, (sizes, displ), MPI.INT64_T], root=0)
        sources = np.repeat(np.arange(comm.size, dtype=np.int64), sizes)
        tree = build_tree(gathered, gathered_keys, comm.size, lo, hi, sources)
    else:
        comm.Gatherv(mine, None, root=0)
        comm.Gatherv(mine_keys, None, root=0)
    return comm.bcast(tree, root=0), False


def _check(comm, positions: np.ndarray, fields: dict[str, np.ndarray],
           keys: np.ndarray | None) -> tuple[list[str], np.ndarray]:
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
    return names, keys


def exchange(comm, positions: np.ndarray, fields: dict[str, np.ndarray],
             keys: np.ndarray | None = None, sample: int = SAMPLE, pool: Pool | None = None
             ) -> Partition:
    """Move this rank's particles (positions [n, 3] m, fields [n] or [n, k]) to the ranks
    whose bricks hold them (collective: every rank calls it, with the same field names).
    keys [n] int64: distinct tie-break keys, default `global_rows`. The result holds the
    particles grouped by source rank, in input order within a source; the input arrays
    themselves when no particle leaves or reaches this rank, else arrays of `pool` (valid
    until the pool's next exchange) or new ones.

    The particles that leave go in rounds of at most ROUND_BYTES sent per rank: each round
    packs their rows (position, key, fields side by side) into one send buffer (numba) and
    moves them with one Alltoallv; those that stay are copied straight into the result."""
    from mpi4py import MPI

    t0 = time.perf_counter()
    n = len(positions)
    names, keys = _check(comm, positions, fields, keys)
    given = {k: fields[k] for k in names}
    if comm.size == 1:  # one brick: nothing to agree on or move
        lo, hi = extent(as_positions(positions)) if n else (np.zeros(3), np.zeros(3))
        none = np.array([-1], np.int64)
        tree = KdTree(np.array([LEAF], np.int64), np.zeros(1), np.zeros(1, np.int64), none,
                      none, np.zeros(1, np.int64), np.array([[lo, hi]], np.float64))
        return Partition(positions, given, keys, np.array([n]), tree,
                         time.perf_counter() - t0, 0.0)
    tree, in_place = agree_tree(comm, positions, keys, sample)
    t1 = time.perf_counter()
    if in_place:  # slabs kept: every particle is on its brick's rank already
        return Partition(positions, given, keys, np.array(comm.allgather(n), np.int64), tree,
                         t1 - t0, time.perf_counter() - t1)
    me, ranks = comm.rank, comm.size
    rank_type = np.int16 if ranks <= np.iinfo(np.int16).max else np.int32
    dest = classify(positions, keys, tree, rank_type)  # 2 bytes a row
    chunk_counts = np.zeros((min(CHUNKS, max(n, 1)), ranks), np.int64)
    _chunk_counts(dest, chunk_counts)
    send_counts = chunk_counts.sum(axis=0)
    recv_counts = np.empty(ranks, np.int64)
    comm.Alltoall([send_counts, MPI.INT64_T], [recv_counts, MPI.INT64_T])
    counts = np.array(comm.allgather(int(recv_counts.sum())), np.int64)
    kept = int(send_counts[me])
    leaving = send_counts.copy()
    leaving[me] = 0
    most = comm.allreduce(int(leaving.max()), op=MPI.MAX)  # the longest send to one rank
    if most == 0:  # nothing moves anywhere
        return Partition(positions, given, keys, counts, tree, t1 - t0, time.perf_counter() - t1)
    # order: the particles leaving, grouped by destination, then (from n - kept) those staying
    group = np.cumsum(leaving) - leaving
    group[me] = n - kept
    order = np.empty(n, np.int32 if n <= np.iinfo(np.int32).max else np.int64)  # 4 bytes a row
    _order(dest, group[None, :] + np.cumsum(chunk_counts, axis=0) - chunk_counts, order)
    del dest
    arrays = [positions, keys] + [given[k] for k in names]
    word = _word(*(_rows(a[:0], np.uint8).shape[1] for a in arrays))
    src = [_rows(a, word) for a in arrays]
    widths = [r.shape[1] for r in src]
    cols = np.cumsum([0] + widths)
    row_words = int(cols[-1])
    arriving = recv_counts.copy()
    arriving[me] = 0
    untouched = kept == n and arriving.sum() == 0  # others exchange, this rank keeps its own
    m = kept + int(arriving.sum())

    def new(i: int, shape: tuple, dtype) -> np.ndarray:
        return np.empty(shape, dtype) if pool is None else pool.get(f"out{i}", shape, dtype)

    out = arrays if untouched else [new(i, (m, *a.shape[1:]), a.dtype)
                                    for i, a in enumerate(arrays)]
    at = np.cumsum(recv_counts) - recv_counts  # result rows by source rank, this one's own
    one = np.ones(1, np.int64)
    if not untouched:
        for a, o in zip(src, out, strict=True):
            _pack_rows(a, order, np.array([n - kept]), kept * one, at[me] * one, _rows(o, word),
                       0)
    # rounds: at most `per` rows to each rank, so send and receive stay within ROUND_BYTES
    per = max(1, ROUND_BYTES // (row_words * np.dtype(word).itemsize * (ranks - 1)))
    rounds = -(-most // per)
    send_buf = np.empty(int(np.minimum(leaving, per).sum()) * row_words, word)
    recv_buf = np.empty(int(np.minimum(arriving, per).sum()) * row_words, word)
    for r in range(rounds):
        send_n = np.clip(leaving - r * per, 0, per)
        recv_n = np.clip(arriving - r * per, 0, per)
        send = send_buf[:int(send_n.sum()) * row_words].reshape(-1, row_words)
        recv = recv_buf[:int(recv_n.sum()) * row_words].reshape(-1, row_words)
        for a, col in zip(src, cols, strict=False):
            _pack_rows(a, order, group + r * per, send_n, np.cumsum(send_n) - send_n, send,
                       col)
        alltoallv_rows(comm, send, send_n, recv, recv_n)
        for o, col in zip([] if untouched else out, cols, strict=False):
            _unpack_rows(recv, col, np.cumsum(recv_n) - recv_n, recv_n, at + r * per,
                         _rows(o, word))
    del send_buf, recv_buf  # freed before rendering: not part of its peak
    return Partition(out[0], dict(zip(names, out[2:], strict=True)), out[1], counts, tree,
                     t1 - t0, time.perf_counter() - t1)
