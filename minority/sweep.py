"""Run the MPM sweep behind the GNS dataset: the scenes gns.sweep plans, as channel columns
(sim.columns), each simulated by the sim's API in a worker process, one HDF5 trajectory per
scene (layout: protocol.trajectory). What `minority oracle dataset` runs before gns.dataset.

A run is what `minority sim SCENE --out H5 --no-publish -q` does (sim.ranks.run_ranks on one
rank), in a process of its own (spawned: numba's threads and MPI are per process). A scene
whose trajectory holds every frame is not run again, so an interrupted or enlarged sweep
resumes where it stopped.
"""

from __future__ import annotations

import multiprocessing
import sys
import time
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import replace
from pathlib import Path

from minority.gns.sweep import ScenePlan, SweepConfig, SweepError, plan
from minority.protocol.trajectory import frames_written
from minority.sim.columns import ColumnSpec, channel_column_toml

# Fixed in every sweep scene (the config draws the geometry and friction): a sand column
# against the back wall (x = 0) of a channel, like the showcase column_13k (2 particles per
# cell per axis); rough side walls, a frictionless lid.
SWEEP_COLUMN = ColumnSpec(density_kg_m3=1800.0, youngs_modulus_pa=2.0e6, poisson_ratio=0.3,
                          floor_friction=0.5, side_friction=0.2, top_friction=0.0,
                          per_cell_per_axis=2, cfl=0.3)


def column(cfg: SweepConfig, p: ScenePlan) -> ColumnSpec:
    """The planned scene p as a channel column; the MPM cell is the config's cell_size_m /
    coarse_grain (m)."""
    return replace(SWEEP_COLUMN, length_m=p.length_m, width_m=p.width_m, height_m=p.height_m,
                   friction_angle_deg=p.friction_angle_deg,
                   domain_length_m=p.domain_length_m,
                   domain_height_m=float(cfg.geometry["domain_height_m"]),
                   cell_size_m=float(cfg.geometry["cell_size_m"]) / cfg.coarse_grain,
                   duration_s=cfg.duration_s, output_interval_s=cfg.output_interval_s)


def scene_toml(cfg: SweepConfig, p: ScenePlan) -> str:
    """The scene TOML text of planned scene p."""
    return channel_column_toml(column(cfg, p), p.name)


def frames_due(cfg: SweepConfig) -> int:
    """Frames of a finished run: t = 0 and every output interval up to the duration."""
    from minority.sim.runner import frame_times

    return len(frame_times(cfg.duration_s, cfg.output_interval_s))


def complete(h5_path: Path, cfg: SweepConfig) -> bool:
    """True if h5_path holds every frame of a finished run of the sweep."""
    return frames_written(h5_path) >= frames_due(cfg)


def run_scene(scene_path: Path, out_path: Path, threads: int) -> None:
    """One MPM run, as `minority sim --no-publish -q` (in a worker process); SweepError on
    failure."""
    from minority.sim.driver import SimulationError
    from minority.sim.ranks import RankRunConfig, run_ranks
    from minority.sim.scene import SceneError

    try:
        run_ranks(RankRunConfig(scene_path=scene_path, out=out_path, threads=threads,
                                progress=False))
    except (SceneError, SimulationError, ValueError, OSError) as exc:
        raise SweepError(f"scene {scene_path.stem} failed: {exc}") from None


def run_sweep(cfg: SweepConfig, out_dir: str | Path, *, jobs: int = 1, threads: int = 1,
              log=None) -> list[tuple[ScenePlan, Path]]:
    """Run every planned scene not already complete in out_dir, `jobs` at a time with
    `threads` numba threads each; return (plan, HDF5 path) of every scene. Writes
    out_dir/{scene}.toml and out_dir/{scene}.h5."""
    log = sys.stderr if log is None else log  # the stream of the call, not of the import
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plans = plan(cfg)
    todo = []
    for p in plans:
        (out / f"{p.name}.toml").write_text(scene_toml(cfg, p))
        if not complete(out / f"{p.name}.h5", cfg):
            todo.append(p)
    print(f"sweep: {len(plans)} scenes, {len(plans) - len(todo)} already done, running "
          f"{len(todo)} ({jobs} at a time, {threads} thread(s) each) in {out}", file=log,
          flush=True)
    if todo:
        _run_all(todo, out, max(1, jobs), threads, log)
    return [(p, out / f"{p.name}.h5") for p in plans]


def _run_all(todo: list[ScenePlan], out: Path, jobs: int, threads: int, log) -> None:
    t0 = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")  # no fork of a process with threads
    with ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=ctx) as pool:
        pending = {pool.submit(run_scene, out / f"{p.name}.toml", out / f"{p.name}.h5",
                               threads): p for p in todo}
        done_count = 0
        while pending:
            done, _ = wait(pending, return_when=FIRST_EXCEPTION)
            # in plan order: of two scenes that failed by now, the first planned is reported
            for fut in sorted(done, key=lambda f: todo.index(pending[f])):
                p = pending.pop(fut)
                exc = fut.exception()
                if exc is not None:  # stop: the queued scenes are dropped, running ones end
                    pool.shutdown(wait=True, cancel_futures=True)
                    if isinstance(exc, SweepError):
                        raise exc
                    raise SweepError(f"scene {p.name} failed: {exc!r}") from exc
                done_count += 1
                print(f"sweep: {done_count}/{len(todo)} {p.name} ({p.particles} particles, "
                      f"a = {p.aspect_ratio:.2f}, phi = {p.friction_angle_deg:.1f} deg) "
                      f"{time.perf_counter() - t0:.0f} s", file=log, flush=True)
