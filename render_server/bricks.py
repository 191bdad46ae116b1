"""Repartition a step's particles into spatially disjoint bricks balanced by count.

k-d splits at the median along the longest axis of each node's particles, to a power-of-two
number of bricks. A particle belongs to the brick that holds its center; a sphere that
crosses a brick face is also referenced (as a ghost) by every other brick its bounding box
touches, so no brick cuts a sphere off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

MAX_BRICKS = 64


@dataclass
class Bricks:
    boxes: np.ndarray  # [b, 2, 3] float64, m: lo and hi corner of each brick (disjoint)
    start: np.ndarray  # [b + 1] int64: members of brick k are members[start[k]:start[k+1]]
    members: np.ndarray  # [m] int64 particle indices, owned ones first then ghosts
    owned: np.ndarray  # [b] int64: how many of each brick's members have their center in it

    @property
    def count(self) -> int:
        return len(self.boxes)


def kd_split(positions: np.ndarray, radius: float, levels: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order particles by brick: returns order [n] int64, boxes [2**levels, 2, 3] (m) and
    bounds [2**levels + 1]: brick k holds order[bounds[k]:bounds[k+1]] (balanced halves)."""
    n = len(positions)
    lo = positions.min(axis=0).astype(np.float64) - radius
    hi = positions.max(axis=0).astype(np.float64) + radius
    order = np.arange(n, dtype=np.int64)
    nodes = [(0, n, lo, hi)]
    for _ in range(levels):
        children = []
        for s, e, blo, bhi in nodes:
            pts = positions[order[s:e]]
            span = (pts.max(axis=0) - pts.min(axis=0)) if e > s else (bhi - blo)
            axis = int(np.argmax(span))
            k = (e - s) // 2
            if e - s > 1:
                part = np.argpartition(pts[:, axis], k)
                order[s:e] = order[s:e][part]
                plane = float(positions[order[s + k], axis])
            else:
                plane = float(0.5 * (blo[axis] + bhi[axis]))
            plane = min(max(plane, blo[axis]), bhi[axis])
            left_hi, right_lo = bhi.copy(), blo.copy()
            left_hi[axis] = right_lo[axis] = plane
            children += [(s, s + k, blo, left_hi), (s + k, e, right_lo, bhi)]
        nodes = children
    boxes = np.array([[b[2], b[3]] for b in nodes], dtype=np.float64)
    return order, boxes, np.array([b[0] for b in nodes] + [n], dtype=np.int64)


@njit(cache=True)
def _ghosts(positions, radius, order, bounds, boxes, count_only, start, out):
    """Count (count_only) or write the ghost references of every brick."""
    nb = boxes.shape[0]
    fill = start.copy() if not count_only else np.zeros(nb + 1, np.int64)
    for b in range(nb):
        for i in range(bounds[b], bounds[b + 1]):
            p = order[i]
            inside = True
            for a in range(3):
                if positions[p, a] - radius < boxes[b, 0, a] or positions[p, a] + radius > boxes[b, 1, a]:
                    inside = False
            if inside:
                continue
            for c in range(nb):
                if c == b:
                    continue
                touches = True
                for a in range(3):
                    if positions[p, a] + radius < boxes[c, 0, a] or positions[p, a] - radius > boxes[c, 1, a]:
                        touches = False
                if touches:
                    if count_only:
                        fill[c + 1] += 1
                    else:
                        out[fill[c]] = p
                        fill[c] += 1
    return fill


def repartition(positions: np.ndarray, radius: float, n_bricks: int) -> Bricks:
    """Bricks of `positions` [n, 3] (m) for spheres of `radius` (m); n_bricks a power of 2."""
    if n_bricks < 1 or n_bricks > MAX_BRICKS or n_bricks & (n_bricks - 1):
        raise ValueError(f"n_bricks must be a power of two in [1, {MAX_BRICKS}], got {n_bricks}")
    if len(positions) == 0:
        raise ValueError("no particles to repartition")
    levels = n_bricks.bit_length() - 1
    order, boxes, bounds = kd_split(positions, radius, levels)
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    ghost_count = _ghosts(pos, radius, order, bounds, boxes, True, bounds, order)
    owned = np.diff(bounds)
    sizes = owned + ghost_count[1:]
    start = np.zeros(n_bricks + 1, np.int64)
    np.cumsum(sizes, out=start[1:])
    members = np.empty(start[-1], np.int64)
    for b in range(n_bricks):
        members[start[b]:start[b] + owned[b]] = order[bounds[b]:bounds[b + 1]]
    ghost_start = start[:-1] + owned
    _ghosts(pos, radius, order, bounds, boxes, False, np.r_[ghost_start, 0], members)
    return Bricks(boxes, start, members, owned)
