"""Predict a scene with a checkpoint and write the rollout: the one path behind
`minority oracle rollout` and the demo's oracle step."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from minority.gns.export import write_hdf5, write_vtk_series
from minority.gns.rollout import initial_state, rollout
from minority.gns.train import coarse_grain_stats, load_checkpoint

# (particle spacing m, frame interval s, C, coarse_grain, coarse_grain_method)
#   -> [C + 1, n, 3] m or None
HistoryFn = Callable[[float, float, int, int, str], "np.ndarray | None"]


@dataclass
class Prediction:
    positions: np.ndarray  # [frames, n, 3] m, frame 0 at rest (t = 0)
    frame_interval_s: float
    spacing_m: float
    bounds_m: np.ndarray  # [3, 2] m
    friction_deg: float
    name: str
    scene: Path
    checkpoint: Path
    wall_s: float
    timing: dict  # graph_s, model_s, clamped

    def write(self, out_dir: Path, vtk_every: int = 1) -> Path:
        """out_dir/rollout.h5 and, with vtk_every > 0, out_dir/vtk/rollout.pvd."""
        h5 = write_hdf5(Path(out_dir) / "rollout.h5", self.positions, self.frame_interval_s,
                        attrs={"scene": str(self.scene), "checkpoint": str(self.checkpoint),
                               "friction_angle_deg": self.friction_deg,
                               "bounds_m": self.bounds_m, "particle_spacing_m": self.spacing_m,
                               "wall_s": self.wall_s})
        if vtk_every:
            write_vtk_series(Path(out_dir) / "vtk", self.positions, self.frame_interval_s,
                             every=vtk_every)
        return h5


def predict(checkpoint: Path, scene: Path, duration_s: float | None = None,
            device: str = "cpu", progress: bool = False, log=None,
            history: np.ndarray | HistoryFn | None = None) -> Prediction:
    """Seed `scene` at the model's spacing and roll it out for duration_s (default: the
    scene's). `history` [C + 1, n, 3] (m): the first frames, e.g. from the MPM, or a function
    of (particle spacing m, frame interval s, C, the training data's coarse_grain and its
    method) giving them
    or None (None: C + 1 frames at rest). Raises RolloutError when the rollout diverges,
    ValueError on bad input."""
    model, ckpt = load_checkpoint(checkpoint, device)
    st = ckpt["stats"]
    c = model.config.input_velocities
    init = initial_state(scene, st["particle_spacing_m"], st["frame_interval_s"], c)
    if callable(history):
        cg = coarse_grain_stats(st)
        history = history(float(st["particle_spacing_m"]), float(st["frame_interval_s"]), c,
                          cg["coarse_grain"], cg["coarse_grain_method"])
    if history is not None:
        if history.ndim != 3 or history.shape[0] != c + 1 or history.shape[2] != 3:
            raise ValueError(f"history must be [{c + 1}, n, 3], got {list(history.shape)}")
        init.positions = np.asarray(history, dtype=np.float64)
    total = round((duration_s or init.duration_s) / st["frame_interval_s"])  # frames after t=0
    frames = max(1, total if history is None else total - c)
    if log is not None:
        print(f"rollout: {init.name}, {init.positions.shape[1]} particles at "
              f"{st['particle_spacing_m']} m, {frames} frames of {st['frame_interval_s']} s",
              file=log)
    t0 = time.perf_counter()
    pos, timing = rollout(model, init.positions, init.friction_deg, init.bounds_m, frames,
                          device=device, progress=progress)
    wall = time.perf_counter() - t0
    return Prediction(pos if history is not None else pos[c:],  # rest history: one frame
                      float(st["frame_interval_s"]), float(st["particle_spacing_m"]),
                      np.asarray(init.bounds_m), float(init.friction_deg), init.name,
                      Path(scene), Path(checkpoint), wall, timing)
