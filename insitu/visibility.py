"""Occlusion culling on the simulation's side: which particles a view's camera can see.

A view with `occlusion_cull` is sent only the particles that may show in its image, so
the bytes follow the visible surface, not the volume. The test is conservative (a
particle it keeps may be hidden; one it drops is hidden), for spheres of radius r (m)
rendered by the server's ray caster (VTK camera, pixel centers):

1. Coverage. Each particle Q covers, in a coarse screen grid of B x B pixel bins, every bin
   that lies wholly inside the projection of its central cross-section (a disk of radius
   r at Q's depth d_Q along the view axis: its projection is a disk of radius k r / d_Q px
   in perspective, k r px in parallel projection). Every ray through that disk enters Q's
   sphere at a view depth <= d_Q. cover[bin] = the least such d_Q.
2. Test. Particle P's sphere lies at view depths >= d_P - r and projects inside a disk of
   radius k r (1 + |s|) / (d_P - r) px around its center (s: the tangent of its off-axis
   angle; k r in parallel projection). P is hidden when every bin that disk touches inside
   the image has cover < d_P - r (along one ray, view depth orders hits as the ray
   parameter does), and out of view when it touches none.

The nearest coverer of a bin is never dropped (its cover is its own depth), so the
particles kept still hide the ones dropped: a chunk holding the union over several views
renders each of them as if every particle were there. Shadows differ (hidden particles
cast them), which is why culling is opt-in per view.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from minority.protocol.projection import (
    camera_basis,
    camera_coordinates,
    in_frame,
    pixels_per_unit,
    to_pixels,
)
from minority.protocol.view import View

MAX_BINS = 1 << 22  # bins per image, a bound on the cover buffer (32 MiB)
BINS_PER_RADIUS = 6.0  # bin edge ~ a sixth of the typical disk radius (px)


def visible_mask(positions: np.ndarray, view: View, radius_m: float) -> np.ndarray:
    """[n] bool: particles (positions [n, 3], m) that may show in `view`'s image as
    spheres of `radius_m` (m)."""
    cam = view.camera
    u, v, d = camera_coordinates(positions, camera_basis(cam))  # m
    w, h = view.width, view.height
    near = d > radius_m  # the camera is outside the sphere, in front of it
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        x, y = to_pixels(u, v, d, cam, w, h)  # px: image x right, y down
        k = pixels_per_unit(cam, h)  # px per m (parallel) or per tangent (perspective)
        if cam.parallel_projection:
            r_in = np.full(len(d), k * radius_m)
            r_out = r_in
        else:
            r_in = k * radius_m / d  # the central cross-section's disk
            # silhouette: within the cone of half-angle asin(r / D) around the center's ray,
            # whose projection reaches tan(theta + alpha) - tan(theta) from the center
            theta = np.arctan(np.hypot(u, v) / d)
            alpha = np.arcsin(np.minimum(radius_m / np.sqrt(u * u + v * v + d * d), 1.0))
            r_out = np.where(theta + alpha < 0.5 * math.pi - 1e-6,
                             k * (np.tan(theta + alpha) - np.tan(theta)), np.inf)
        framed = in_frame(x, y, r_out, w, h)  # the silhouette's disk reaches the image
    typical = float(np.median(r_in[near])) if near.any() else 0.0
    # bins of whole pixels, a few per disk radius, at most MAX_BINS per image
    b = int(max(1, math.floor(typical / BINS_PER_RADIUS), math.ceil(math.sqrt(w * h / MAX_BINS))))
    cover = np.full((-(-h // b), -(-w // b)), np.inf)
    _cover(x, y, d, r_in, near, b, cover)
    return _visible(x, y, d, r_out, near, framed, radius_m, b, cover)


@njit(cache=True, nogil=True)
def _cover(x, y, d, r_in, near, b, cover):
    """cover[bin] = least depth d of a particle whose disk r_in holds every pixel center of
    the bin (pixel centers of bin (i, j): i b + 0.5 ... (i + 1) b - 0.5, likewise in y)."""
    nby, nbx = cover.shape
    for q in range(len(x)):
        rad = r_in[q]
        if not near[q] or not rad > 0.5:
            continue
        j0 = max(int(math.floor((y[q] - rad) / b)), 0)
        j1 = min(int(math.floor((y[q] + rad) / b)), nby - 1)
        dq = d[q]
        for j in range(j0, j1 + 1):
            dy = max(abs(j * b + 0.5 - y[q]), abs((j + 1) * b - 0.5 - y[q]))
            if dy >= rad:
                continue
            half = math.sqrt(rad * rad - dy * dy)  # the bin's columns must lie in x +- half
            i0 = max(int(math.ceil((x[q] - half - 0.5) / b)), 0)
            i1 = min(int(math.floor((x[q] + half + 0.5) / b)) - 1, nbx - 1)
            row = cover[j]
            for i in range(i0, i1 + 1):
                if dq < row[i]:
                    row[i] = dq


@njit(cache=True, parallel=True, nogil=True)
def _visible(x, y, d, r_out, near, framed, radius, b, cover):
    """Keep a particle unless its silhouette misses the image (framed False), or every bin
    holding a pixel center inside it is covered nearer than its front (d - radius)."""
    nby, nbx = cover.shape
    keep = np.zeros(len(x), dtype=np.bool_)
    for p in prange(len(x)):
        if not near[p]:  # the sphere holds the camera or is behind it
            keep[p] = d[p] + radius > 0.0
            continue
        rad = r_out[p]
        if not rad < 1e9:
            keep[p] = True
            continue
        if not framed[p]:
            continue  # out of view
        front = d[p] - radius
        j0 = max(int(math.floor((y[p] - rad) / b)), 0)
        j1 = min(int(math.floor((y[p] + rad) / b)), nby - 1)
        seen = False
        for j in range(j0, j1 + 1):
            # nearest pixel-center row of the bin to the center
            dy = max(j * b + 0.5 - y[p], 0.0, y[p] - ((j + 1) * b - 0.5))
            if dy > rad:
                continue
            half = math.sqrt(rad * rad - dy * dy)  # bins with a column center in x +- half
            i0 = max(int(math.floor((x[p] - half - 0.5) / b)), 0)
            i1 = min(int(math.floor((x[p] + half - 0.5) / b)), nbx - 1)
            row = cover[j]
            for i in range(i0, i1 + 1):
                if not row[i] < front:
                    seen = True
                    break
            if seen:
                break
        keep[p] = seen
    return keep
