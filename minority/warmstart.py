"""The GNS oracle's first frames from the MPM itself (a warm start).

A GNS predicts from the velocities of its last C frames; a column released from rest has
none, and C identical frames at rest are not a state the training data hold (every training
window starts from frames the MPM already moved). So the oracle runs the MPM at the model's
particle spacing for those C frames (about a second at 1,600 particles, 25 ms simulated)
and lets the GNS go on from there, as its validation rollouts do.
"""

from __future__ import annotations

import copy
import sys
import tomllib
from pathlib import Path

import numpy as np

from minority.sim.driver import Simulator
from minority.sim.scene import SceneError, parse_scene


def mpm_history(scene_toml: Path, spacing_m: float, frame_interval_s: float,
                frames: int, coarse_grain: int = 1, method: str = "mean") -> np.ndarray:
    """[frames + 1, n, 3] positions (m) at t = 0, dt, ... of the scene simulated by the MPM
    with particles at `spacing_m` (one per cell of that size, or two per axis in cells
    twice as large when the domain is not a whole number of the smaller cells). With
    coarse_grain k > 1 (a model trained on coarse-grained MPM runs), the MPM runs as its
    training data did, two particles per axis at spacing_m / k, and each group of k^3 becomes
    one by `method` (gns.dataset.coarse_grain: "mean" or "sample")."""
    from minority.gns import dataset

    data = tomllib.loads(Path(scene_toml).read_text())
    errors = []
    fine = spacing_m / coarse_grain
    for per_axis in ((1, 2) if coarse_grain == 1 else (2, 1)):
        d = copy.deepcopy(data)
        d.setdefault("domain", {})["cell_size_m"] = fine * per_axis
        d.setdefault("particles", {})["per_cell_per_axis"] = per_axis
        d.setdefault("time", {}).update(duration_s=frames * frame_interval_s,
                                        output_interval_s=frame_interval_s)
        try:
            scene = parse_scene(d, name=f"{Path(scene_toml).stem}_warm_start")
        except SceneError as exc:
            errors.append(str(exc))
            continue
        sim = Simulator(scene, threads=1)
        out = []
        for k in range(frames + 1):
            sim.advance_to(k * frame_interval_s)
            out.append(sim.fields_by_id()["positions"].astype(np.float64))
        return dataset.coarse_grain(np.stack(out), fine, coarse_grain, method)
    raise ValueError(f"{scene_toml}: cannot seed the MPM at the model's spacing {spacing_m} m "
                     f"({'; '.join(errors)})")


def predict_scene(checkpoint: Path, scene: Path, duration_s: float | None = None,
                  start: str = "mpm", device: str = "cpu", progress: bool = False, log=None):
    """gns.predict.predict from the MPM's first frames (start "mpm"; from rest, with a
    warning, when the MPM cannot seed the scene at the model's spacing) or from rest."""
    from minority.gns.predict import predict

    out = log if log is not None else sys.stderr

    def from_mpm(spacing_m: float, frame_interval_s: float, frames: int,
                 coarse_grain: int = 1, method: str = "mean") -> np.ndarray | None:
        try:
            history = mpm_history(scene, spacing_m, frame_interval_s, frames, coarse_grain,
                                  method)
        except ValueError as exc:
            print(f"rollout: warning: {exc}; starting from rest instead", file=out)
            return None
        print(f"rollout: the first {frames} frames ({frames * frame_interval_s:.3f} s) from "
              f"the MPM at {spacing_m / coarse_grain} m"
              + (f", coarse-grained by {coarse_grain} ({method})" if coarse_grain > 1 else ""),
              file=out)
        return history

    return predict(checkpoint, scene, duration_s, device, progress, log,
                   history=from_mpm if start == "mpm" else None)
