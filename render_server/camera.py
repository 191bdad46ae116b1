"""The renderer's camera: primary rays through pixel centers (numba, inlined by the ray
kernels in render_server.cast and render_server.render).

The camera model itself (frame, frustum, projection of points to pixels) lives in
protocol.projection, shared with the sim's visibility; the rays here are its inverse: the
ray through pixel (i, j) projects to the pixel center (i + 0.5, j + 0.5).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from minority.protocol.projection import camera_basis, half_extents
from minority.protocol.spec import Camera


class RayFrame(NamedTuple):
    """What the ray kernels need of a camera (a NamedTuple, so numba takes it as is)."""

    position: np.ndarray  # [3] m
    right: np.ndarray  # [3]
    up: np.ndarray  # [3]
    forward: np.ndarray  # [3]
    half_width: float  # perspective: tan(angle/2) * aspect; parallel: scale * aspect (m)
    half_height: float  # perspective: tan(angle/2); parallel: parallel scale (m)
    perspective: bool


def ray_frame(camera: Camera, width: int, height: int) -> RayFrame:
    b = camera_basis(camera)
    half_width, half_height = half_extents(camera, width / height)
    return RayFrame(b.position, b.right, b.up, b.forward, half_width, half_height,
                    not camera.parallel_projection)


@njit(cache=True, inline="always")
def pixel_ray_unnormalized(f, i, j, width, height):
    """Origin and direction (ox, oy, oz, dx, dy, dz) of the ray through the center of pixel
    column i, row j (row 0 at the top); the direction is not normalized in perspective."""
    gx = 2.0 * (i + 0.5) / width - 1.0
    gy = 1.0 - 2.0 * (j + 0.5) / height
    sx, sy = gx * f.half_width, gy * f.half_height
    if f.perspective:
        return (f.position[0], f.position[1], f.position[2],
                f.forward[0] + sx * f.right[0] + sy * f.up[0],
                f.forward[1] + sx * f.right[1] + sy * f.up[1],
                f.forward[2] + sx * f.right[2] + sy * f.up[2])
    return (f.position[0] + sx * f.right[0] + sy * f.up[0],
            f.position[1] + sx * f.right[1] + sy * f.up[1],
            f.position[2] + sx * f.right[2] + sy * f.up[2],
            f.forward[0], f.forward[1], f.forward[2])


@njit(cache=True, inline="always")
def pixel_ray(f, i, j, width, height):
    """Origin and unit direction of the ray through the center of pixel (i, j)."""
    ox, oy, oz, dx, dy, dz = pixel_ray_unnormalized(f, i, j, width, height)
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return ox, oy, oz, dx / norm, dy / norm, dz / norm


@njit(parallel=True, cache=True, nogil=True)
def _rays(f, width, height, origins, dirs):
    for j in prange(height):
        for i in range(width):
            q = j * width + i
            (origins[q, 0], origins[q, 1], origins[q, 2],
             dirs[q, 0], dirs[q, 1], dirs[q, 2]) = pixel_ray(f, i, j, width, height)


def primary_rays(camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions [height * width, 3] through pixel centers, row-major
    from the top-left pixel."""
    origins = np.empty((width * height, 3))
    dirs = np.empty((width * height, 3))
    _rays(ray_frame(camera, width, height), width, height, origins, dirs)
    return origins, dirs
