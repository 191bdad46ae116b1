"""Re-render a recorded run: the log's chunks assembled into steps as the daemon assembles
them, rendered by the daemon's own `frames.render_views`, with the log's spec or a new one.

A step is complete when it holds a chunk of every rank; what is missing at the end is
rendered and reported incomplete. The log's own spec gives pixel-identical frames. A new spec
may ask for what the log does not hold; such views are reported per view, with the steps,
and not rendered:
- a field the chunks do not carry;
- particles the simulation culled away: the view's regions at a step reach outside the
  regions the recorded spec requested at that step, or its decimation needs particles (or
  particle ids) that the recorded stride left out, or the recorded views were occlusion
  culled and none of them sees what this view sees (same camera, size, stride, regions);
- steps the new schedule wants that were never recorded (estimated from the recorded steps'
  numbers and times: step numbers for every_steps windows, instants for every_s windows).
"""

from __future__ import annotations

import itertools
import math
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from minority.protocol import keys
from minority.protocol.logread import LogNote, read_log_noting
from minority.protocol.runlog import RunLogError, log_run, log_specs
from minority.protocol.spec import ID_FIELD, Region, Spec, View
from minority.protocol.view import INSTANT_TOLERANCE
from minority.protocol.vtkseries import VtkSeries
from minority.render_server.assemble import AssembledStep, StepAssembler
from minority.render_server.frames import render_views
from minority.render_server.particles import ParticleCache, complete_step

Topic = keys.Topic
MAX_PENDING_STEPS = 64  # steps assembled at once; past that the oldest is released incomplete
SHOWN_STEPS = 8  # steps listed per reported problem
UNRECORDED = "the new schedule wants them and the log does not hold them"


@dataclass
class ViewReport:
    frames: int = 0
    problems: dict[str, list] = field(default_factory=lambda: defaultdict(list))  # why -> steps


@dataclass
class ReplaySummary:
    run: str
    spec_source: str  # "the log's spec" or "a given spec"
    steps: int = 0  # steps assembled from the log
    incomplete: list[tuple[int, int, int]] = field(default_factory=list)  # step, got, expected
    frames: int = 0
    views: dict[str, ViewReport] = field(default_factory=dict)
    unchecked: int = 0  # due steps the recorded spec did not schedule (culling not known)
    late: int = 0  # chunks of a step already released, or duplicates
    out: Path | None = None
    vtk: Path | None = None
    log_notes: list[LogNote] = field(default_factory=list)  # truncated or damaged: read so far

    def text(self) -> str:
        lines = [f"run {self.run}: {self.steps} steps replayed with {self.spec_source}, "
                 f"{self.frames} frames"
                 + (f" in {self.out}" if self.out else "")]
        lines += [n.line() for n in self.log_notes]
        if self.vtk:
            lines.append(f"VTK series: {self.vtk}")
        if self.incomplete:
            lines.append(f"{len(self.incomplete)} incomplete steps (step: chunks of ranks): "
                         + ", ".join(f"{s}: {g}/{e}" for s, g, e in self.incomplete[:SHOWN_STEPS])
                         + (" ..." if len(self.incomplete) > SHOWN_STEPS else ""))
        if self.late:
            lines.append(f"{self.late} chunks dropped as duplicates or late")
        if self.unchecked:
            lines.append(f"{self.unchecked} steps that the recorded spec did not schedule: "
                         f"rendered without checking their regions and decimation")
        for name, v in self.views.items():
            lines.append(f"view {name}: {v.frames} frames")
            for why, steps in v.problems.items():
                shown = ", ".join(map(str, steps[:SHOWN_STEPS]))
                more = f" and {len(steps) - SHOWN_STEPS} more" if len(steps) > SHOWN_STEPS else ""
                lines.append(f"  NOT RENDERED at {len(steps)} steps ({shown}{more}): {why}")
        return "\n".join(lines)


def recorded_steps(path: Path, run: str, assembler: StepAssembler,
                   notes: list[LogNote] | None = None
                   ) -> Iterator[tuple[AssembledStep, Spec | None]]:
    """The run's steps, assembled in log order, each with the recorded spec in force then
    (a truncated or damaged log is noted in `notes`)."""
    spec = None
    topics = [keys.log_topic(run, Topic.SPEC), keys.log_topic(run, Topic.CHUNK)]
    records = read_log_noting(path, notes, topics)
    for record in records:
        message = record.decode()
        if isinstance(message, Spec):
            spec = message
            continue
        for step in assembler.add(message, record.log_ns, len(record.data)):
            yield step, spec
    for step in assembler.drain(time.time_ns()):
        yield step, spec


def completed_steps(steps: Iterator[tuple[AssembledStep, Spec | None]]
                    ) -> Iterator[tuple[AssembledStep, Spec | None]]:
    """The steps completed from a particle cache, as the server completed them."""
    cache = ParticleCache()
    for step, spec in steps:
        yield complete_step(cache, step), spec


def covered(boxes: tuple[Region, ...], by: tuple[Region, ...]) -> bool:
    """Whether the union of `by` holds every box of `boxes` (exact: each box is cut by the
    planes of `by` and the centre of every cell must lie in some box of `by`)."""
    return all(_box_covered(b.lo_m, b.hi_m, tuple((r.lo_m, r.hi_m) for r in by)) for b in boxes)


@lru_cache(maxsize=1024)
def _box_covered(lo, hi, by) -> bool:
    if any(all(l0 <= a and b <= h0 for a, b, l0, h0 in zip(lo, hi, blo, bhi, strict=True))
           for blo, bhi in by):
        return True
    axes = []
    for a in range(3):
        cuts = sorted({lo[a], hi[a], *(x for blo, bhi in by for x in (blo[a], bhi[a])
                                       if lo[a] < x < hi[a])})
        axes.append([(c0 + c1) / 2 for c0, c1 in zip(cuts, cuts[1:], strict=False)] or [lo[a]])
    return all(any(all(blo[a] <= p[a] <= bhi[a] for a in range(3)) for blo, bhi in by)
               for p in itertools.product(*axes))


def _names(regions: tuple[Region, ...]) -> str:
    return ", ".join(r.name for r in regions)


def missing_data(spec: Spec, view: View, step: AssembledStep, recorded: Spec | None) -> str:
    """Why the log cannot give `view` (due at `step`) what it shows, or "" when it can."""
    if view.field not in step.fields:
        return f"field {view.field!r} is not in the log (it holds {sorted(step.fields)})"
    request = recorded and recorded.request(step.step, step.time_s, step.prev_time_s)
    if not request:
        return ""  # the recorded spec did not ask for this step: nothing to check against
    wanted = spec.view_regions(view, step.step, step.time_s, step.prev_time_s)
    if request.regions is not None and not step.completed and (
            wanted is None or not covered(wanted, request.regions)):
        shown = "every particle" if wanted is None else f"regions {_names(wanted)}"
        return (f"it shows {shown}; the simulation sent only the particles in regions "
                f"{_names(request.regions)}")
    k, stride = view.decimate, request.decimate
    if k % stride:
        return (f"decimate {k} needs particles that the recorded stride {stride} left out")
    if k != stride and ID_FIELD not in step.fields:
        return (f"decimate {k} needs particle ids to pick from the recorded stride {stride}, "
                f"and the log holds no {ID_FIELD!r} field")
    if request.visible_in and not (spec.sphere_radius_m == recorded.sphere_radius_m and any(
            (v.camera, v.width, v.height, v.decimate, r)
            == (view.camera, view.width, view.height, view.decimate, wanted)
            for v, r in request.visible_in)):
        return ("the simulation sent only the particles the recorded cameras could see "
                "(occlusion_cull), and no recorded view has this view's camera, size, "
                "stride, regions and sphere radius")
    return ""


def unrecorded(view: View, steps: list[tuple[int, float, float | None]]) -> list[int | str]:
    """About which steps (every_steps windows) or instants (every_s windows) `view` would
    render within the recorded span that the log does not hold; steps: (step, time_s s,
    prev_time_s s) of the recorded steps."""
    if not steps:
        return []
    steps = sorted(steps)
    nums = np.array([s for s, _, _ in steps])
    times = np.array([t for _, t, _ in steps])
    missing: set[int] = set()
    instants: set[float] = set()
    for w in view.schedule:
        if w.every_s is None:
            first = -(-int(nums[0]) // w.every_steps) * w.every_steps
            cand = np.arange(first, int(nums[-1]) + 1, w.every_steps)
            cand = cand[~np.isin(cand, nums)]
            t = np.interp(cand, nums, times)
            missing.update(cand[(t >= w.t_start_s) & (t <= w.t_end_s)].tolist())
            continue
        e, t0 = w.every_s, w.t_start_s
        s0, first_t, first_prev = steps[0]
        k_lo = (w.instant(first_prev) + 1 if first_prev is not None
                else math.ceil((first_t - t0) / e - INSTANT_TOLERANCE))
        k_hi = w.instant(float(times[-1]))
        done = {w.instant(t) for s, t, p in steps if w.wants(s, t, p)}
        instants.update(t0 + k * e for k in range(max(k_lo, 0), k_hi + 1) if k not in done)
    return sorted(missing) + [f"t={t:.6g} s" for t in sorted(instants)]


def rerender(path: Path, spec: Spec | None = None, out: Path | None = None,
             vtk: Path | None = None, run: str | None = None, shadows: bool = False,
             progress: Callable[[str], None] | None = None,
             notes: list[LogNote] | None = None) -> ReplaySummary:
    """Re-render the log at `path` into out/{view}/{step:06d}.png (out None: render nothing)
    with `spec` (None: the log's spec in force at each step, as the server rendered it: an
    update put during the run applies from the steps logged after it), and/or export its steps to a VTK
    series in `vtk` ({run}_{step:06d}.vtp, {run}.pvd). A truncated or damaged log replays
    up to its last complete chunk, noted in `notes`."""
    specs = log_specs(path, notes)
    run = log_run(path, specs, run, notes)
    own = [s for s in specs if s.run == run]
    if spec is None and out is not None and not own:
        raise RunLogError(f"{path}: no spec of run {run!r} is recorded; pass --spec")
    summary = ReplaySummary(run, "the log's spec" if spec is None else "a given spec", out=out)
    follow = spec is None  # the recorded spec of each step
    spec = spec if spec is not None else (own[-1] if own else None)
    if spec is not None and out is not None:
        summary.views = {v.name: ViewReport() for s in (own if follow else [spec])
                         for v in s.views}
    culled = sorted({v.name for s in own for v in s.views if v.occlusion_cull})
    if shadows and out is not None and culled and progress is not None:
        progress(f"note: the recorded views {', '.join(culled)} had occlusion_cull: the log "
                 "lacks the hidden particles, so their shadows are missing")
    series = VtkSeries(vtk, run) if vtk is not None else None
    assembler = StepAssembler(max_pending=MAX_PENDING_STEPS)  # no timeouts: never expired
    canvases: dict = {}
    seen: list[tuple[int, float, float | None]] = []
    for step, recorded in completed_steps(recorded_steps(path, run, assembler, notes)):
        summary.steps += 1
        seen.append((step.step, step.time_s, step.prev_time_s))
        if step.incomplete:
            summary.incomplete.append((step.step, step.ranks_received, step.ranks_expected))
        if series is not None:
            series.add(step)
        if out is None:
            continue
        ok = []
        now = recorded if follow and recorded is not None else spec
        due = now.wants(step.step, step.time_s, step.prev_time_s)
        if recorded is None or not recorded.request(step.step, step.time_s, step.prev_time_s):
            summary.unchecked += bool(due)
        for view in due:
            why = missing_data(now, view, step, recorded)
            if why:
                summary.views[view.name].problems[why].append(step.step)
            else:
                ok.append(view)
        rendered = 0
        for r in render_views(step, now, canvases, shadows, ok):
            if r.error:  # not expected: missing_data checked the field
                summary.views[r.view.name].problems[r.error].append(step.step)
                continue
            target = out / r.view.name / f"{step.step:06d}.png"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(r.png)
            summary.views[r.view.name].frames += 1
            rendered += 1
        summary.frames += rendered
        if progress is not None and due:
            progress(f"step {step.step} (t = {step.time_s:.6g} s): {rendered} of {len(due)} "
                     f"due views rendered" + (" [incomplete]" if step.incomplete else ""))
    summary.late = assembler.stats.late + assembler.stats.duplicates
    if series is not None:
        summary.vtk = series.close()
    if summary.steps == 0:
        raise RunLogError(f"{path}: no chunks of run {run!r} recorded")
    for view in (spec.views if out is not None else ()):
        gaps = unrecorded(view, seen)
        if gaps:
            summary.views[view.name].problems[UNRECORDED] = gaps
    return summary
