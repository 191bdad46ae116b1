"""Sort-last depth compositing of per-rank images into one frame on the root rank.

Sparse direct send: rank r owns a band of image rows (rows h*r//N to h*(r+1)//N); every rank
sends each owner only the pixels of that band its particles hit, as 24-byte records (pixel
index and colour in one word, depth, key), all owners in one Alltoallv. Each owner starts
from its own layer and keeps at every pixel the record of the nearest depth, on equal depth
the lowest key; the root gathers the bands (colour and hit flag, 4 bytes a pixel). The
winning (depth, key) is what a one-process render chooses among all the particles
(render_server.cast breaks ties by the same keys), so the composited frame is
pixel-identical to it. A rank sends 24 bytes per hit pixel outside its own band: with
coverage c of the image, 24 c (N-1)/N bytes a pixel instead of the 19 (N-1)/N of dense
direct send, and a brick covers less of the image the more ranks there are.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from minority.render_server.distribute import Pool, alltoallv_rows

RECORD_WORDS = 3  # uint64 words of a pixel record: index << 24 | rgb, depth bits, key


def bands(height: int, ranks: int) -> np.ndarray:
    """First row of each rank's band and the end: [ranks + 1] int64."""
    return np.array([height * r // ranks for r in range(ranks + 1)], np.int64)


@njit(parallel=True, cache=True, nogil=True)
def _count_hits(depth, starts, counts):
    """counts[b]: pixels hit (depth < inf) in band b, pixels starts[b] .. starts[b + 1]."""
    for b in prange(counts.shape[0]):
        c = 0
        for q in range(starts[b], starts[b + 1]):
            if depth[q] < np.inf:
                c += 1
        counts[b] = c


@njit(parallel=True, cache=True, nogil=True)
def _pack(rgb, depth, key, starts, offsets, skip, out):
    """The records [k, 3] uint64 of every hit pixel of every band but `skip`, band b's at
    offsets[b]: (index in the band << 24 | r << 16 | g << 8 | b, depth bits, key)."""
    bits = depth.view(np.uint64)
    for b in prange(starts.shape[0] - 1):
        if b == skip:
            continue
        r = offsets[b]
        for q in range(starts[b], starts[b + 1]):
            if depth[q] < np.inf:
                colour = (np.uint64(rgb[q, 0]) << np.uint64(16)) | (np.uint64(rgb[q, 1]) << np.uint64(8)) \
                    | np.uint64(rgb[q, 2])
                out[r, 0] = (np.uint64(q - starts[b]) << np.uint64(24)) | colour
                out[r, 1] = bits[q]
                out[r, 2] = np.uint64(key[q])
                r += 1


@njit(cache=True, nogil=True)
def _merge_records(rgb, depth, key, start, records, record_depth, band_rgb, band_hit):
    """Merge records [k, 3] (record_depth: the same memory seen as float64) into this rank's
    band (band_rgb [m, 3] uint8, band_hit [m] bool), which starts as this rank's own layer
    (rgb [h * w, 3], depth and key [h * w] from pixel `start`): a record replaces the pixel
    if its depth is nearer, or equal with a lower key. The band's depth and key are merged
    in place, in depth and key."""
    for q in range(band_rgb.shape[0]):  # explicit: numba's 2-D slice copy is 5x slower
        band_rgb[q, 0], band_rgb[q, 1] = rgb[start + q, 0], rgb[start + q, 1]
        band_rgb[q, 2] = rgb[start + q, 2]
        band_hit[q] = depth[start + q] < np.inf
    for r in range(records.shape[0]):
        q = start + np.int64(records[r, 0] >> np.uint64(24))
        d = record_depth[r, 1]
        k = np.int64(records[r, 2])
        if d < depth[q] or (d == depth[q] and k < key[q]):
            depth[q], key[q] = d, k
            colour = records[r, 0]
            band_rgb[q - start, 0] = np.uint8((colour >> np.uint64(16)) & np.uint64(255))
            band_rgb[q - start, 1] = np.uint8((colour >> np.uint64(8)) & np.uint64(255))
            band_rgb[q - start, 2] = np.uint8(colour & np.uint64(255))
            band_hit[q - start] = True


def _row_type(row_bytes: int):
    from mpi4py import MPI

    return MPI.BYTE.Create_contiguous(row_bytes).Commit()


def composite(comm, rgb: np.ndarray, depth: np.ndarray, key: np.ndarray, root: int = 0,
              pool: Pool | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Composite every rank's layer (collective): rgb [h, w, 3] uint8, depth [h * w] float64
    (inf where nothing is hit), key [h * w] int64 of each pixel's particle. Returns on `root`
    the frame [h, w, 3] uint8 and hit [h * w] bool (a particle covers the pixel); None on
    the other ranks. This rank's band of depth and key is overwritten with the merged one
    (when they are C-contiguous; otherwise copies are merged). `pool` keeps the send,
    receive and band buffers from call to call (no page faults once grown)."""
    from mpi4py import MPI

    h, w = rgb.shape[:2]
    if depth.shape != (h * w,) or key.shape != (h * w,):
        raise ValueError(f"depth and key must be [{h * w}], got {depth.shape} and {key.shape}")
    if comm is None or comm.size == 1:
        return np.ascontiguousarray(rgb), depth < np.inf
    n, me = comm.size, comm.rank
    rows = bands(h, n)
    starts = rows * w  # first pixel of each band [n + 1]
    flat = np.ascontiguousarray(rgb).reshape(h * w, 3)
    depth, key = np.ascontiguousarray(depth), np.ascontiguousarray(key)
    send_counts = np.empty(n, np.int64)
    _count_hits(depth, starts, send_counts)
    send_counts[me] = 0  # this rank's own band stays in place
    recv_counts = np.empty(n, np.int64)
    comm.Alltoall([send_counts, MPI.INT64_T], [recv_counts, MPI.INT64_T])
    pool = Pool() if pool is None else pool
    send = pool.get("composite_send", (int(send_counts.sum()), RECORD_WORDS), np.uint64)
    _pack(flat, depth, key, starts, np.cumsum(send_counts) - send_counts, me, send)
    recv = pool.get("composite_recv", (int(recv_counts.sum()), RECORD_WORDS), np.uint64)
    alltoallv_rows(comm, send, send_counts, recv, recv_counts)
    del send
    mine = int(rows[me + 1] - rows[me])
    band_rgb = pool.get("composite_rgb", (mine * w, 3), np.uint8)
    band_hit = pool.get("composite_hit", (mine * w,), np.bool_)
    _merge_records(flat, depth, key, int(starts[me]), recv, recv.view(np.float64), band_rgb,
                   band_hit)
    del recv
    out = hit = None
    if me == root:
        out, hit = np.empty((h, w, 3), np.uint8), np.empty(h * w, np.bool_)
    for band, full, bytes_per_px in ((band_rgb, out, 3), (band_hit, hit, 1)):
        row = _row_type(w * bytes_per_px)
        try:
            recv_spec = None if full is None else [full.view(np.uint8).reshape(-1),
                                                   (np.diff(rows), rows[:-1]), row]
            comm.Gatherv([band.view(np.uint8).reshape(-1), mine, row], recv_spec, root=root)
        finally:
            row.Free()
    return None if out is None else (out, hit)
