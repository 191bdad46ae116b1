"""Render one view of one step: repartition, acceleration structures, ray casting, shading.

Lambert plus ambient shading with one directional key light placed relative to the camera,
optional hard shadows (a shadow ray per lit pixel), background color where no sphere is hit.
Image: uint8 [height, width, 3], row 0 at the top.
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass

import numba
import numpy as np
from PIL import Image

from protocol.spec import View
from render_server.accel import BrickGrids, build_grids
from render_server.bricks import Bricks, repartition
from render_server.camera import basis, primary_rays
from render_server.colormap import preset
from render_server.trace import trace

AMBIENT = 0.3
DIFFUSE = 0.7
# key light direction in camera coordinates (right, up, toward the viewer), normalized below
KEY_LIGHT_CAMERA = np.array([-0.4, 0.6, 0.7])
SHADOW_OFFSET_RADII = 1e-3  # shadow rays start this far off the surface, in sphere radii
BRICKS_PER_THREAD = 4
PNG_COMPRESS_LEVEL = 1  # zlib level: fast, still lossless


@dataclass
class Scene:
    """A step's particles prepared for rendering (the setup phase)."""

    positions: np.ndarray  # [n, 3] float64, m
    radius: float  # m
    bricks: Bricks
    grids: BrickGrids


def default_bricks() -> int:
    n = BRICKS_PER_THREAD * numba.get_num_threads()
    return 1 << (n - 1).bit_length()


def prepare(positions: np.ndarray, radius: float, n_bricks: int | None = None) -> Scene:
    """Setup: k-d bricks and their uniform grids for spheres of `radius` (m)."""
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    bricks = repartition(pos, radius, n_bricks or default_bricks())
    return Scene(pos, radius, bricks, build_grids(pos, radius, bricks))


def field_values(field: np.ndarray) -> np.ndarray:
    """Scalar per particle: the field itself [n], or its magnitude for [n, k]."""
    return field if field.ndim == 1 else np.linalg.norm(field, axis=1)


def key_light(view: View) -> np.ndarray:
    b = basis(view.camera)
    d = KEY_LIGHT_CAMERA[0] * b.right + KEY_LIGHT_CAMERA[1] * b.up - KEY_LIGHT_CAMERA[2] * b.forward
    return d / np.linalg.norm(d)  # direction from a surface point toward the light


def render(scene: Scene, values: np.ndarray, view: View, shadows: bool = False) -> np.ndarray:
    """The image of `view`: spheres colored by `values` [n] with the view's colormap/range."""
    origins, dirs = primary_rays(view.camera, view.width, view.height)
    t, ids = trace(origins, dirs, scene.positions, scene.radius, scene.bricks, scene.grids)
    hit = ids >= 0
    image = np.empty((len(ids), 3))
    image[:] = view.background
    if hit.any():
        hp = origins[hit] + dirs[hit] * t[hit, None]
        normals = (hp - scene.positions[ids[hit]]) / scene.radius
        light = key_light(view)
        lambert = np.clip(normals @ light, 0.0, None)
        if shadows:
            lit = lambert > 0
            start = hp[lit] + normals[lit] * (SHADOW_OFFSET_RADII * scene.radius)
            _, blocker = trace(start, np.broadcast_to(light, start.shape), scene.positions,
                               scene.radius, scene.bricks, scene.grids)
            shade = lambert[lit]
            shade[blocker >= 0] = 0.0
            lambert[lit] = shade
        base = preset(view.colormap).map(values[ids[hit]], *view.range)
        image[hit] = base * (AMBIENT + DIFFUSE * lambert)[:, None]
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).reshape(
        view.height, view.width, 3)


def encode_png(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image, "RGB").save(buf, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


@dataclass
class RenderTimes:
    setup_s: float
    render_s: float


def render_step(positions: np.ndarray, fields: dict[str, np.ndarray], radius: float,
                views: list[View], shadows: bool = False) -> tuple[dict[str, np.ndarray], RenderTimes]:
    """Every view of one step; returns images by view name and the setup/render wall times."""
    t0 = time.perf_counter()
    scene = prepare(positions, radius)
    t1 = time.perf_counter()
    images = {}
    for view in views:
        if view.field not in fields:
            raise KeyError(f"view {view.name!r} needs field {view.field!r}; the step has "
                           f"{sorted(fields)}")
        images[view.name] = render(scene, field_values(fields[view.field]), view, shadows)
    return images, RenderTimes(t1 - t0, time.perf_counter() - t1)
