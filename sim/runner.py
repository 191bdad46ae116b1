"""Run a scene to completion and write its trajectory (what `minority sim` calls)."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from minority.sim.driver import Simulator
from minority.sim.output import TrajectoryWriter
from minority.sim.scene import load_scene

PROGRESS_EVERY_S = 2.0  # wall time between progress lines between frames, s
PROGRESS_STEPS = 50  # steps between checks of the progress clock
FRAME_TIME_TOL = 1e-9  # relative tolerance when counting output frames


@dataclass
class RunSummary:
    out_path: Path
    particles: int
    steps: int
    frames: int
    sim_time_s: float
    wall_s: float  # stepping and output, s (includes JIT compile on a cold cache)
    step_wall_s: float  # inside the MPM phases only, s
    particle_steps_per_s: float  # particles * steps / step_wall_s
    clamped_particle_steps: int  # particle positions clamped back into the domain
    threads: int


def frame_times(duration_s: float, interval_s: float) -> list[float]:
    """The times (s) a run of duration_s writes frames at: t = 0 and every interval_s."""
    count = int(math.floor(duration_s / interval_s * (1.0 + FRAME_TIME_TOL)))
    return [k * interval_s for k in range(count + 1)]


def run_scene(scene_path: str | Path, out_path: str | Path, *, dt: float | None = None,
              threads: int | None = None, progress: bool = True,
              stream: TextIO | None = None) -> RunSummary:
    """Simulate the scene in scene_path and write frames to the HDF5 file out_path.

    dt: fixed time step in s (refused with TimeStepError if above the CFL bound); None
    follows the CFL bound. threads: numba threads (None = numba's default). Progress lines
    (steps, sim time, particle-steps/s) go to stderr unless progress is False."""
    import numba

    scene = load_scene(scene_path)
    log = stream if stream is not None else sys.stderr
    wall0 = time.perf_counter()
    sim = Simulator(scene, fixed_dt=dt, threads=threads)
    n = sim.particles.n
    frames = frame_times(scene.duration_s, scene.output_interval_s)
    dt0 = dt if dt is not None else sim.stable_dt()

    def say(msg: str) -> None:
        if progress:
            print(msg, file=log, flush=True)

    say(f"sim: scene {scene.name}: {n} particles, grid {sim.grid.shape}, "
        f"{len(frames)} frames, dt {dt0:.3g} s ({'fixed' if dt is not None else 'cfl'})")
    last_print = time.perf_counter()
    with TrajectoryWriter(out_path, scene, n, dt_s=dt0,
                          dt_mode="fixed" if dt is not None else "cfl") as writer:
        for k, t_frame in enumerate(frames):
            while not sim.reached(t_frame):
                sim.advance_to(t_frame, max_steps=PROGRESS_STEPS)
                if progress and time.perf_counter() - last_print > PROGRESS_EVERY_S:
                    say(_progress_line(sim, n, len(frames)))
                    last_print = time.perf_counter()
            diag = sim.diagnostics()
            writer.write_frame(time_s=sim.time_s, step=sim.step_count,
                               fields=sim.fields_by_id(),
                               kinetic_energy_j=diag.kinetic_energy_j,
                               momentum=diag.momentum_kg_m_s)
            say(f"frame {k + 1}/{len(frames)} written: " + _progress_line(sim, n, len(frames)))
            last_print = time.perf_counter()
    step_wall = sim.times.total
    return RunSummary(
        out_path=Path(out_path), particles=n, steps=sim.step_count, frames=len(frames),
        sim_time_s=sim.time_s, wall_s=time.perf_counter() - wall0, step_wall_s=step_wall,
        particle_steps_per_s=n * sim.step_count / step_wall if step_wall > 0 else 0.0,
        clamped_particle_steps=sim.clamp_count, threads=numba.get_num_threads())


def _progress_line(sim: Simulator, n: int, nframes: int) -> str:
    rate = n * sim.step_count / sim.times.total if sim.times.total > 0 else 0.0
    return (f"step {sim.step_count}, t = {sim.time_s:.4f} s, dt = {sim.stable_dt():.3g} s, "
            f"max speed {sim.max_speed_m_s:.3g} m/s, {rate:.3g} particle-steps/s")
