"""Ray casting of spheres through the bricks' uniform grids (numba, rays in parallel): the
shadow rays of the renderer (primary visibility is cast in object order, `cast`), and a
brute-force reference for tests.

A ray visits the bricks it crosses front to back (k-d bricks are disjoint, so the order of
entry distances is a valid order) and, inside each, the cells it crosses (3D DDA,
Amanatides & Woo 1987). It stops at the first cell, or brick, whose exit distance is past
the nearest hit so far: every sphere is referenced by each cell its bounding box touches,
so a closer hit would have been found in a cell already visited.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from minority.render_server.accel import BrickGrids
from minority.render_server.bricks import MAX_BRICKS, Bricks, as_positions

RAYS_PER_TASK = 256  # rays per parallel work item (scratch arrays are per item)
NO_HIT = -1


@njit(cache=True, inline="always")
def _ray_box(o, d, lo, hi):
    """Entry and exit distances of a ray into an axis-aligned box (t1 < t0: missed)."""
    t0, t1 = 0.0, math.inf
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
        else:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    return t0, t1


@njit(cache=True, inline="always")
def _hit_sphere(o, d, cx, cy, cz, r2, t_min):
    """Distance to the first intersection at or beyond t_min of a unit-direction ray with a
    sphere (center cx, cy, cz; squared radius r2), or inf."""
    ox, oy, oz = o[0] - cx, o[1] - cy, o[2] - cz
    b = ox * d[0] + oy * d[1] + oz * d[2]
    disc = b * b - (ox * ox + oy * oy + oz * oz - r2)
    if disc < 0.0:
        return math.inf
    s = math.sqrt(disc)
    t = -b - s
    if t < t_min:
        t = -b + s
    return t if t >= t_min else math.inf


@njit(cache=True, inline="always")
def _dda_axis(o, d, t_enter, lo, h, n):
    """Start cell, step, distance to the next cell boundary and per-cell distance along one
    axis of a DDA walk through n cells of size h from lo."""
    c = min(max(int(math.floor((o + d * t_enter - lo) / h)), 0), n - 1)
    if d > 0.0:
        return c, 1, (lo + (c + 1) * h - o) / d, h / d
    if d < 0.0:
        return c, -1, (lo + c * h - o) / d, -h / d
    return c, 0, math.inf, math.inf


@njit(cache=True, nogil=True)
def _trace_brick(o, d, b, t_enter, t_exit, t_min, best_t, best_id, positions, r2, boxes,
                 dims, cell_size, cell_offset, cell_start, ref_offset, items):
    """Closest hit inside brick b between t_enter and t_exit; returns (best_t, best_id)."""
    nx, ny, nz = dims[b, 0], dims[b, 1], dims[b, 2]
    base = cell_offset[b] + b
    refs = ref_offset[b]
    cx, sx, tx, dtx = _dda_axis(o[0], d[0], t_enter, boxes[b, 0, 0], cell_size[b, 0], nx)
    cy, sy, ty, dty = _dda_axis(o[1], d[1], t_enter, boxes[b, 0, 1], cell_size[b, 1], ny)
    cz, sz, tz, dtz = _dda_axis(o[2], d[2], t_enter, boxes[b, 0, 2], cell_size[b, 2], nz)
    while True:
        c = base + (cx * ny + cy) * nz + cz
        for k in range(cell_start[c], cell_start[c + 1]):
            p = items[refs + k]
            t = _hit_sphere(o, d, positions[p, 0], positions[p, 1], positions[p, 2], r2, t_min)
            if t < best_t or (t == best_t and p < best_id):
                best_t, best_id = t, p
        t_cell_exit = min(tx, ty, tz, t_exit)
        if best_t <= t_cell_exit or t_cell_exit >= t_exit:
            return best_t, best_id
        if tx <= ty and tx <= tz:
            cx += sx
            tx += dtx
            if cx < 0 or cx >= nx:
                return best_t, best_id
        elif ty <= tz:
            cy += sy
            ty += dty
            if cy < 0 or cy >= ny:
                return best_t, best_id
        else:
            cz += sz
            tz += dtz
            if cz < 0 or cz >= nz:
                return best_t, best_id


@njit(cache=True, nogil=True)
def _closest(o, d, t_min, positions, r2, boxes, dims, cell_size, cell_offset, cell_start,
             ref_offset, items, t_in, t_out, order):
    nb = boxes.shape[0]
    m = 0
    for b in range(nb):
        t0, t1 = _ray_box(o, d, boxes[b, 0], boxes[b, 1])
        if t1 >= t0 and t1 >= t_min:
            # insertion sort by entry distance
            j = m
            while j > 0 and t_in[order[j - 1]] > t0:
                order[j] = order[j - 1]
                j -= 1
            t_in[b], t_out[b] = max(t0, t_min), t1
            order[j] = b
            m += 1
    best_t, best_id = math.inf, NO_HIT
    for i in range(m):
        b = order[i]
        best_t, best_id = _trace_brick(o, d, b, t_in[b], t_out[b], t_min, best_t, best_id,
                                       positions, r2, boxes, dims, cell_size, cell_offset,
                                       cell_start, ref_offset, items)
        if best_t <= t_out[b]:
            break
    return best_t, best_id


@njit(parallel=True, cache=True, nogil=True)
def _trace_all(origins, dirs, positions, r2, boxes, dims, cell_size, cell_offset, cell_start,
               ref_offset, items, hit_t, hit_id):
    nrays = origins.shape[0]
    ntasks = (nrays + RAYS_PER_TASK - 1) // RAYS_PER_TASK
    for task in prange(ntasks):
        t_in = np.empty(MAX_BRICKS)
        t_out = np.empty(MAX_BRICKS)
        order = np.empty(MAX_BRICKS, np.int64)
        for r in range(task * RAYS_PER_TASK, min(nrays, (task + 1) * RAYS_PER_TASK)):
            hit_t[r], hit_id[r] = _closest(origins[r], dirs[r], 0.0, positions, r2, boxes, dims,
                                           cell_size, cell_offset, cell_start, ref_offset,
                                           items, t_in, t_out, order)


def trace(origins: np.ndarray, dirs: np.ndarray, positions: np.ndarray, radius: float,
          bricks: Bricks, grids: BrickGrids) -> tuple[np.ndarray, np.ndarray]:
    """Closest sphere hit per ray: distances [r] (m, inf if none) and particle ids [r] (-1)."""
    hit_t = np.empty(len(origins))
    hit_id = np.empty(len(origins), np.int64)
    _trace_all(np.ascontiguousarray(origins, np.float64), np.ascontiguousarray(dirs, np.float64),
               as_positions(positions), radius * radius, bricks.boxes,
               grids.dims, grids.cell_size, grids.cell_offset, grids.cell_start,
               grids.ref_offset, grids.items, hit_t, hit_id)
    return hit_t, hit_id


def trace_brute_force(origins: np.ndarray, dirs: np.ndarray, positions: np.ndarray,
                      radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference: every ray against every sphere (NumPy; small scenes only)."""
    oc = origins[:, None, :] - positions[None, :, :].astype(np.float64)  # [r, n, 3]
    b = np.einsum("rnk,rk->rn", oc, dirs)
    disc = b * b - (np.einsum("rnk,rnk->rn", oc, oc) - radius * radius)
    s = np.sqrt(np.where(disc >= 0, disc, np.nan))
    t = -b - s
    t = np.where(t >= 0, t, -b + s)
    t = np.where((disc >= 0) & (t >= 0), t, np.inf)
    hit_id = np.argmin(t, axis=1)  # ties: lowest index, as the fast path
    hit_t = t[np.arange(len(t)), hit_id]
    return hit_t, np.where(np.isfinite(hit_t), hit_id, NO_HIT)
