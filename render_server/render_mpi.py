"""Render one step on N MPI ranks, composited into frames pixel-identical to one process.

Per step, every rank (collectively): agrees with the others on count-balanced k-d bricks and
exchanges particles so it holds one brick (render_server.distribute; only the fields the due
views need), builds its acceleration structure per distinct particle subset (regions,
decimation: render_server.frames' rules), ray-casts each view into colour, depth and key
(render_server.render), and the ranks composite by depth into rank 0's frame
(render_server.composite), which rank 0 annotates and encodes as render_views does.

Pixel identity with the one-process render of the same particles holds because a pixel's
colour depends only on its winning particle (its depth, its field value, the view's
colormap and light), every rank computes depths with the same arithmetic, and ties at equal
depth go to the lowest key on every rank and in the composite, where the key of a particle is
its row in the one-process step (default: rank 0's rows first, then rank 1's, ...).

Shadows are refused on more than one rank: a shadow ray toward the key light crosses the
whole domain, so it would need either every rank's particles on each rank or the shadow
rays' origins sent to every rank and their hits reduced back (see SHADOWS_REFUSED).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from minority.protocol.spec import ID_FIELD, Spec, View, render_radius_m
from minority.protocol.view import NO_ANNOTATIONS
from minority.render_server.composite import composite
from minority.render_server.distribute import Partition, Pool, exchange
from minority.render_server.frames import (
    RenderedView,
    StepLike,
    SubsetKey,
    background,
    cannot_render,
    select,
    subset_key,
)
from minority.render_server.overlay import OVERLAYS, apply
from minority.render_server.render import NO_KEY, Canvas, Scene, encode_png, prepare, render

SHADOWS_REFUSED = (
    "shadows are not drawn on more than one render rank: a shadow ray toward the key light "
    "crosses every rank's bricks, so each rank would need the whole step; render with "
    "shadows on one rank, or without shadows on several")


@dataclass
class PhaseTimes:
    """This rank's wall times of one distributed step, s."""

    exchange_s: float = 0.0  # sample, tree, classification and Alltoallv of the particles
    setup_s: float = 0.0  # subsets and acceleration structures
    render_s: float = 0.0  # ray casting and shading of the layers, until every rank has its
    composite_s: float = 0.0  # depth compositing and the gather to rank 0
    annotate_s: float = 0.0  # rank 0: annotations and PNG encoding
    total_s: float = 0.0
    counts: list[int] = field(default_factory=list)  # particles each rank held after exchange


@dataclass
class _LocalStep:
    """This rank's brick of the step, shaped as frames.StepLike for subset selection."""

    step: int
    time_s: float
    prev_time_s: float | None
    positions: np.ndarray
    fields: dict[str, np.ndarray]
    spacing_m: float
    completed: bool
    bounds_m: tuple | None


class Layers:
    """Per-view depth and key buffers of one image size, and the exchange's buffers (pool),
    reused step after step."""

    def __init__(self):
        self.buffers: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.pool = Pool()

    def get(self, view: View) -> tuple[np.ndarray, np.ndarray]:
        size = view.width * view.height
        pair = self.buffers.get(view.name)
        if pair is None or len(pair[0]) != size:
            pair = self.buffers[view.name] = (np.empty(size), np.empty(size, np.int64))
        return pair


def _draw(scene: Scene | None, values: np.ndarray | None, keys: np.ndarray | None, view: View,
          canvas: Canvas, layers: Layers) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """This rank's layer of `view`: colour [h, w, 3] uint8, depth [h * w] float64 (m along
    the view direction, inf: nothing) and key [h * w] int64 of each pixel's particle."""
    depth, key = layers.get(view)
    if scene is None:  # nothing of this subset here: background, nothing hit
        depth.fill(np.inf)
        key.fill(NO_KEY)
        return background(view), depth, key
    return render(scene, values, view, False, canvas, keys=keys, depth=(depth, key)), depth, key


def _canvas(canvases: dict[str, Canvas], view: View) -> Canvas:
    canvas = canvases.get(view.name)
    if canvas is None or canvas.size != (view.width, view.height):
        canvas = canvases[view.name] = Canvas(view.width, view.height)
    return canvas


def render_views_distributed(comm, step: StepLike, spec: Spec, canvases: dict[str, Canvas],
                             keys: np.ndarray | None = None, views: list[View] | None = None,
                             shadows: bool = False, layers: Layers | None = None
                             ) -> tuple[list[RenderedView], PhaseTimes]:
    """render_server.frames.render_views on N ranks (collective): `step` holds this rank's
    share of the step's particles (positions [n, 3] m, fields [n] or [n, k]; the same field
    names, spec and step metadata on every rank), keys [n] int64 their rows in the
    one-process step (default: rank order). Returns rank 0's RenderedViews, pixel-identical
    to render_views on the concatenated step ([] on the other ranks), and this rank's
    phase times. Setup and render times of a view are this rank's own. `canvases` and
    `layers` (per view name) are reused from step to step."""
    if shadows and comm.size > 1:
        raise ValueError(SHADOWS_REFUSED)
    layers = Layers() if layers is None else layers
    t0 = time.perf_counter()
    times = PhaseTimes()
    names = sorted(step.fields)
    every = comm.allgather(names)
    if any(other != names for other in every):  # else ranks would disagree on what to draw
        raise ValueError(f"ranks hold different fields for step {step.step}: {every}")
    if views is None:
        views = spec.wants(step.step, step.time_s, step.prev_time_s)
    errors = {v.name: cannot_render(v, step) for v in views}
    drawable = [v for v in views if not errors[v.name]]
    needed = {v.field for v in drawable}
    if any(v.decimate > 1 for v in drawable) and ID_FIELD in step.fields:
        needed.add(ID_FIELD)
    radius = render_radius_m(spec, step.spacing_m)
    part: Partition | None = None
    if drawable:
        part = exchange(comm, step.positions, {k: step.fields[k] for k in sorted(needed)}, keys,
                        pool=layers.pool)
        times.exchange_s = part.sample_s + part.exchange_s
        times.counts = part.counts.tolist()
        local = _LocalStep(step.step, step.time_s, step.prev_time_s, part.positions, part.fields,
                           step.spacing_m, getattr(step, "completed", False),
                           getattr(step, "bounds_m", None))
    # per distinct subset: local rows, scene, keys, and how many particles all ranks hold
    subsets: dict[SubsetKey, list] = {}
    for view in drawable:
        key = subset_key(spec, view, local)
        if key not in subsets:
            t1 = time.perf_counter()
            index = select(local, key)
            pos = local.positions if index is None else local.positions[index]
            sub_keys = part.keys if index is None else part.keys[index]
            scene = prepare(pos, radius, grids=False) if len(pos) else None
            subsets[key] = [index, scene, sub_keys, len(pos), time.perf_counter() - t1]
    if subsets:  # one reduction for every subset's global count
        from mpi4py import MPI

        totals = np.array([s[3] for s in subsets.values()], np.int64)
        comm.Allreduce(MPI.IN_PLACE, totals, op=MPI.SUM)
        for sub, total in zip(subsets.values(), totals, strict=True):
            sub[3] = int(total)
    times.setup_s = sum(s[4] for s in subsets.values())
    out = []
    for view in views:
        if errors[view.name]:
            out.append(RenderedView(view, None, b"", 0.0, 0.0, 0, errors[view.name]))
            continue
        index, scene, sub_keys, total, setup_s = subsets[subset_key(spec, view, local)]
        t1 = time.perf_counter()
        if total == 0:  # nothing on any rank: every rank skips the composite
            image, hit = (background(view) if comm.rank == 0 else None), None
        else:
            values = None
            if scene is not None:
                values = local.fields[view.field]
                values = values if index is None else values[index]
            layer = _draw(scene, values, sub_keys, view, _canvas(canvases, view), layers)
            if comm.size > 1:
                comm.Barrier()  # waiting for the slowest rank's layer counts as rendering
            t2 = time.perf_counter()
            times.render_s += t2 - t1
            image, hit = composite(comm, *layer, pool=layers.pool) or (None, None)
            times.composite_s += time.perf_counter() - t2
        if comm.rank != 0:
            continue
        t3 = time.perf_counter()
        if view.annotations != NO_ANNOTATIONS:
            overlay = OVERLAYS.get(view, getattr(step, "bounds_m", None))
            apply(overlay, image, hit, step.step, step.time_s)
        render_s = time.perf_counter() - t1  # as render_views: annotation in, PNG out
        png = encode_png(image)
        times.annotate_s += time.perf_counter() - t3
        out.append(RenderedView(view, image, png, setup_s, render_s, total))
    times.total_s = time.perf_counter() - t0
    return (out if comm.rank == 0 else []), times


def render_step_distributed(comm, positions: np.ndarray, fields: dict[str, np.ndarray],
                            radius: float, views: list[View], keys: np.ndarray | None = None,
                            shadows: bool = False, canvases: dict[str, Canvas] | None = None,
                            layers: Layers | None = None
                            ) -> tuple[dict[str, np.ndarray], PhaseTimes]:
    """render_server.render.render_step on N ranks (collective): every view of one step,
    every particle, no annotations. positions [n, 3] m and fields [n] or [n, k] are this
    rank's share; spheres of `radius` m. Returns rank 0's images [h, w, 3] uint8 by view
    name, pixel-identical to render_step on the concatenation in rank order (or in `keys`
    order, keys [n] int64 each particle's row there), {} on other ranks, and the times."""
    if shadows and comm.size > 1:
        raise ValueError(SHADOWS_REFUSED)
    for view in views:
        if view.field not in fields:
            raise KeyError(f"view {view.name!r} needs field {view.field!r}; the step has "
                           f"{sorted(fields)}")
    canvases = {} if canvases is None else canvases
    layers = Layers() if layers is None else layers
    t0 = time.perf_counter()
    times = PhaseTimes()
    part = exchange(comm, positions, {k: fields[k] for k in sorted({v.field for v in views})},
                    keys, pool=layers.pool)
    times.exchange_s = part.sample_s + part.exchange_s
    times.counts = part.counts.tolist()
    t1 = time.perf_counter()
    scene = prepare(part.positions, radius, grids=False) if len(part.positions) else None
    times.setup_s = time.perf_counter() - t1
    images = {}
    for view in views:
        t2 = time.perf_counter()
        layer = _draw(scene, part.fields[view.field], part.keys, view, _canvas(canvases, view),
                      layers)
        if comm.size > 1:
            comm.Barrier()  # waiting for the slowest rank's layer counts as rendering
        t3 = time.perf_counter()
        done = composite(comm, *layer, pool=layers.pool)
        times.render_s += t3 - t2
        times.composite_s += time.perf_counter() - t3
        if done is not None:
            images[view.name] = done[0]
    times.total_s = time.perf_counter() - t0
    return images, times
