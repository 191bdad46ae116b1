"""Render the due views of one assembled step: the one function the daemon and an offline
replay share, so both make pixel-identical frames from the same inputs.

Each view shows the particles inside the regions of its window at the step (every particle
when the window names none) and, with `decimate` k > 1, only those with id % k == 0 when the
step carries an `id` field (without one, the simulation already decimated by the request's
stride, so what arrived is drawn). The acceleration structure is built once per distinct
particle subset of the step, not once per view; its setup time is charged to every view
that uses it. A view whose subset is empty shows the background. Each image is annotated
(render_server.overlay: colorbar, time and step, the domain's floor and walls) as its view's
`annotations` ask, before it is encoded.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from minority.protocol.errors import SpecError
from minority.protocol.spec import ID_FIELD, Region, Spec, View, inside_mask, render_radius_m
from minority.protocol.view import NO_ANNOTATIONS
from minority.render_server.colormap import view_colormap
from minority.render_server.overlay import OVERLAYS, apply
from minority.render_server.render import Canvas, Scene, encode_png, prepare, render

# (regions or None for every particle, id stride or 1): what picks a view's particles
SubsetKey = tuple[tuple[Region, ...] | None, int]


class StepLike(Protocol):
    """What rendering needs of a step (render_server.assemble.AssembledStep has it)."""

    step: int
    time_s: float  # simulated time, s
    prev_time_s: float | None  # simulated time of the step before, s (None: unknown)
    positions: np.ndarray  # [n, 3] float32, m
    fields: dict[str, np.ndarray]  # [n] or [n, k]
    spacing_m: float  # particle spacing, m
    # (optional, absent: False) True when the step holds every particle, those outside the
    # regions from the server's cache: a view then draws them all, not only its regions
    completed: bool
    # (optional, absent: None) the simulation's domain, (lo, hi) corners in m: the floor and
    # walls the annotations draw (render_server.overlay); None: unknown, not drawn
    bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None


@dataclass
class RenderedView:
    """One view of one step: its image and PNG, or why it could not be rendered."""

    view: View
    image: np.ndarray | None  # [height, width, 3] uint8 (the view's canvas buffer: valid
    # until that canvas renders again); None when `error` says why not
    png: bytes
    setup_s: float  # picking the view's particles and building their acceleration structure, s
    render_s: float  # image synthesis and annotation, s (PNG encoding excluded)
    particles: int  # particles the view shows
    error: str = ""


@dataclass
class _Subset:
    index: np.ndarray | None  # [m] int64 rows of the step, None: every row
    scene: Scene | None  # None: no particle to draw
    setup_s: float


def subset_key(spec: Spec, view: View, step: StepLike) -> SubsetKey:
    """The particle subset `view` shows at `step` (the view must be due)."""
    regions = (None if getattr(step, "completed", False)
               else spec.view_regions(view, step.step, step.time_s, step.prev_time_s))
    stride = view.decimate if view.decimate > 1 and ID_FIELD in step.fields else 1
    return regions, stride


def select(step: StepLike, key: SubsetKey) -> np.ndarray | None:
    """Rows of the step in the subset, in step order; None for every row."""
    regions, stride = key
    if regions is None and stride == 1:
        return None
    keep = np.ones(len(step.positions), dtype=bool)
    if regions is not None:
        keep &= inside_mask(step.positions, regions)
    if stride > 1:
        keep &= step.fields[ID_FIELD].reshape(-1) % stride == 0
    return np.flatnonzero(keep)


def background(view: View) -> np.ndarray:
    """The image [height, width, 3] uint8 of a view with nothing in it."""
    rgb = (np.clip(np.asarray(view.background), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return np.broadcast_to(rgb, (view.height, view.width, 3)).copy()


def cannot_render(view: View, step: StepLike) -> str:
    """Why `view` cannot be rendered from `step` (a missing field, an unknown colormap
    preset), or "" when it can."""
    if view.field not in step.fields:
        return (f"view {view.name!r} needs field {view.field!r}; step {step.step} has "
                f"{sorted(step.fields)}")
    try:
        view_colormap(view.colormap)
    except SpecError as exc:
        return f"view {view.name!r}: {exc}"
    return ""


def render_views(step: StepLike, spec: Spec, canvases: dict[str, Canvas],
                 shadows: bool = False, views: list[View] | None = None) -> list[RenderedView]:
    """Render the views of `spec` due at `step` (or `views`, each due at the step), reusing
    and filling `canvases` (per view name). A due view of a step without particles (the sim
    sends empty chunks when nothing is in the regions) renders its background."""
    if views is None:
        views = spec.wants(step.step, step.time_s, step.prev_time_s)
    if not views:
        return []
    radius = render_radius_m(spec, step.spacing_m)
    subsets: dict[SubsetKey, _Subset] = {}
    out = []
    for view in views:
        error = cannot_render(view, step)
        if error:
            out.append(RenderedView(view, None, b"", 0.0, 0.0, 0, error))
            continue
        key = subset_key(spec, view, step)
        sub = subsets.get(key)
        if sub is None:
            t0 = time.perf_counter()
            index = select(step, key)
            pos = step.positions if index is None else step.positions[index]
            scene = prepare(pos, radius, grids=shadows) if len(pos) else None
            sub = subsets[key] = _Subset(index, scene, time.perf_counter() - t0)
        canvas = canvases.get(view.name)
        if canvas is None or canvas.size != (view.width, view.height):
            canvas = canvases[view.name] = Canvas(view.width, view.height)
        t1 = time.perf_counter()
        if sub.scene is None:
            image, count, hit = background(view), 0, None
        else:
            values = step.fields[view.field]
            values = values if sub.index is None else values[sub.index]
            image, count = render(sub.scene, values, view, shadows, canvas), len(values)
            hit = canvas.hit  # the pixels a particle covers, from the render just done
        if view.annotations != NO_ANNOTATIONS:
            overlay = OVERLAYS.get(view, getattr(step, "bounds_m", None))
            apply(overlay, image, hit, step.step, step.time_s)
        render_s = time.perf_counter() - t1
        out.append(RenderedView(view, image, encode_png(image), sub.setup_s, render_s, count))
    return out
