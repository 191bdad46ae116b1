"""Primary visibility by exact ray casting in object order.

Each sphere's screen footprint is bounded exactly (tangent lines of the perspective
projection, or its extent in parallel projection) plus a rounding margin; within it, the ray
of every pixel center is intersected with the sphere exactly and the nearest hit wins
(ties: lowest particle index, as in the brute-force reference, or lowest key when the caller
gives each particle a key: a distributed render passes the particles' global rows, so every
rank breaks ties as the one-process render of all of them does). Spheres are binned into
image row bands by a counting sort; bands are disjoint, so threads never write the same
pixel. Work is linear in the particle count and in the footprint area, not in pixels times
traversal depth. Rays are the ones of `camera.primary_rays`, computed by the same code.

Memory: 13 bytes per sphere (its footprint, depth bucket and nearest depth) and the binned
references (28 bytes each with float32 positions), built for a group of consecutive bands
at a time so that at most RECORD_BYTES of them exist at once: a pixel's hit depends only on
the references of its own band, so the groups' order changes nothing.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from minority.render_server.bricks import as_positions, extent
from minority.render_server.camera import RayFrame, pixel_ray_unnormalized

BANDS_PER_WORKER = 8  # fewer, taller bands: fewer spheres listed twice (A/B: 1M -15%)
DEPTH_BUCKETS = 256  # depth ordering resolution (front-to-back culling only; not correctness)
CHUNKS_PER_WORKER = 4  # particle chunks per thread in the binning passes
MARGIN_NDC = 1e-6  # footprint margin against rounding at the tangent bound (NDC units)
NO_KEYS = np.empty(0, np.int64)  # ties by particle index
RECORD_BYTES = 64 << 20  # most bytes of binned records held at once (bands cast in groups)


@njit(cache=True, nogil=True, inline="always")
def _footprint(positions, p, r, f, width, height):
    """Pixel column/row ranges (i0, i1, j0, j1) that can see sphere p (empty: i0 > i1) and
    its nearest camera depth zmin (m along the view direction)."""
    rx = positions[p, 0] - f.position[0]
    ry = positions[p, 1] - f.position[1]
    rz = positions[p, 2] - f.position[2]
    xc = rx * f.right[0] + ry * f.right[1] + rz * f.right[2]
    yc = rx * f.up[0] + ry * f.up[1] + rz * f.up[2]
    zc = rx * f.forward[0] + ry * f.forward[1] + rz * f.forward[2]
    if f.perspective:
        if zc + r <= 0.0:  # wholly behind the camera
            return 1, 0, 1, 0, zc - r
        if zc <= r * 1.000001:  # crosses the camera plane: any pixel may see it
            return 0, width - 1, 0, height - 1, zc - r
        den = zc * zc - r * r
        sx = r * math.sqrt(xc * xc + den)
        sy = r * math.sqrt(yc * yc + den)
        gx_lo = (xc * zc - sx) / den / f.half_width
        gx_hi = (xc * zc + sx) / den / f.half_width
        gy_lo = (yc * zc - sy) / den / f.half_height
        gy_hi = (yc * zc + sy) / den / f.half_height
    else:
        gx_lo, gx_hi = (xc - r) / f.half_width, (xc + r) / f.half_width
        gy_lo, gy_hi = (yc - r) / f.half_height, (yc + r) / f.half_height
    a = math.ceil((gx_lo - MARGIN_NDC + 1.0) * 0.5 * width - 0.5)
    b = math.floor((gx_hi + MARGIN_NDC + 1.0) * 0.5 * width - 0.5)
    c = math.ceil((1.0 - gy_hi - MARGIN_NDC) * 0.5 * height - 0.5)
    d = math.floor((1.0 - gy_lo + MARGIN_NDC) * 0.5 * height - 0.5)
    # clamped into [-1, size], so far-off footprints fit int32 and stay empty
    return (min(max(a, 0), width), max(min(b, width - 1), -1),
            min(max(c, 0), height), max(min(d, height - 1), -1), zc - r)


@njit(cache=True, nogil=True, inline="always")
def _bucket(z, zlo, zscale):
    return min(max(int((z - zlo) * zscale), 0), DEPTH_BUCKETS - 1)


@njit(cache=True, nogil=True, inline="always")
def _down32(z):
    """z as float32, rounded toward -inf (a nearest depth may only move nearer: culling
    against it stays conservative)."""
    z32 = np.float32(z)
    if z32 > z:
        z32 = np.nextafter(z32, np.float32(-np.inf))
    return z32


@njit(parallel=True, cache=True, nogil=True)
def _footprints(positions, r, f, width, height, zlo, zscale, band_rows, box, bucket, zmin,
                counts):
    """Footprint box [n, 4] (i0, i1, j0, j1; empty: i0 > i1), depth bucket [n] and nearest
    depth zmin [n] (float32, rounded down) of every sphere, and counts[c, band *
    DEPTH_BUCKETS + depth bucket] of the references of particle chunk c (one pass, chunks in
    parallel)."""
    n_chunks, n = counts.shape[0], positions.shape[0]
    for c in prange(n_chunks):
        for p in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            i0, i1, j0, j1, z = _footprint(positions, p, r, f, width, height)
            box[p, 0], box[p, 1], box[p, 2], box[p, 3] = i0, i1, j0, j1
            zmin[p] = _down32(z)
            if i0 <= i1 and j0 <= j1:
                k = _bucket(z, zlo, zscale)
                bucket[p] = k
                for b in range(j0 // band_rows, j1 // band_rows + 1):
                    counts[c, b * DEPTH_BUCKETS + k] += 1


@njit(parallel=True, cache=True, nogil=True)
def _bin_fill(positions, box, bucket, zmin, band_rows, b0, b1, base, offsets, rec_id, rec_box,
              rec_z, rec_c):
    """Write each chunk's references to bands b0 .. b1 - 1 at its offsets (less `base`, the
    first of those bands' records): compact records (id, footprint, zmin, center) grouped by
    band, front to back within a band."""
    n_chunks, n = offsets.shape[0], zmin.shape[0]
    for c in prange(n_chunks):
        fill = offsets[c] - base
        for p in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            if box[p, 0] <= box[p, 1] and box[p, 2] <= box[p, 3]:
                k = np.int64(bucket[p])
                for b in range(max(box[p, 2] // band_rows, b0),
                               min(box[p, 3] // band_rows + 1, b1)):
                    r = fill[b * DEPTH_BUCKETS + k]
                    fill[b * DEPTH_BUCKETS + k] += 1
                    rec_id[r] = p
                    rec_box[r, 0], rec_box[r, 1] = box[p, 0], box[p, 1]
                    rec_box[r, 2], rec_box[r, 3] = box[p, 2], box[p, 3]
                    rec_z[r] = zmin[p]
                    rec_c[r, 0], rec_c[r, 1] = positions[p, 0], positions[p, 1]
                    rec_c[r, 2] = positions[p, 2]


@njit(cache=True, nogil=True, inline="always")
def _before(keys, p, other):
    """Whether particle p wins a tie at equal distance against particle `other`: the lower
    key, or the lower index when keys is empty."""
    if keys.shape[0] == 0:
        return p < other
    return keys[p] < keys[other]


@njit(parallel=True, cache=True, nogil=True)
def _cast_bands(r2, f, width, height, band_rows, b0, b1, base, band_start, rec_id, rec_box,
                rec_z, rec_c, n_workers, keys, hit_t, hit_id):
    """Cast bands b0 .. b1 - 1, whose records start at band_start[b0] = base."""
    for w in prange(n_workers):
        for band in range(b0 + w, b1, n_workers):  # interleaved: balanced across workers
            row0, row1 = band * band_rows, min((band + 1) * band_rows, height) - 1
            for k in range(band_start[band] - base, band_start[band + 1] - base):
                p = rec_id[k]
                ia, ib = rec_box[k, 0], rec_box[k, 1]
                ja, jb = max(rec_box[k, 2], row0), min(rec_box[k, 3], row1)
                # hit_t is the camera depth of the hit (the unnormalized direction has unit
                # component along the view): skip a sphere whose nearest depth lies behind
                # everything already hit in its footprint (front-to-back order makes it common)
                zmin = rec_z[k]
                occluded = True
                for j in range(ja, jb + 1):
                    for i in range(ia, ib + 1):
                        if hit_t[j * width + i] >= zmin:
                            occluded = False
                            break
                    if not occluded:
                        break
                if occluded:
                    continue
                cx, cy, cz = rec_c[k, 0], rec_c[k, 1], rec_c[k, 2]
                for j in range(ja, jb + 1):
                    for i in range(ia, ib + 1):
                        q = j * width + i
                        if hit_t[q] < zmin:  # something nearer than this whole sphere
                            continue
                        # unnormalized direction: t is in units of |d|, the same for every
                        # sphere of this pixel, so comparisons hold; scaled to m at the end
                        ox, oy, oz, dx, dy, dz = pixel_ray_unnormalized(f, i, j, width, height)
                        qx, qy, qz = ox - cx, oy - cy, oz - cz
                        a = dx * dx + dy * dy + dz * dz
                        b = qx * dx + qy * dy + qz * dz
                        disc = b * b - a * (qx * qx + qy * qy + qz * qz - r2)
                        if disc < 0.0:
                            continue
                        s = math.sqrt(disc)
                        t = (-b - s) / a
                        if t < 0.0:
                            t = (-b + s) / a
                        if t < 0.0:
                            continue
                        if t < hit_t[q] or (t == hit_t[q] and _before(keys, p, hit_id[q])):
                            hit_t[q], hit_id[q] = t, p


def _depth_range(f: RayFrame, box: np.ndarray, radius: float) -> tuple[float, float]:
    """Camera depths (m) bounding every sphere of the box [2, 3] (m), for depth buckets."""
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1)
                        for k in (0, 1)])
    depth = (corners - f.position) @ f.forward
    return float(depth.min()) - radius, float(depth.max())


@njit(parallel=True, cache=True, nogil=True)
def _clear(hit_t, hit_id, height, width):
    for j in prange(height):
        for q in range(j * width, (j + 1) * width):
            hit_t[q], hit_id[q] = math.inf, -1


def cast(positions: np.ndarray, radius: float, frame: RayFrame, width: int, height: int,
         box: np.ndarray | None = None, metres: bool = True,
         out: tuple[np.ndarray, np.ndarray] | None = None, out_clear: bool = False,
         keys: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closest sphere hit per pixel, row-major from the top left: distances [h * w] and
    particle ids [h * w] (-1 where nothing is hit; distance inf). Distances are in m, or with
    metres=False the camera depth of the hit (m along the view direction, the parameter of
    `pixel_ray_unnormalized`). box [2, 3] (m) bounds the positions if known; `out` reuses
    (float64 [h * w], int32 [h * w]) buffers across frames; with out_clear they already hold
    inf and -1 everywhere (the renderer's shading pass leaves them so). keys [n] int64, if
    given, break ties at equal distance (lowest key wins) instead of the particle index."""
    pos = as_positions(positions)
    n = len(pos)
    if box is None:
        box = np.array(extent(pos)) if n else np.zeros((2, 3))
    zlo, zhi = _depth_range(frame, box, radius)
    zscale = (DEPTH_BUCKETS - 1) / (zhi - zlo) if zhi > zlo else 0.0
    n_workers = numba.get_num_threads()
    n_bands = min(height, BANDS_PER_WORKER * n_workers)
    band_rows = -(-height // n_bands)
    n_bands = -(-height // band_rows)
    # per sphere 13 bytes, per reference 28 (float32 positions, image sides < 32767, fewer
    # than 2^31 spheres): int16 pixel bounds, a float32 nearest depth rounded down (it only
    # culls) and the center in the positions' own dtype (exact, so every depth is the same)
    box_type = np.int16 if max(width, height) < np.iinfo(np.int16).max else np.int32
    box, zmin = np.empty((n, 4), box_type), np.empty(n, np.float32)
    bucket = np.zeros(n, np.uint8)  # DEPTH_BUCKETS = 256
    counts = np.zeros((CHUNKS_PER_WORKER * n_workers, n_bands * DEPTH_BUCKETS), np.int64)
    _footprints(pos, radius, frame, width, height, zlo, zscale, band_rows, box, bucket, zmin,
                counts)
    totals = counts.sum(axis=0)
    key_start = np.cumsum(totals) - totals
    offsets = key_start[None, :] + np.cumsum(counts, axis=0) - counts
    del counts
    m = int(totals.sum())
    band_start = np.append(key_start[::DEPTH_BUCKETS], m)
    if out is None:
        out = (np.empty(width * height), np.empty(width * height, np.int32))
    hit_t, hit_id = out
    if not out_clear:
        _clear(hit_t, hit_id, height, width)
    if keys is None:
        keys = NO_KEYS
    elif keys.shape != (n,) or keys.dtype != np.int64:
        raise ValueError(f"keys must be int64 [{n}], got {keys.dtype} {keys.shape}")
    # the bands in groups of consecutive ones, each group's records at most RECORD_BYTES
    # (unless one band alone holds more), built and cast in turn in the same buffers
    id_type = np.int32 if n < np.iinfo(np.int32).max else np.int64
    row_bytes = np.dtype(id_type).itemsize + 4 * np.dtype(box_type).itemsize + 4 \
        + 3 * pos.dtype.itemsize
    groups, b0 = [], 0
    while b0 < n_bands:
        b1 = b0 + 1
        while b1 < n_bands and (band_start[b1 + 1] - band_start[b0]) * row_bytes <= RECORD_BYTES:
            b1 += 1
        groups.append((b0, b1))
        b0 = b1
    most = max(int(band_start[b1] - band_start[b0]) for b0, b1 in groups)
    rec_id, rec_box = np.empty(most, id_type), np.empty((most, 4), box_type)
    rec_z, rec_c = np.empty(most, np.float32), np.empty((most, 3), pos.dtype)
    for b0, b1 in groups:
        base = int(band_start[b0])
        _bin_fill(pos, box, bucket, zmin, band_rows, b0, b1, base, offsets, rec_id, rec_box,
                  rec_z, rec_c)
        _cast_bands(radius * radius, frame, width, height, band_rows, b0, b1, base, band_start,
                    rec_id, rec_box, rec_z, rec_c, n_workers, keys, hit_t, hit_id)
    del rec_id, rec_box, rec_z, rec_c, box, bucket, zmin
    if metres:
        _to_metres(frame, width, height, hit_t)
    return hit_t, hit_id


@njit(parallel=True, cache=True, nogil=True)
def _to_metres(f, width, height, hit_t):
    """Scale distances from units of the unnormalized ray direction to m."""
    if not f.perspective:
        return
    for j in prange(height):
        for i in range(width):
            q = j * width + i
            if hit_t[q] < math.inf:
                _, _, _, dx, dy, dz = pixel_ray_unnormalized(f, i, j, width, height)
                hit_t[q] *= math.sqrt(dx * dx + dy * dy + dz * dz)
