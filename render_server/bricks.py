"""Repartition a step's particles into spatially disjoint bricks balanced by count.

k-d splits at the median along the longest axis of each node's particles, to a power-of-two
number of bricks. The split planes are the exact medians of an evenly strided sample of at
most SAMPLE particles (all of them when there are fewer), and every particle is then
classified by the planes in parallel: linear time, balanced to within the sampling error
(about 1% per brick at 8 bricks). A particle belongs to the brick that holds its center; a sphere that
crosses a brick face is also referenced (as a ghost) by every other brick its bounding box
touches, so no brick cuts a sphere off.

The split planes and boxes come from the sample alone; the per-particle part (classifying
every particle, the member lists and ghosts: 8 bytes a member and a transient 16 bytes a
particle) is done on first use of the members, which only shadow rays and their grids
need: primary rays (render_server.cast) take the bricks' boxes only.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from numba import njit, prange

MAX_BRICKS = 64
SAMPLE = 1 << 16  # particles that choose the split planes


def as_positions(positions: np.ndarray) -> np.ndarray:
    """Positions [n, 3] as a C-contiguous float32 or float64 array, copied only if needed
    (chunks carry float32; kernels compute in float64 either way)."""
    if positions.dtype in (np.float32, np.float64):
        return np.ascontiguousarray(positions)
    return np.ascontiguousarray(positions, dtype=np.float64)


@njit(parallel=True, cache=True, nogil=True)
def _extent(positions, parts):
    """Per-part partial minima and maxima of positions [n, 3] (parts [k, 2, 3], k chunks)."""
    k = parts.shape[0]
    n = positions.shape[0]
    for c in prange(k):
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for p in range(c * n // k, (c + 1) * n // k):
            for a in range(3):
                x = positions[p, a]
                lo[a] = min(lo[a], x)
                hi[a] = max(hi[a], x)
        parts[c, 0], parts[c, 1] = lo, hi


def extent(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner [3] of positions [n, 3] (numpy's axis-0 min/max of an [n, 3]
    array is an order of magnitude slower)."""
    parts = np.empty((64, 2, 3))
    _extent(positions, parts)
    return parts[:, 0].min(axis=0), parts[:, 1].max(axis=0)


class Bricks:
    """A power-of-two number of k-d bricks of some positions: boxes, and (classified on first
    use of `start`, `members` or `owned`) each brick's members."""

    def __init__(self, boxes: np.ndarray, positions: np.ndarray, radius: float,
                 axes: np.ndarray, planes: np.ndarray):
        self.boxes = boxes  # [b, 2, 3] float64, m: lo and hi corner of each brick (disjoint)
        self._split = (positions, radius, axes, planes)

    @property
    def count(self) -> int:
        return len(self.boxes)

    @property
    def start(self) -> np.ndarray:
        """[b + 1] int64: members of brick k are members[start[k]:start[k+1]]."""
        return self._members[0]

    @property
    def members(self) -> np.ndarray:
        """[m] int64 particle indices, owned ones first then ghosts."""
        return self._members[1]

    @property
    def owned(self) -> np.ndarray:
        """[b] int64: how many of each brick's members have their center in it."""
        return self._members[2]

    @cached_property
    def _members(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos, radius, axes, planes = self._split
        n_bricks = self.count
        order, bounds = _order_by_leaf(pos, axes, planes, n_bricks)
        boxes = self.boxes
        counts = np.zeros((n_bricks, n_bricks), np.int64)  # [owner, receiver]
        _ghost_counts(pos, radius, order, bounds, boxes, counts)
        owned = np.diff(bounds)
        sizes = owned + counts.sum(axis=0)
        start = np.zeros(n_bricks + 1, np.int64)
        np.cumsum(sizes, out=start[1:])
        members = np.empty(start[-1], np.int64)
        for b in range(n_bricks):
            members[start[b]:start[b] + owned[b]] = order[bounds[b]:bounds[b + 1]]
        # ghosts of receiver c after its owned members, grouped by owner b
        offsets = (start[:-1] + owned)[None, :] + np.cumsum(counts, axis=0) - counts
        _ghost_fill(pos, radius, order, bounds, boxes, offsets, members)
        return start, members, owned


@njit(cache=True, nogil=True)
def _select(order, s, e, k, positions, axis):
    """Reorder order[s:e] so that order[k] holds the particle of rank k - s along `axis`,
    with smaller-or-equal coordinates before it and larger-or-equal after (quickselect,
    linear expected time, median-of-three pivots)."""
    lo, hi = s, e - 1
    while hi > lo:
        mid = (lo + hi) // 2
        a, b, c = positions[order[lo], axis], positions[order[mid], axis], positions[order[hi], axis]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = lo, hi
        while i <= j:
            while positions[order[i], axis] < pivot:
                i += 1
            while positions[order[j], axis] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@njit(cache=True, nogil=True)
def _kd_level(positions, order, starts, boxes, new_starts, new_boxes, axes, planes):
    """Split every node of one level at its median along its particles' longest axis;
    records each node's axis and plane."""
    for node in range(starts.shape[0] - 1):
        s, e = starts[node], starts[node + 1]
        k = s + (e - s) // 2
        axis, best = 0, -1.0
        for a in range(3):
            lo, hi = np.inf, -np.inf
            for i in range(s, e):
                x = positions[order[i], a]
                lo, hi = min(lo, x), max(hi, x)
            span = hi - lo if e > s else boxes[node, 1, a] - boxes[node, 0, a]
            if span > best:
                axis, best = a, span
        if e - s > 1:
            _select(order, s, e, k, positions, axis)
            plane = positions[order[k], axis]
        else:
            plane = 0.5 * (boxes[node, 0, axis] + boxes[node, 1, axis])
        plane = min(max(plane, boxes[node, 0, axis]), boxes[node, 1, axis])
        axes[node], planes[node] = axis, plane
        new_starts[2 * node], new_starts[2 * node + 1] = s, k
        new_boxes[2 * node] = boxes[node]
        new_boxes[2 * node + 1] = boxes[node]
        new_boxes[2 * node, 1, axis] = plane
        new_boxes[2 * node + 1, 0, axis] = plane
    new_starts[-1] = starts[-1]


@njit(parallel=True, cache=True, nogil=True)
def _classify(positions, axes, planes, levels, leaf):
    """Leaf (brick) index of every particle: descend the planes; below a plane goes left,
    on or above it right (as the median element itself in the split)."""
    for p in prange(positions.shape[0]):
        node = 0
        for _ in range(levels):
            node = 2 * node + (1 if positions[p, axes[node]] < planes[node] else 2)
        leaf[p] = node - ((1 << levels) - 1)


@njit(cache=True, nogil=True)
def _sort_by_leaf(leaf, n_leaves, order, bounds):
    bounds[:] = 0
    for p in range(leaf.shape[0]):
        bounds[leaf[p] + 1] += 1
    for b in range(n_leaves):
        bounds[b + 1] += bounds[b]
    fill = bounds[:n_leaves].copy()
    for p in range(leaf.shape[0]):
        order[fill[leaf[p]]] = p
        fill[leaf[p]] += 1


def _planes(positions: np.ndarray, radius: float, levels: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The k-d split of positions [n, 3] (m) into 2**levels bricks, from the sample: boxes
    [2**levels, 2, 3] (m; grown by `radius` at the outer faces), axes and planes [nodes]
    (heap order: children 2i+1, 2i+2)."""
    n = len(positions)
    sample = positions[::max(1, n // SAMPLE)]
    sample_order = np.arange(len(sample), dtype=np.int64)
    starts = np.array([0, len(sample)], dtype=np.int64)
    lo, hi = extent(positions)
    boxes = np.array([[lo - radius, hi + radius]], dtype=np.float64)
    axes = np.zeros(max(1, (1 << levels) - 1), np.int64)
    planes = np.zeros(len(axes))
    for level in range(levels):
        first = (1 << level) - 1
        new_starts = np.empty(2 * (len(starts) - 1) + 1, np.int64)
        new_boxes = np.empty((2 * len(boxes), 2, 3))
        _kd_level(sample, sample_order, starts, boxes, new_starts, new_boxes,
                  axes[first:first + len(boxes)], planes[first:first + len(boxes)])
        starts, boxes = new_starts, new_boxes
    return boxes, axes, planes


def _order_by_leaf(positions: np.ndarray, axes: np.ndarray, planes: np.ndarray, n_leaves: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Every particle's brick by the planes: order [n] int64 and bounds [n_leaves + 1], brick
    k holds order[bounds[k]:bounds[k+1]]."""
    n = len(positions)
    leaf = np.empty(n, np.int64)
    _classify(positions, axes, planes, n_leaves.bit_length() - 1, leaf)
    order, bounds = np.empty(n, np.int64), np.empty(n_leaves + 1, np.int64)
    _sort_by_leaf(leaf, n_leaves, order, bounds)
    return order, bounds


def kd_split(positions: np.ndarray, radius: float, levels: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order particles by brick: returns order [n] int64, boxes [2**levels, 2, 3] (m) and
    bounds [2**levels + 1]: brick k holds order[bounds[k]:bounds[k+1]].

    positions: [n, 3] float32 or float64, m."""
    boxes, axes, planes = _planes(positions, radius, levels)
    order, bounds = _order_by_leaf(positions, axes, planes, len(boxes))
    return order, boxes, bounds


@njit(cache=True, nogil=True, inline="always")
def _crosses(positions, p, radius, boxes, b):
    """Whether sphere p's bounding box leaves box b."""
    for a in range(3):
        if positions[p, a] - radius < boxes[b, 0, a] or positions[p, a] + radius > boxes[b, 1, a]:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _touches(positions, p, radius, boxes, c):
    """Whether sphere p's bounding box overlaps box c."""
    for a in range(3):
        if positions[p, a] + radius < boxes[c, 0, a] or positions[p, a] - radius > boxes[c, 1, a]:
            return False
    return True


@njit(parallel=True, cache=True, nogil=True)
def _ghost_counts(positions, radius, order, bounds, boxes, counts):
    """counts[b, c]: spheres owned by brick b that also touch brick c (c != b)."""
    nb = boxes.shape[0]
    for b in prange(nb):
        for i in range(bounds[b], bounds[b + 1]):
            p = order[i]
            if _crosses(positions, p, radius, boxes, b):
                for c in range(nb):
                    if c != b and _touches(positions, p, radius, boxes, c):
                        counts[b, c] += 1


@njit(parallel=True, cache=True, nogil=True)
def _ghost_fill(positions, radius, order, bounds, boxes, offsets, out):
    """Write the ghosts: brick b's ghosts in brick c go to out[offsets[b, c]:...]."""
    nb = boxes.shape[0]
    for b in prange(nb):
        fill = offsets[b].copy()
        for i in range(bounds[b], bounds[b + 1]):
            p = order[i]
            if _crosses(positions, p, radius, boxes, b):
                for c in range(nb):
                    if c != b and _touches(positions, p, radius, boxes, c):
                        out[fill[c]] = p
                        fill[c] += 1


def repartition(positions: np.ndarray, radius: float, n_bricks: int) -> Bricks:
    """Bricks of `positions` [n, 3] (m) for spheres of `radius` (m); n_bricks a power of 2.
    The members are classified when first asked for (Bricks.members)."""
    if n_bricks < 1 or n_bricks > MAX_BRICKS or n_bricks & (n_bricks - 1):
        raise ValueError(f"n_bricks must be a power of two in [1, {MAX_BRICKS}], got {n_bricks}")
    if len(positions) == 0:
        raise ValueError("no particles to repartition")
    pos = as_positions(positions)
    boxes, axes, planes = _planes(pos, radius, n_bricks.bit_length() - 1)
    return Bricks(boxes, pos, radius, axes, planes)
