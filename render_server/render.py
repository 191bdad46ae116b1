"""Render one view of one step: repartition, acceleration structures, ray casting, shading.

Primary visibility by exact object-order ray casting (`cast`), Lambert plus ambient shading
with one directional key light placed relative to the camera, optional hard shadows (a
shadow ray per lit pixel through the bricks' grids), background color where nothing is hit.
Image: uint8 [height, width, 3], row 0 at the top.
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange
from PIL import Image

from minority.protocol.projection import camera_basis
from minority.protocol.spec import View
from minority.render_server.accel import BrickGrids, build_grids
from minority.render_server.bricks import Bricks, as_positions, repartition
from minority.render_server.camera import pixel_ray, pixel_ray_unnormalized, primary_rays, ray_frame
from minority.render_server.cast import NO_KEYS, cast
from minority.render_server.colormap import view_colormap
from minority.render_server.trace import trace

AMBIENT = 0.3
DIFFUSE = 0.7
# key light direction in camera coordinates (right, up, toward the viewer), normalized below
KEY_LIGHT_CAMERA = np.array([-0.4, 0.6, 0.7])
SHADOW_OFFSET_RADII = 1e-3  # shadow rays start this far off the surface, in sphere radii
BRICKS_PER_THREAD = 4
PARTICLES_PER_BRICK_MIN = 16_384  # below this, splitting costs more setup than it saves
PNG_COMPRESS_LEVEL = 1  # zlib level: fast, still lossless
NO_KEY = np.iinfo(np.int64).max  # depth capture: the key of a pixel nothing covers


@dataclass
class Scene:
    """A step's particles prepared for rendering (the setup phase)."""

    positions: np.ndarray  # [n, 3] float32 or float64, m
    radius: float  # m
    bricks: Bricks
    grids: BrickGrids | None  # per-brick uniform grids, built when shadow rays are cast


def default_bricks(particles: int) -> int:
    """A power of two: BRICKS_PER_THREAD per thread, fewer for small steps."""
    most = BRICKS_PER_THREAD * numba.get_num_threads()
    wanted = max(1, min(most, particles // PARTICLES_PER_BRICK_MIN))
    return 1 << (wanted.bit_length() - 1)


def prepare(positions: np.ndarray, radius: float, n_bricks: int | None = None,
            grids: bool = True) -> Scene:
    """Setup: k-d bricks for spheres of `radius` (m) and, with `grids`, their uniform grids
    (needed by shadow rays; primary rays are cast in object order without them)."""
    pos = as_positions(positions)
    bricks = repartition(pos, radius, n_bricks or default_bricks(len(pos)))
    return Scene(pos, radius, bricks, build_grids(pos, radius, bricks) if grids else None)


def field_columns(field: np.ndarray) -> np.ndarray:
    """A field [n] or [n, k] as a C-contiguous [n, k] array (a view when possible); pixels
    are colored by the value (k = 1) or the magnitude (k > 1) of their particle's row."""
    return np.ascontiguousarray(field.reshape(len(field), -1))


def key_light(view: View) -> np.ndarray:
    b = camera_basis(view.camera)
    d = KEY_LIGHT_CAMERA[0] * b.right + KEY_LIGHT_CAMERA[1] * b.up - KEY_LIGHT_CAMERA[2] * b.forward
    return d / np.linalg.norm(d)  # direction from a surface point toward the light


@njit(parallel=True, cache=True, nogil=True)
def _shade(f, width, height, hit_t, hit_id, metric, positions, radius, field, lut, vmin, vmax,
           nan_rgb, light, shadowed, background, out, hit):
    """Lambert + ambient shading of every pixel into out [h * w, 3] uint8, and hit [h * w]
    bool: whether a particle covers the pixel; hit_t in m along unit rays (metric) or in
    camera depth along `pixel_ray_unnormalized`. Leaves hit_t and hit_id cleared (inf, -1)
    for the next frame, saving a pass over the image."""
    scale = (lut.shape[0] - 1) / (vmax - vmin) if vmax > vmin else 0.0
    for j in prange(height):
        for i in range(width):
            q = j * width + i
            p = hit_id[q]
            hit[q] = p >= 0
            if p < 0:
                out[q, 0], out[q, 1], out[q, 2] = background[0], background[1], background[2]
                continue
            if metric:
                ox, oy, oz, dx, dy, dz = pixel_ray(f, i, j, width, height)
            else:
                ox, oy, oz, dx, dy, dz = pixel_ray_unnormalized(f, i, j, width, height)
            t = hit_t[q]
            hit_t[q], hit_id[q] = math.inf, -1
            nx = (ox + dx * t - positions[p, 0]) / radius
            ny = (oy + dy * t - positions[p, 1]) / radius
            nz = (oz + dz * t - positions[p, 2]) / radius
            lambert = max(nx * light[0] + ny * light[1] + nz * light[2], 0.0)
            if shadowed[q]:
                lambert = 0.0
            if field.shape[1] == 1:
                v = float(field[p, 0])
            else:
                acc = 0.0
                for c in range(field.shape[1]):
                    acc += float(field[p, c]) * float(field[p, c])
                v = math.sqrt(acc)
            if math.isnan(v):
                r, g, b = nan_rgb[0], nan_rgb[1], nan_rgb[2]
            else:
                k = int(min(max((v - vmin) * scale + 0.5, 0.0), lut.shape[0] - 1))
                r, g, b = lut[k, 0], lut[k, 1], lut[k, 2]
            shade = AMBIENT + DIFFUSE * lambert
            out[q, 0] = np.uint8(min(max(r * shade, 0.0), 1.0) * 255.0 + 0.5)
            out[q, 1] = np.uint8(min(max(g * shade, 0.0), 1.0) * 255.0 + 0.5)
            out[q, 2] = np.uint8(min(max(b * shade, 0.0), 1.0) * 255.0 + 0.5)


def _shadow_mask(scene: Scene, view: View, t: np.ndarray, ids: np.ndarray,
                 light: np.ndarray) -> np.ndarray:
    """True where a lit hit point's shadow ray toward the key light meets another sphere."""
    if scene.grids is None:
        raise ValueError("shadows need the bricks' grids: prepare(..., grids=True)")
    mask = np.zeros(len(ids), np.bool_)
    hit = np.flatnonzero(ids >= 0)
    if hit.size == 0:
        return mask
    origins, dirs = primary_rays(view.camera, view.width, view.height)
    hp = origins[hit] + dirs[hit] * t[hit, None]
    normals = (hp - scene.positions[ids[hit]]) / scene.radius
    facing = normals @ light > 0
    start = hp[facing] + normals[facing] * (SHADOW_OFFSET_RADII * scene.radius)
    _, blocker = trace(start, np.broadcast_to(light, start.shape), scene.positions, scene.radius,
                       scene.bricks, scene.grids)
    mask[hit[facing]] = blocker >= 0
    return mask


class Canvas:
    """Per-pixel buffers of one image size, reused frame after frame (no page faults)."""

    def __init__(self, width: int, height: int):
        self.size = (width, height)
        self.hit_t = np.full(width * height, np.inf)  # hit distance or depth, m
        self.hit_id = np.full(width * height, -1, np.int32)  # particle index, -1: none
        self.clear = True  # hit buffers hold inf / -1 everywhere
        self.rgb = np.empty((width * height, 3), np.uint8)
        self.unshadowed = np.zeros(width * height, np.bool_)  # stays all False
        self.hit = np.zeros(width * height, np.bool_)  # the last render: particle at pixel


@njit(parallel=True, cache=True, nogil=True)
def _capture(hit_t, hit_id, keys, height, width, depth, key):
    """Copy the hit depths and the winning particles' keys (index when keys is empty;
    NO_KEY where nothing is hit) before shading clears the hit buffers."""
    for j in prange(height):
        for q in range(j * width, (j + 1) * width):
            p = hit_id[q]
            depth[q] = hit_t[q]
            key[q] = NO_KEY if p < 0 else (keys[p] if keys.shape[0] else p)


def render(scene: Scene, field: np.ndarray, view: View, shadows: bool = False,
           canvas: Canvas | None = None, keys: np.ndarray | None = None,
           depth: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The image [height, width, 3] uint8 of `view` (a view of the canvas's buffer, valid until
    the canvas renders again): spheres colored by `field` ([n] values,
    or [n, k] vectors by magnitude, computed only for visible particles) with the
    view's colormap and range, Lambert + ambient shading, optional shadows.

    For sort-last compositing (render_server.composite): keys [n] int64 break ties at equal
    depth (lowest key wins; default the particle index), and `depth`, a pair of buffers
    (float64 [h * w], int64 [h * w]), receives each pixel's hit depth (m along the view
    direction, inf where nothing is hit) and its particle's key (NO_KEY where none)."""
    if depth is not None and shadows:
        raise ValueError("depth capture is for compositing, which does not draw shadows")
    frame = ray_frame(view.camera, view.width, view.height)
    box = np.array([scene.bricks.boxes[:, 0].min(axis=0), scene.bricks.boxes[:, 1].max(axis=0)])
    if canvas is None or canvas.size != (view.width, view.height):
        canvas = Canvas(view.width, view.height)
    clear, canvas.clear = canvas.clear, False  # until shading has cleared them again
    t, ids = cast(scene.positions, scene.radius, frame, view.width, view.height, box,
                  metres=shadows,  # shadow rays start from metric hit points
                  out=(canvas.hit_t, canvas.hit_id), out_clear=clear, keys=keys)
    if depth is not None:
        _capture(t, ids, NO_KEYS if keys is None else keys, view.height, view.width, *depth)
    light = key_light(view)
    shadowed = _shadow_mask(scene, view, t, ids, light) if shadows else canvas.unshadowed
    cmap = view_colormap(view.colormap)
    out = canvas.rgb
    background = (np.clip(np.asarray(view.background), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    _shade(frame, view.width, view.height, t, ids, shadows, scene.positions, scene.radius,
           field_columns(field), cmap.lut(), float(view.range[0]),
           float(view.range[1]), np.asarray(cmap.nan_color, np.float64), light, shadowed,
           background, out, canvas.hit)
    canvas.clear = True
    return out.reshape(view.height, view.width, 3)


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
    scene = prepare(positions, radius, grids=shadows)
    t1 = time.perf_counter()
    images = {}
    for view in views:
        if view.field not in fields:
            raise KeyError(f"view {view.name!r} needs field {view.field!r}; the step has "
                           f"{sorted(fields)}")
        images[view.name] = render(scene, fields[view.field], view, shadows)
    return images, RenderTimes(t1 - t0, time.perf_counter() - t1)
