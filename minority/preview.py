"""`minority oracle preview SPEC ROLLOUT.h5`: the spec's views rendered on the predicted run,
as one contact sheet PNG (a row per view, columns spread over the frames the view's
schedule renders), so a person can judge cameras, windows, regions and colors before the
full run. Rendered by the server's own ray tracer, regions of interest applied.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from protocol.spec import Spec
from render_server.render import Canvas, prepare, render

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


def _subset(spec: Spec, view, k: int, time_s: np.ndarray, x: np.ndarray) -> np.ndarray:
    regions = spec.view_regions(view, k, float(time_s[k]), float(time_s[k - 1]) if k else None)
    if regions is None:
        return np.arange(len(x))
    keep = np.zeros(len(x), bool)
    for r in regions:
        keep |= np.all((x >= r.lo_m) & (x <= r.hi_m), axis=1)
    return np.flatnonzero(keep)


def contact_sheet(spec: Spec, positions: np.ndarray, frame_interval_s: float, spacing_m: float,
                  columns: int = 6, thumb_width: int = 256, log=sys.stderr) -> Image.Image:
    """positions [frames, n, 3] (m) -> the sheet: a row per view, up to `columns` frames."""
    time_s = np.arange(len(positions)) * frame_interval_s
    radius = spec.sphere_radius_m or 0.5 * spacing_m
    rows = []
    for view in spec.views:
        frames = scheduled_frames(spec, view, time_s)
        picks = ([frames[int(round(i))] for i in np.linspace(0, len(frames) - 1, columns)]
                 if len(frames) > columns else frames)
        picks = list(dict.fromkeys(picks))
        canvas = Canvas(view.width, view.height)
        thumbs = []
        for k in picks:
            x = positions[k]
            idx = _subset(spec, view, k, time_s, x)
            if len(idx) == 0:
                img = Image.new("RGB", (view.width, view.height), (128, 128, 128))
            else:
                field = rollout_field(view.field, positions, k, frame_interval_s)[idx]
                scene = prepare(np.ascontiguousarray(x[idx], np.float32), radius)
                img = Image.fromarray(np.array(render(scene, field, view, canvas=canvas)))
            h = round(thumb_width * view.height / view.width)
            thumbs.append((k, len(idx), img.resize((thumb_width, h), Image.LANCZOS)))
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
                      f"{view.name} t={time_s[k]:.3f}s {n}p", fill="black")
            sheet.paste(img, (c * thumb_width, y + LABEL_PX))
    return sheet


def preview(spec_path: Path, rollout_path: Path, out: Path, columns: int = 6,
            thumb_width: int = 256) -> Path:
    from gns.export import read_rollout

    spec = Spec.load(spec_path)
    r = read_rollout(rollout_path)
    sheet = contact_sheet(spec, r["positions"], float(r["frame_interval_s"]),
                          float(r["particle_spacing_m"]), columns, thumb_width)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out
