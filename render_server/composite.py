"""Sort-last depth compositing of per-rank images into one frame on the root rank.

Direct send (as IceT's): rank r owns a band of image rows (rows h*r//N to h*(r+1)//N); every
rank sends each owner the rows of its band (colour, depth and key, one Alltoallv each; the
bands are contiguous rows, so no packing), each owner keeps at every pixel the layer of the
nearest depth, on equal depth the lowest key, and the root gathers the bands. The winning
(depth, key) is what a one-process render chooses among all the particles (render_server.cast
breaks ties by the same keys), so the composited frame is pixel-identical to it. Each rank
sends and receives (N - 1)/N of its image, 19 bytes a pixel (rgb, float64 depth, int64 key).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


def bands(height: int, ranks: int) -> np.ndarray:
    """First row of each rank's band and the end: [ranks + 1] int64."""
    return np.array([height * r // ranks for r in range(ranks + 1)], np.int64)


@njit(parallel=True, cache=True, nogil=True)
def _merge(rgb, depth, key, out_rgb, out_hit):
    """out_rgb[q], out_hit[q]: the layer of rgb [s, m, 3] / depth [s, m] / key [s, m] with
    the nearest depth at pixel q (lowest key on ties; source 0's background when no layer
    is hit), and whether any layer is hit."""
    for q in prange(rgb.shape[1]):
        best = 0
        for s in range(1, rgb.shape[0]):
            if depth[s, q] < depth[best, q] or (depth[s, q] == depth[best, q]
                                                and key[s, q] < key[best, q]):
                best = s
        out_rgb[q, 0], out_rgb[q, 1], out_rgb[q, 2] = rgb[best, q, 0], rgb[best, q, 1], rgb[best, q, 2]
        out_hit[q] = depth[best, q] < np.inf


def _row_type(row_bytes: int):
    from mpi4py import MPI

    return MPI.BYTE.Create_contiguous(row_bytes).Commit()


def composite(comm, rgb: np.ndarray, depth: np.ndarray, key: np.ndarray, root: int = 0
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """Composite every rank's layer (collective): rgb [h, w, 3] uint8, depth [h * w] float64
    (inf where nothing is hit), key [h * w] int64 of each pixel's particle. Returns on `root`
    the frame [h, w, 3] uint8 and hit [h * w] bool (a particle covers the pixel); None on
    the other ranks."""
    h, w = rgb.shape[:2]
    if depth.shape != (h * w,) or key.shape != (h * w,):
        raise ValueError(f"depth and key must be [{h * w}], got {depth.shape} and {key.shape}")
    if comm is None or comm.size == 1:
        return np.ascontiguousarray(rgb), depth < np.inf
    n = comm.size
    rows = bands(h, n)
    mine = int(rows[comm.rank + 1] - rows[comm.rank])
    send_counts = np.diff(rows)
    send_displs = rows[:-1]
    recv_counts = np.full(n, mine, np.int64)
    recv_displs = np.arange(n, dtype=np.int64) * mine
    layers = {"rgb": np.empty((n, mine * w, 3), np.uint8),
              "depth": np.empty((n, mine * w)), "key": np.empty((n, mine * w), np.int64)}
    for name, data in (("rgb", rgb), ("depth", depth), ("key", key)):
        data = np.ascontiguousarray(data)
        row = _row_type(w * data.itemsize * (3 if name == "rgb" else 1))
        try:
            comm.Alltoallv([data.view(np.uint8).reshape(-1), (send_counts, send_displs), row],
                           [layers[name].view(np.uint8).reshape(-1), (recv_counts, recv_displs),
                            row])
        finally:
            row.Free()
    band_rgb = np.empty((mine * w, 3), np.uint8)
    band_hit = np.empty(mine * w, np.bool_)
    _merge(layers["rgb"], layers["depth"], layers["key"], band_rgb, band_hit)
    out = hit = None
    if comm.rank == root:
        out, hit = np.empty((h, w, 3), np.uint8), np.empty(h * w, np.bool_)
    for band, full, bytes_per_px in ((band_rgb, out, 3), (band_hit, hit, 1)):
        row = _row_type(w * bytes_per_px)
        try:
            recv = None if full is None else [full.view(np.uint8).reshape(-1),
                                              (send_counts, send_displs), row]
            comm.Gatherv([band.view(np.uint8).reshape(-1), mine, row], recv, root=root)
        finally:
            row.Free()
    return None if out is None else (out, hit)
