"""Per-brick acceleration structure: a uniform grid of sphere references, built by a
counting sort (linear in the references), bricks in parallel.

Every sphere is referenced by each cell its bounding box overlaps (clipped to the brick).
Cells are at least one sphere diameter wide, so a sphere touches at most 8 cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from minority.render_server.bricks import Bricks, as_positions

SPHERES_PER_CELL = 2.0  # target mean references per cell
MAX_CELLS_PER_AXIS = 1024


@dataclass
class BrickGrids:
    dims: np.ndarray  # [b, 3] int64 cells per axis
    cell_size: np.ndarray  # [b, 3] float64, m
    cell_offset: np.ndarray  # [b + 1] int64: brick k's cells are cell_start[off[k]:off[k+1]+1]
    cell_start: np.ndarray  # [total cells + bricks] int64 prefix sums per brick (one extra each)
    ref_offset: np.ndarray  # [b + 1] int64: brick k's references are items[ref_offset[k]:...]
    items: np.ndarray  # [refs] int64 particle indices, grouped by cell


def grid_dims(boxes: np.ndarray, counts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Cells per axis and cell size per brick for about SPHERES_PER_CELL spheres a cell."""
    extent = np.maximum(boxes[:, 1] - boxes[:, 0], 1e-12)  # [b, 3]
    volume = extent.prod(axis=1)
    target = np.maximum(counts / SPHERES_PER_CELL, 1.0)
    h = np.maximum(np.cbrt(volume / target), 2.0 * radius)  # cell edge, m
    dims = np.clip(np.ceil(extent / h[:, None]), 1, MAX_CELLS_PER_AXIS).astype(np.int64)
    return dims, extent / dims


@njit(cache=True, inline="always")
def _cell_range(x, r, lo, h, n):
    c0 = int(np.floor((x - r - lo) / h))
    c1 = int(np.floor((x + r - lo) / h))
    return max(c0, 0), min(c1, n - 1)


@njit(parallel=True, cache=True, nogil=True)
def _build(positions, radius, boxes, start, members, dims, cell_size, cell_offset,
           cell_start, ref_offset, items, count_only):
    for b in prange(boxes.shape[0]):
        nx, ny, nz = dims[b, 0], dims[b, 1], dims[b, 2]
        base = cell_offset[b] + b  # each brick's prefix array has one extra slot
        counts = cell_start[base:base + nx * ny * nz + 1]
        if count_only:
            counts[:] = 0
        else:
            fill = counts[:-1].copy()
        for i in range(start[b], start[b + 1]):
            p = members[i]
            x0, x1 = _cell_range(positions[p, 0], radius, boxes[b, 0, 0], cell_size[b, 0], nx)
            y0, y1 = _cell_range(positions[p, 1], radius, boxes[b, 0, 1], cell_size[b, 1], ny)
            z0, z1 = _cell_range(positions[p, 2], radius, boxes[b, 0, 2], cell_size[b, 2], nz)
            for cx in range(x0, x1 + 1):
                for cy in range(y0, y1 + 1):
                    for cz in range(z0, z1 + 1):
                        c = (cx * ny + cy) * nz + cz
                        if count_only:
                            counts[c + 1] += 1
                        else:
                            items[ref_offset[b] + fill[c]] = p
                            fill[c] += 1
        if count_only:
            for c in range(nx * ny * nz):
                counts[c + 1] += counts[c]


def build_grids(positions: np.ndarray, radius: float, bricks: Bricks) -> BrickGrids:
    """Uniform grids of every brick of `bricks` (positions [n, 3] m, sphere radius m)."""
    pos = as_positions(positions)
    dims, cell_size = grid_dims(bricks.boxes, np.diff(bricks.start), radius)
    ncells = dims.prod(axis=1)
    cell_offset = np.zeros(bricks.count + 1, np.int64)
    np.cumsum(ncells, out=cell_offset[1:])
    cell_start = np.zeros(cell_offset[-1] + bricks.count, np.int64)
    ref_offset = np.zeros(bricks.count + 1, np.int64)
    _build(pos, radius, bricks.boxes, bricks.start, bricks.members, dims, cell_size,
           cell_offset, cell_start, ref_offset, np.empty(0, np.int64), True)
    last = cell_offset[1:] + np.arange(1, bricks.count + 1)  # index of each brick's total
    np.cumsum(cell_start[last - 1], out=ref_offset[1:])
    items = np.empty(ref_offset[-1], np.int64)
    _build(pos, radius, bricks.boxes, bricks.start, bricks.members, dims, cell_size,
           cell_offset, cell_start, ref_offset, items, False)
    return BrickGrids(dims, cell_size, cell_offset, cell_start, ref_offset, items)
