"""VTK's camera model: view and projection matrices, pixel projection, primary rays.

Conventions follow vtkCamera: the view angle is the full vertical angle in degrees; with
parallel projection, parallel_scale is half the view height in m. Image pixels: x to the
right, y down (row 0 at the top), pixel centers at (i + 0.5, j + 0.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from minority.protocol.spec import Camera
from numba import njit, prange


@dataclass(frozen=True)
class CameraBasis:
    """Orthonormal camera frame in world coordinates (m)."""

    position: np.ndarray  # [3]
    right: np.ndarray  # [3], image +x
    up: np.ndarray  # [3], image +y (orthogonalized view up)
    forward: np.ndarray  # [3], from position toward the focal point
    distance: float  # position to focal point, m


def basis(camera: Camera) -> CameraBasis:
    return CameraBasis(*camera.frame())


def view_matrix(camera: Camera) -> np.ndarray:
    """World to camera coordinates [4, 4] (camera looks down -z, +y up)."""
    b = basis(camera)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = b.right, b.up, -b.forward
    m[:3, 3] = -m[:3, :3] @ b.position
    return m


def projection_matrix(camera: Camera, aspect: float, near: float, far: float) -> np.ndarray:
    """Camera to clip coordinates [4, 4], OpenGL/VTK convention (NDC z in [-1, 1])."""
    m = np.zeros((4, 4))
    if camera.parallel_projection:
        s = camera.parallel_scale_m
        m[0, 0], m[1, 1] = 1.0 / (s * aspect), 1.0 / s
        m[2, 2], m[2, 3] = -2.0 / (far - near), -(far + near) / (far - near)
        m[3, 3] = 1.0
    else:
        f = 1.0 / math.tan(math.radians(camera.view_angle_deg) / 2.0)
        m[0, 0], m[1, 1] = f / aspect, f
        m[2, 2], m[2, 3] = -(far + near) / (far - near), -2.0 * far * near / (far - near)
        m[3, 2] = -1.0
    return m


def project(points: np.ndarray, camera: Camera, width: int, height: int,
            near: float = 0.01, far: float = 1000.0) -> np.ndarray:
    """Pixel coordinates [n, 2] (x right, y down, px) of world points [n, 3] (m)."""
    pv = projection_matrix(camera, width / height, near, far) @ view_matrix(camera)
    h = np.c_[points, np.ones(len(points))] @ pv.T
    ndc = h[:, :2] / h[:, 3:4]
    return np.c_[(ndc[:, 0] + 1.0) * 0.5 * width, (1.0 - ndc[:, 1]) * 0.5 * height]


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
    b = basis(camera)
    aspect = width / height
    if camera.parallel_projection:
        hh = camera.parallel_scale_m
    else:
        hh = math.tan(math.radians(camera.view_angle_deg) / 2.0)
    return RayFrame(b.position, b.right, b.up, b.forward, hh * aspect, hh,
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
