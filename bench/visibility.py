"""Occlusion-culling benchmark: one JSON line per scene and view.

{"bench": "visibility", "scene": S, "particles": N, "view": V, "kept": fraction, "s": seconds}

The column of each built-in scene at rest (or, with --h5, the frame of a `minority sim` run
nearest --time), seen by the oracle's three cameras (side, top, aerial; 1024 x 768) fitted
to the particles' extent as `minority oracle spec` fits them. `s` is the median time of
insitu.visibility.visible_mask over --reps calls (JIT compile excluded).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import h5py
import numpy as np

from minority.gns.oracle import AERIAL_DIRECTION, fit_camera
from minority.insitu.visibility import visible_mask
from minority.protocol.spec import View
from minority.sim.scene import builtin_scene_path, load_scene
from minority.sim.state import seed_particles

VIEWS = {"side": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "top": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
         "aerial": (AERIAL_DIRECTION, (0.0, 0.0, 1.0))}
WIDTH, HEIGHT = 1024, 768
KEYS = {"visibility": ("scene", "particles", "view", "kept", "s")}


def views_for(positions: np.ndarray, margin: float = 0.1) -> list[View]:
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    pad = margin * (hi - lo).max() * 0.5
    return [View(name, fit_camera(lo - pad, hi + pad, d, up, WIDTH / HEIGHT),
                 WIDTH, HEIGHT) for name, (d, up) in VIEWS.items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=["column_13k", "column_100k", "column_1m"])
    parser.add_argument("--h5", help="a minority sim HDF5 run: use its frame nearest --time")
    parser.add_argument("--time", type=float, default=0.5, help="s (with --h5)")
    parser.add_argument("--reps", type=int, default=5)
    args = parser.parse_args()
    cases = []
    if args.h5:
        with h5py.File(args.h5, "r") as f:
            k = int(np.argmin(np.abs(f["time"][:] - args.time)))
            cases.append((f"{args.h5}@{float(f['time'][k]):.3f}s", f["positions"][k].astype(np.float64),
                          0.5 * float(f.attrs["particle_spacing_m"])))
    else:
        for name in args.scenes:
            scene = load_scene(builtin_scene_path(name))
            ps = seed_particles(scene)
            cases.append((name, ps.x, 0.5 * scene.particle_spacing_m))
    visible_mask(cases[0][1][:100], views_for(cases[0][1])[0], cases[0][2])  # compile
    for name, pos, radius in cases:
        for view in views_for(pos):
            times, keep = [], None
            for _ in range(args.reps):
                t0 = time.perf_counter()
                keep = visible_mask(pos, view, radius)
                times.append(time.perf_counter() - t0)
            print(json.dumps({"bench": "visibility", "scene": name, "particles": len(pos),
                              "view": view.name, "kept": round(float(keep.mean()), 4),
                              "s": round(statistics.median(times), 5)}), flush=True)


if __name__ == "__main__":
    main()
