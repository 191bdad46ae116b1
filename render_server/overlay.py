"""Annotations drawn over a view's frame: a colorbar with the field's name, unit and range,
the simulated time and step, the domain's floor and channel walls as light context lines,
and the domain's bounding box (`protocol.view.Annotations` says which).

All of it but the time text depends only on the view (camera, size, background, field,
colormap, range, annotations) and the domain, so it is composed once per distinct key by an
`OverlayCache` into sparse layers (flat pixel indices and their colours), and a frame is
annotated by writing only those pixels:

- context (floor, walls, bounding box): written where no particle covers the pixel (the
  renderer's hit mask), so particles hide it; those pixels hold the background colour, so
  the lines' antialiased colours are blended with it once, at composition;
- legend (colorbar, its title and tick labels): blended over everything, premultiplied
  colour and coverage; text has a halo in the background colour, readable over particles;
- time text: laid out per frame from glyph bitmaps rendered once per font size
  (`render_server/glyphs.py`, which also holds the font and its sizes).

Applying is a few numba loops over those pixels: well under a millisecond a frame.

Geometry: the domain is the box (lo, hi) in m the chunks carry; the floor is z = lo[2], the
channel walls the planes y = lo[1] and y = hi[1]. A face seen from inside the box gets a
grid; every face gets its outline. Images smaller than MIN_TEXT_SIDE px on a side get no
text or colorbar (there is no room); elements are placed at the image's top corners.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numba import njit
from PIL import Image, ImageDraw

from minority.protocol.fields import colour_label
from minority.protocol.projection import camera_basis, camera_coordinates, to_pixels
from minority.protocol.view import View
from minority.render_server.colormap import view_colormap
from minority.render_server.glyphs import (
    TimeText,
    draw_time,
    font,
    font_px,
    glyphs,
    halo_px,
    tick_text,
    time_label,
)

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]  # (lo, hi) corners, m

MIN_TEXT_SIDE = 96  # px: a smaller image gets no text nor colorbar
GRID_LINES = 10  # about this many grid lines across the domain's longest side
# coverage of the context lines drawn on the background (ink: black on a light background)
GRID_ALPHA, EDGE_ALPHA, BBOX_ALPHA = 0.16, 0.32, 0.55
LINE_PX_HEIGHT = 768  # lines are 1 px wide up to this image height, 2 px to twice it, ...
SUPERSAMPLE = 2  # context lines are drawn at this scale and averaged down (antialiasing)
SUPERSAMPLE_MAX_PIXELS = 1 << 22  # larger images are drawn at scale 1
NEAR_FRACTION = 1e-3  # perspective: lines are clipped this far in front of the camera,
# as a fraction of the focal distance
TEXT_INK_DARK, TEXT_INK_LIGHT = (0.08, 0.08, 0.08), (0.95, 0.95, 0.95)  # on light / dark


@dataclass(frozen=True)
class Layer:
    """Pixels of an overlay layer: flat indices y * width + x [k] int64 and colours."""

    index: np.ndarray  # [k] int64
    rgb: np.ndarray  # [k, 3]: uint8 final colours (context), float32 premultiplied (legend)
    alpha: np.ndarray | None = None  # [k] float32 coverage in [0, 1] (legend); None: opaque

    @staticmethod
    def empty() -> Layer:
        return Layer(np.zeros(0, np.int64), np.zeros((0, 3), np.uint8))


@dataclass(frozen=True)
class Overlay:
    """A view's composed annotations, for images of width x height px."""

    width: int
    height: int
    context: Layer  # where no particle is hit
    legend: Layer  # over everything
    time: TimeText | None


def _luminance(rgb) -> float:
    return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]


def _inks(view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background, line ink and text ink as float64 [3] in [0, 255]."""
    bg = np.clip(np.asarray(view.background, np.float64), 0.0, 1.0)
    light = _luminance(bg) > 0.5
    line = np.zeros(3) if light else np.ones(3)
    text = np.asarray(TEXT_INK_DARK if light else TEXT_INK_LIGHT)
    # the renderer's background is round(bg * 255): blend with exactly what is there
    return np.floor(bg * 255.0 + 0.5), line * 255.0, text * 255.0


# --- context: the domain's floor, walls and box as lines -------------------------------


def _grid_step(extent_m: float) -> float:
    """A round grid spacing (1, 2 or 5 x 10^k m) giving about GRID_LINES lines over extent_m."""
    raw = extent_m / GRID_LINES
    power = 10.0 ** math.floor(math.log10(raw))
    return next(s * power for s in (1.0, 2.0, 5.0, 10.0) if s * power >= raw * 0.999)


def _ticks(lo: float, hi: float, step: float) -> np.ndarray:
    """Multiples of step strictly inside (lo, hi)."""
    k = np.arange(math.floor(lo / step) + 1, math.ceil(hi / step))
    t = k * step
    return t[(t > lo + 1e-9 * step) & (t < hi - 1e-9 * step)]


def _face(axis: int, level: float, lo: np.ndarray, hi: np.ndarray, step: float,
          grid: bool) -> tuple[list, list]:
    """The outline segments and (with `grid`) grid segments of the box face at coordinate
    `level` of `axis`, each segment [2, 3] m."""
    a, b = [i for i in range(3) if i != axis]
    corners = []
    for ua, ub in ((lo[a], lo[b]), (hi[a], lo[b]), (hi[a], hi[b]), (lo[a], hi[b])):
        p = np.empty(3)
        p[axis], p[a], p[b] = level, ua, ub
        corners.append(p)
    edges = [np.array([corners[i], corners[(i + 1) % 4]]) for i in range(4)]
    lines = []
    if grid:
        for i, j in ((a, b), (b, a)):
            for t in _ticks(lo[i], hi[i], step):
                p, q = np.empty(3), np.empty(3)
                p[axis] = q[axis] = level
                p[i] = q[i] = t
                p[j], q[j] = lo[j], hi[j]
                lines.append(np.array([p, q]))
    return edges, lines


def _sees_inside(view: View, axis: int, level: float, inward: float) -> bool:
    """Whether the camera sees the face at `level` of `axis` from inside the box (the
    face's inward normal along axis has sign `inward`)."""
    cam = view.camera
    if cam.parallel_projection:
        toward = -(np.asarray(cam.focal_point) - np.asarray(cam.position))[axis]
    else:
        toward = cam.position[axis] - level
    return toward * inward > 0.0


def context_segments(view: View, bounds: Bounds) -> list[tuple[np.ndarray, float]]:
    """The context lines of `view` in the domain `bounds`: (segments [k, 2, 3] m, coverage)
    for the faces' grids, their outlines, then the bounding box, as the view's annotations
    ask."""
    lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
    notes = view.annotations
    out = []
    if notes.context:
        step = _grid_step(float(np.max(hi - lo)) or 1.0)
        grids, edges = [], []
        # floor z = lo (inward +z), channel walls y = lo (inward +y) and y = hi (inward -y)
        for axis, level, inward in ((2, lo[2], 1.0), (1, lo[1], 1.0), (1, hi[1], -1.0)):
            e, g = _face(axis, level, lo, hi, step, _sees_inside(view, axis, level, inward))
            edges += e
            grids += g
        out += [(np.array(grids).reshape(-1, 2, 3), GRID_ALPHA),
                (np.array(edges).reshape(-1, 2, 3), EDGE_ALPHA)]
    if notes.bbox:  # the outlines of the bottom and top faces, and the 4 edges between
        box = _face(2, lo[2], lo, hi, 1.0, False)[0] + _face(2, hi[2], lo, hi, 1.0, False)[0]
        box += [np.array([e[0], e[0]]) for e in box[:4]]
        for e in box[8:]:
            e[1, 2] = hi[2]
        out.append((np.array(box), BBOX_ALPHA))
    return out


def project_segments(segments: np.ndarray, view: View) -> np.ndarray:
    """Segments [k, 2, 3] (m) as pixel segments [k', 2, 2] (px, x right, y down), clipped
    to the part in front of the camera (perspective) and to the image."""
    if len(segments) == 0:
        return np.zeros((0, 2, 2))
    basis = camera_basis(view.camera)
    u, v, d = camera_coordinates(segments.reshape(-1, 3), basis)
    u, v, d = (c.reshape(-1, 2) for c in (u, v, d))
    if not view.camera.parallel_projection:
        near = NEAR_FRACTION * basis.distance
        keep = (d > near).any(axis=1)
        u, v, d = u[keep], v[keep], d[keep]
        # move an end behind the near plane onto it, along the segment
        for e in (0, 1):
            o = 1 - e
            behind = d[:, e] <= near
            s = (near - d[behind, o]) / (d[behind, e] - d[behind, o])
            for c in (u, v):
                c[behind, e] = c[behind, o] + s * (c[behind, e] - c[behind, o])
            d[behind, e] = near
    x, y = to_pixels(u, v, d, view.camera, view.width, view.height)
    return _clip_to_box(np.stack([x, y], axis=2), view.width, view.height)


def _clip_to_box(seg: np.ndarray, width: int, height: int) -> np.ndarray:
    """Liang-Barsky: segments [k, 2, 2] (px) clipped to [-1, width + 1] x [-1, height + 1];
    those wholly outside are dropped."""
    p0, delta = seg[:, 0], seg[:, 1] - seg[:, 0]
    t0, t1 = np.zeros(len(seg)), np.ones(len(seg))
    for axis, top in ((0, width + 1.0), (1, height + 1.0)):
        for p, q in ((-delta[:, axis], p0[:, axis] + 1.0), (delta[:, axis], top - p0[:, axis])):
            with np.errstate(divide="ignore", invalid="ignore"):
                r = q / p
            parallel = p == 0.0
            t1 = np.where(parallel & (q < 0), -1.0, t1)  # parallel and outside: dropped
            t0 = np.where(~parallel & (p < 0), np.maximum(t0, r), t0)
            t1 = np.where(~parallel & (p > 0), np.minimum(t1, r), t1)
    keep = t0 <= t1
    return np.stack([p0 + t0[:, None] * delta, p0 + t1[:, None] * delta], axis=1)[keep]


def compose_context(view: View, bounds: Bounds) -> Layer:
    """The context layer: antialiased lines, blended with the background colour."""
    lines = context_segments(view, bounds)
    if not lines:
        return Layer.empty()
    w, h = view.width, view.height
    scale = SUPERSAMPLE if w * h * SUPERSAMPLE ** 2 <= SUPERSAMPLE_MAX_PIXELS * 4 else 1
    thick = max(1, round(h / LINE_PX_HEIGHT))  # line width, px
    mask = Image.new("L", (w * scale, h * scale), 0)
    draw = ImageDraw.Draw(mask)
    for segments, alpha in lines:  # later (stronger) lines overwrite earlier ones
        for (x0, y0), (x1, y1) in project_segments(segments, view):
            # Pillow's integer coordinates are pixel centres, ours pixel corners
            draw.line([(x0 * scale - 0.5, y0 * scale - 0.5), (x1 * scale - 0.5, y1 * scale - 0.5)],
                      fill=round(alpha * 255), width=thick * scale)
    if scale > 1:
        mask = mask.reduce(scale)
    cover = np.asarray(mask).reshape(-1)
    index = np.flatnonzero(cover).astype(np.int64)
    a = cover[index, None].astype(np.float64) / 255.0
    bg, ink, _ = _inks(view)
    rgb = np.floor(bg * (1.0 - a) + ink * a + 0.5).astype(np.uint8)
    return Layer(index, rgb)


# --- legend: colorbar, title, tick labels --------------------------------------------


def compose_legend(view: View) -> Layer:
    """The colorbar at the top right: title (field, unit), the view's colormap from its
    range's low (bottom) to high (top) end, ticks at both ends and the middle."""
    w, h = view.width, view.height
    size = font_px(h)
    f = font(size)
    margin, bar_w = size, size
    bar_h = max(3 * size, round(0.35 * h))
    title = colour_label(view.field)
    lo, hi = view.range
    labels = [(tick_text(v), frac) for v, frac in ((hi, 0.0), ((lo + hi) / 2, 0.5), (lo, 1.0))]
    tick = max(2, size // 3)
    label_w = max(f.getlength(t) for t, _ in labels)
    title_w = f.getlength(title)
    ascent, descent = f.getmetrics()
    box_w = math.ceil(max(title_w, label_w + tick + size // 2 + bar_w)) + 2 * halo_px(size) + 2
    box_h = ascent + descent + size + bar_h + (ascent + descent) // 2 + 2
    if box_w + 2 * margin > w or box_h + 2 * margin > h:
        return Layer.empty()  # it does not fit
    # drawn on the legend's corner of the image only: columns from ox on, rows above oh
    ox, oh = max(0, w - margin - box_w - margin), min(h, box_h + 2 * margin)
    x_right, y_top = w - margin - ox, margin
    bar_x0, bar_y0 = x_right - bar_w, y_top + ascent + descent + size
    # RGBA on transparent: Pillow leaves straight (not premultiplied) colour and coverage
    canvas = Image.new("RGBA", (w - ox, oh), (0, 0, 0, 0))
    draw = ImageDraw.Draw(canvas)
    bg, line, text_ink = _inks(view)
    ink = tuple(int(c) for c in text_ink) + (255,)
    halo = tuple(int(c) for c in bg) + (255,)
    stroke = halo_px(size)
    draw.text((x_right, y_top), title, font=f, fill=ink, anchor="ra", stroke_width=stroke,
              stroke_fill=halo)
    for text, frac in labels:
        y = bar_y0 + frac * (bar_h - 1)
        draw.line([(bar_x0 - tick, y), (bar_x0 - 1, y)], fill=ink, width=1)
        draw.text((bar_x0 - tick - size // 4, y), text, font=f, fill=ink, anchor="rm",
                  stroke_width=stroke, stroke_fill=halo)
    rgba = np.array(canvas)  # [oh, w - ox, 4] uint8
    # the bar: row r (0 at the top) shows the value at (r + 0.5) / bar_h from the high end,
    # looked up in the colormap as the renderer's shading does
    lut = view_colormap(view.colormap).lut()
    frac = 1.0 - (np.arange(bar_h) + 0.5) / bar_h
    colours = lut[np.minimum((frac * (len(lut) - 1) + 0.5).astype(np.int64), len(lut) - 1)]
    rgba[bar_y0:bar_y0 + bar_h, bar_x0:bar_x0 + bar_w, :3] = np.floor(
        colours[:, None, :] * 255.0 + 0.5).astype(np.uint8)
    rgba[bar_y0:bar_y0 + bar_h, bar_x0:bar_x0 + bar_w, 3] = 255
    # a thin frame around the bar, in the line ink
    edge = np.floor(bg * 0.4 + line * 0.6 + 0.5).astype(np.uint8)
    for sl in ((slice(bar_y0 - 1, bar_y0), slice(bar_x0 - 1, bar_x0 + bar_w + 1)),
               (slice(bar_y0 + bar_h, bar_y0 + bar_h + 1), slice(bar_x0 - 1, bar_x0 + bar_w + 1)),
               (slice(bar_y0, bar_y0 + bar_h), slice(bar_x0 - 1, bar_x0)),
               (slice(bar_y0, bar_y0 + bar_h), slice(bar_x0 + bar_w, bar_x0 + bar_w + 1))):
        rgba[sl[0], sl[1], :3] = edge
        rgba[sl[0], sl[1], 3] = 255
    rows, cols = np.nonzero(rgba[:, :, 3])
    alpha = rgba[rows, cols, 3].astype(np.float32) / 255.0
    return Layer(rows.astype(np.int64) * w + cols + ox,
                 rgba[rows, cols, :3].astype(np.float32) * alpha[:, None], alpha)


@njit(cache=True, nogil=True)
def _write_free(flat, index, rgb, hit):
    """flat[index[k]] = rgb[k] where hit[index[k]] is False (hit empty: everywhere)."""
    check = hit.shape[0] > 0
    for k in range(index.shape[0]):
        q = index[k]
        if check and hit[q]:
            continue
        flat[q, 0], flat[q, 1], flat[q, 2] = rgb[k, 0], rgb[k, 1], rgb[k, 2]


@njit(cache=True, nogil=True)
def _blend(flat, index, premultiplied, alpha):
    """flat[index] = flat[index] * (1 - alpha) + premultiplied, uint8 [k, 3] in place."""
    for k in range(index.shape[0]):
        q, a = index[k], alpha[k]
        for c in range(3):
            flat[q, c] = np.uint8(flat[q, c] * (1.0 - a) + premultiplied[k, c] + 0.5)


# --- composition, cache, application -------------------------------------------------


def overlay_key(view: View, bounds: Bounds | None) -> tuple:
    """What a view's overlay depends on (and nothing else: not its name nor schedule)."""
    return (view.camera, view.width, view.height, tuple(view.background), view.field,
            view.colormap, tuple(view.range), view.annotations,
            None if bounds is None else (tuple(map(float, bounds[0])),
                                         tuple(map(float, bounds[1]))))


def compose(view: View, bounds: Bounds | None) -> Overlay:
    """The overlay of `view` over the domain `bounds` (None: unknown, no context drawn)."""
    notes = view.annotations
    roomy = min(view.width, view.height) >= MIN_TEXT_SIDE
    context = (compose_context(view, bounds)
               if bounds is not None and (notes.context or notes.bbox) else Layer.empty())
    legend = compose_legend(view) if notes.colorbar and roomy else Layer.empty()
    time = None
    if notes.time and roomy:
        size = font_px(view.height)
        bg, _, ink = _inks(view)
        pad = glyphs(size).pad
        time = TimeText(size - pad, size - pad, size, ink.astype(np.float32),
                        bg.astype(np.float32))
    return Overlay(view.width, view.height, context, legend, time)


class OverlayCache:
    """Composed overlays by `overlay_key`, the least recently used dropped past `size`;
    `composed` counts compositions. Thread-safe."""

    def __init__(self, size: int = 64):
        self.size = size
        self.composed = 0
        self._items: OrderedDict[tuple, Overlay] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, view: View, bounds: Bounds | None) -> Overlay:
        key = overlay_key(view, bounds)
        with self._lock:
            found = self._items.get(key)
            if found is not None:
                self._items.move_to_end(key)
                return found
        made = compose(view, bounds)
        with self._lock:
            self.composed += 1
            self._items[key] = made
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return made


OVERLAYS = OverlayCache()  # the process's overlays (daemon, replay and preview share it)


NO_HIT = np.zeros(0, np.bool_)


def apply(overlay: Overlay, image: np.ndarray, hit: np.ndarray | None, step: int,
          time_s: float) -> None:
    """Annotate image [height, width, 3] uint8 (C-contiguous) in place: context where
    hit [height * width] bool is False (None: no particle anywhere), the legend over it,
    the time text of sim step `step` at `time_s` (s)."""
    if image.shape != (overlay.height, overlay.width, 3) or not image.flags.c_contiguous:
        raise ValueError(f"overlay of {overlay.width}x{overlay.height} px applied to an image "
                         f"of shape {image.shape}")
    flat = image.reshape(-1, 3)
    ctx = overlay.context
    if len(ctx.index):
        _write_free(flat, ctx.index, ctx.rgb, NO_HIT if hit is None else hit)
    legend = overlay.legend
    if len(legend.index):
        _blend(flat, legend.index, legend.rgb, legend.alpha)
    if overlay.time is not None:
        draw_time(image, overlay.time, time_label(step, time_s))
