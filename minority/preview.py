"""`minority oracle preview SPEC ROLLOUT.h5`: the spec's views rendered on the predicted run,
as one contact sheet PNG (a row per view, columns spread over the frames the view's
schedule renders), so a person can judge cameras, windows, regions and colors before the
full run. Rendered by the server's own code (render_server.frames.render_views) as the run
draws them: every particle (the server completes the regions from its cache), decimation
applied, annotated (the domain's floor and walls from the rollout's bounds_m); each label
says how many particles the view's regions hold then (what the ranks send fresh).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from minority.protocol.spec import ID_FIELD, Spec, inside_mask
from minority.render_server.frames import render_views
from minority.render_server.render import Canvas

LABEL_PX = 14  # label strip height above each thumbnail


def scheduled_frames(spec: Spec, view, time_s: np.ndarray) -> list[int]:
    """Rollout frames the view's schedule renders, taking each frame as a sim step."""
    return [k for k in range(len(time_s))
            if view.wants(k, float(time_s[k]), float(time_s[k - 1]) if k else None)]


def rollout_field(name: str, positions: np.ndarray, k: int, frame_interval_s: float) -> np.ndarray:
    """A particle field of rollout frame k: displacement (m) or velocity (m/s, backward
    difference), as vectors [n, 3] or magnitudes [n] (`*_magnitude`)."""
    base = name.removesuffix("_magnitude")
    if base == "displacement":
        v = positions[k] - positions[0]
    elif base == "velocity":
        v = (positions[k] - positions[max(k - 1, 0)]) / frame_interval_s
    else:
        raise ValueError(f"the rollout has no field {name!r} (it has displacement, velocity "
                         f"and their _magnitude)")
    return np.linalg.norm(v, axis=1) if name.endswith("_magnitude") else v


@dataclass
class RolloutStep:
    """A rollout frame as a step the server renders (render_server.frames.StepLike)."""

    step: int
    time_s: float
    prev_time_s: float | None
    positions: np.ndarray  # [n, 3] float32, m
    fields: dict[str, np.ndarray]
    spacing_m: float
    bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    completed: bool = True  # every particle is there: views draw them all, as in the run


def domain(bounds_m) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A trajectory's bounds_m [3, 2] (lo, hi per axis, m) as the (lo, hi) corners a step
    carries."""
    b = np.asarray(bounds_m, dtype=np.float64).reshape(3, 2)
    return tuple(map(float, b[:, 0])), tuple(map(float, b[:, 1]))


def contact_sheet(spec: Spec, positions: np.ndarray, frame_interval_s: float, spacing_m: float,
                  columns: int = 6, thumb_width: int = 256, log=None,
                  bounds_m: np.ndarray | None = None) -> Image.Image:
    """positions [frames, n, 3] (m) -> the sheet: a row per view, up to `columns` frames;
    bounds_m [3, 2] (m): the domain the annotations draw (None: no floor nor walls)."""
    log = sys.stderr if log is None else log  # the stream of the call, not of the import
    box = None if bounds_m is None else domain(bounds_m)
    time_s = np.arange(len(positions)) * frame_interval_s
    ids = np.arange(positions.shape[1])  # rollout rows: decimation picks id % k == 0
    rows = []
    for view in spec.views:
        frames = scheduled_frames(spec, view, time_s)
        picks = ([frames[int(round(i))] for i in np.linspace(0, len(frames) - 1, columns)]
                 if len(frames) > columns else frames)
        picks = list(dict.fromkeys(picks))
        canvases: dict[str, Canvas] = {}
        thumbs = []
        for k in picks:
            step = RolloutStep(k, float(time_s[k]), float(time_s[k - 1]) if k else None,
                               np.ascontiguousarray(positions[k], np.float32),
                               {view.field: rollout_field(view.field, positions, k,
                                                          frame_interval_s),
                                ID_FIELD: ids}, spacing_m, box)
            (shown,) = render_views(step, spec, canvases, views=[view])
            if shown.error:
                raise ValueError(shown.error)
            img = Image.fromarray(np.array(shown.image))
            h = round(thumb_width * view.height / view.width)
            regions = spec.view_regions(view, step.step, step.time_s, step.prev_time_s)
            fresh = (len(step.positions) if regions is None
                     else int(inside_mask(step.positions, regions).sum()))
            thumbs.append((k, fresh, img.resize((thumb_width, h), Image.LANCZOS)))
        rows.append((view, len(frames), thumbs))
        print(f"preview: view {view.name}: {len(frames)} frames scheduled on the rollout, "
              f"{len(thumbs)} shown", file=log)
    h_row = max((t[2].height for _, _, ts in rows for t in ts), default=64) + LABEL_PX
    sheet = Image.new("RGB", (thumb_width * columns, h_row * len(rows) + LABEL_PX), "white")
    draw = ImageDraw.Draw(sheet)
    draw.text((4, 1), f"spec {spec.run}: {len(spec.views)} views on the rollout "
                      f"({positions.shape[1]} particles)", fill="black")
    for r, (view, n_frames, thumbs) in enumerate(rows):
        y = LABEL_PX + r * h_row
        if not thumbs:
            draw.text((4, y + 2), f"{view.name}: none of the rollout's {len(positions)} "
                                  f"frames is scheduled ({n_frames})",
                      fill="red")
        for c, (k, n, img) in enumerate(thumbs):
            draw.text((c * thumb_width + 4, y + 1),
                      f"{view.name} t={time_s[k]:.3f}s, {n} in regions", fill="black")
            sheet.paste(img, (c * thumb_width, y + LABEL_PX))
    return sheet


def preview(spec_path: Path, rollout_path: Path, out: Path, columns: int = 6,
            thumb_width: int = 256) -> Path:
    from minority.protocol.trajectory import read_rollout

    spec = Spec.load(spec_path)
    r = read_rollout(rollout_path)
    sheet = contact_sheet(spec, r["positions"], float(r["frame_interval_s"]),
                          float(r["particle_spacing_m"]), columns, thumb_width,
                          bounds_m=r["bounds_m"])
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out
