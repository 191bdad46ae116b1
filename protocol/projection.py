"""VTK's camera model as numbers: the camera frame, the frustum, world points to pixels.

The one home of the projection rules that both sides of the wire apply to a spec's camera:
the render server (render_server.camera builds its pixel rays from `camera_basis` and
`half_extents`), the ranks (insitu.visibility projects particles with `camera_coordinates`,
`to_pixels` and `in_frame` to leave out what no view sees) and the oracle
(gns.oracle.fit_camera frames a box with `orthonormal_frame` and `view_tangent`).

Conventions follow vtkCamera: the view angle is the full vertical angle in degrees; with
parallel projection, parallel_scale_m is half the view height in m. Camera coordinates:
u along right (image +x), v along up (image +y), d along forward (depth, m). Image pixels:
x to the right, y down (row 0 at the top), the image spans [0, width] x [0, height] px and
pixel (i, j) has its center at (i + 0.5, j + 0.5).

Plain numpy, no numba: a kernel that inlined a helper from here would keep a stale copy in
numba's on-disk cache after an edit (protocol.jitcache tracks a package's own files only).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from minority.protocol.view import Camera


class CameraBasis(NamedTuple):
    """Orthonormal camera frame in world coordinates."""

    position: np.ndarray  # [3] float64, m
    right: np.ndarray  # [3], image +x
    up: np.ndarray  # [3], image +y (the view up orthogonalized)
    forward: np.ndarray  # [3], from position toward the focal point
    distance: float  # position to focal point, m


def orthonormal_frame(direction, view_up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """right, up, forward [3] float64 (unit) of a camera looking along `direction` [3] with
    `view_up` [3] (neither need be unit; they must not be parallel), VTK's convention."""
    forward = np.asarray(direction, dtype=np.float64)
    forward = forward / float(np.linalg.norm(forward))
    right = np.cross(forward, np.asarray(view_up, dtype=np.float64))
    right /= np.linalg.norm(right)
    return right, np.cross(right, forward), forward


def camera_basis(camera: Camera) -> CameraBasis:
    """The camera's frame: position [3] (m), right, up, forward [3] and focal distance (m)."""
    position = np.asarray(camera.position, dtype=np.float64)
    direction = np.asarray(camera.focal_point, dtype=np.float64) - position
    right, up, forward = orthonormal_frame(direction, camera.view_up)
    return CameraBasis(position, right, up, forward, float(np.linalg.norm(direction)))


def view_tangent(view_angle_deg: float) -> float:
    """tan of half the vertical view angle (deg): the frustum's half height at depth 1."""
    return math.tan(math.radians(view_angle_deg) / 2.0)


def half_extents(camera: Camera, aspect: float) -> tuple[float, float]:
    """Half width and half height of the image in the camera plane for an image of
    width / height `aspect`: tangents (perspective; at depth d they span d times as many
    m) or m (parallel projection)."""
    hh = camera.parallel_scale_m if camera.parallel_projection else view_tangent(
        camera.view_angle_deg)
    return hh * aspect, hh


def camera_coordinates(points: np.ndarray, basis: CameraBasis
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera coordinates u, v, d [n] (m) of world points [n, 3] (m): along right, up and
    forward from the camera position."""
    rel = np.asarray(points, dtype=np.float64) - basis.position
    return rel @ basis.right, rel @ basis.up, rel @ basis.forward


def pixels_per_unit(camera: Camera, height: int) -> float:
    """Image scale k: px per unit of u / d (perspective) or per m of u (parallel)."""
    return height / (2.0 * half_extents(camera, 1.0)[1])


def to_pixels(u: np.ndarray, v: np.ndarray, d: np.ndarray, camera: Camera, width: int,
              height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates x, y [n] (px; x right, y down) of camera coordinates u, v, d [n]
    (m). In perspective, points at d <= 0 (behind the camera) come out mirrored or
    infinite: test d first (callers silence numpy's division warnings if they pass such)."""
    k = pixels_per_unit(camera, height)
    if camera.parallel_projection:
        x, y = k * u, k * v
    else:
        x, y = k * u / d, k * v / d
    return x + 0.5 * width, 0.5 * height - y


def project(points: np.ndarray, camera: Camera, width: int, height: int) -> np.ndarray:
    """Pixel coordinates [n, 2] (px; x right, y down) of world points [n, 3] (m) in front
    of the camera (perspective: depth > 0) in an image of width x height px."""
    u, v, d = camera_coordinates(points, camera_basis(camera))
    x, y = to_pixels(u, v, d, camera, width, height)
    return np.stack([x, y], axis=1)


def in_frame(x: np.ndarray, y: np.ndarray, r_px, width: int, height: int) -> np.ndarray:
    """[n] bool: the disk of radius r_px (px, [n] or scalar; 0 for a point) around (x, y)
    (px) reaches the image [0, width] x [0, height] (edges included). NaN coordinates count
    as in frame (the caller decides those)."""
    return ~((x + r_px < 0.0) | (x - r_px > width) | (y + r_px < 0.0) | (y - r_px > height))


def in_view(points: np.ndarray, camera: Camera, width: int, height: int) -> np.ndarray:
    """[n] bool: the view frustum test for points [n, 3] (m): in front of the camera
    (depth > 0; the renderer's rays start at the camera, or its plane in parallel
    projection) and projected into the image, edges included."""
    u, v, d = camera_coordinates(points, camera_basis(camera))
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = to_pixels(u, v, d, camera, width, height)
        return (d > 0.0) & in_frame(x, y, 0.0, width, height)
