"""Run a scene on MPI ranks (one rank needs no launcher): slab decomposition, one HDF5 file,
publishing to the render server, lifecycle events. What `minority sim` calls.

Order on every rank: load the scene, build its slab (`sim.decomp.SlabSimulator`), open its
zenoh session and fetch the spec (ranks check that they follow the same spec; rank 0's wins
otherwise), `run_start` (rank 0), then per step: MPM step, then minority.insitu's `due` at
every step, step 0 included (it keeps the previous step's time for `every_s` cadences) and,
when it says so, `publish` with the fields it wants built from the ParticleState
(sim.publish: a chunk if the spec schedules the step, a Stats message on the stats
cadence); per output frame:
rank 0 gathers and writes. At the end each rank drains its outbox and publishes `rank_done`
with its counts; rank 0 gathers the totals. A stop asked for (`RankRunConfig.stop`: SIGINT or
SIGTERM on any rank) ends the stepping at the next step boundary on every rank alike (the
ranks agree on it at every step), and the end is the same: frames so far written,
`rank_done` (with `stopped`), records and sessions closed. An error on one rank that the others
cannot see (e.g. a failed write) is published as an `error` event, then MPI_Abort ends the
run; a non-finite value or an unstable time step is seen by every rank at the same step.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from minority.protocol.messages import EventKind
from minority.sim.decomp import DEFAULT_REBALANCE_EVERY, SlabSimulator
from minority.sim.driver import NonFiniteError, TimeStepError
from minority.sim.output import TrajectoryWriter
from minority.sim.runner import PROGRESS_EVERY_S, frame_times
from minority.sim.scene import load_scene


@dataclass
class RankRunConfig:
    scene_path: Path
    out: Path | None  # HDF5 trajectory (rank 0 writes it); None: no HDF5
    dt: float | None = None  # fixed time step, s; None: CFL
    threads: int | None = None  # numba threads per rank; None: cores / ranks on the node
    rebalance_every: int = DEFAULT_REBALANCE_EVERY  # steps; 0: never
    progress: bool = True
    publish: object | None = None  # insitu PublishOptions; None: no network, no record
    run: str | None = None  # run id of the keys minority/{run}/...; None: the scene name
    wait_s: float = 0.0  # keep trying to reach the server this long at start, s
    max_steps: int | None = None  # stop after this many steps (benchmarks, tests)
    # polled at every step boundary: a signal number when a stop is asked for, else 0
    # (sim.launcher.StopSignals); None: never
    stop: Callable[[], int] | None = None


@dataclass
class RankRunSummary:
    """The run as rank 0 sees it (totals over ranks); other ranks get their own."""

    out_path: Path | None
    particles: int
    ranks: int
    steps: int
    frames: int
    sim_time_s: float
    wall_s: float  # from scene load to the end, s
    loop_wall_s: float  # stepping, publishing and output, s
    step_wall_s: float  # inside MPM phases and exchanges, slowest rank, s
    particle_steps_per_s: float  # particles * steps / step_wall_s
    clamped_particle_steps: int
    threads: int
    rebalances: int
    migrated: int  # particles received from other ranks, all ranks
    run: str | None
    spec_version: int | None
    publish: dict = field(default_factory=dict)  # PublishStats summed over ranks
    not_published: str = ""  # why some ranks reached no server (not_published); "": all did
    rank_particles: list[int] = field(default_factory=list)  # per rank, at the end
    rank_compute_cpu_s: list[float] = field(default_factory=list)  # per rank: CPU s, MPM phases
    rank_phases_s: list[dict] = field(default_factory=list)  # per rank: s per phase (PhaseTimes)
    stopped: int = 0  # the signal that stopped the stepping early (every rank's view); 0: none


def _default_threads(comm) -> int:
    from mpi4py import MPI

    local = comm.Split_type(MPI.COMM_TYPE_SHARED).Get_size()
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, (cpus or 1) // local)


def _spec_digest(spec) -> str:
    text = "" if spec is None else json.dumps(spec.to_dict(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def run_ranks(config: RankRunConfig, comm=None, stream: TextIO | None = None) -> RankRunSummary:
    """Simulate the scene on the ranks of `comm` (MPI.COMM_WORLD; one rank without a
    launcher). Collective: every rank calls it with the same config."""
    import numba
    from mpi4py import MPI

    comm = comm if comm is not None else MPI.COMM_WORLD
    rank, ranks = comm.Get_rank(), comm.Get_size()
    log = stream if stream is not None else sys.stderr
    wall0 = time.perf_counter()

    def say(msg: str) -> None:
        if config.progress and rank == 0:
            print(msg, file=log, flush=True)

    scene = load_scene(config.scene_path)
    threads = config.threads if config.threads is not None else (
        _default_threads(comm) if ranks > 1 else None)
    sim = SlabSimulator(scene, fixed_dt=config.dt, threads=threads, comm=comm,
                        rebalance_every=config.rebalance_every)
    sim.stop_source = config.stop
    n_total = sim.n_total
    frames = frame_times(scene.duration_s, scene.output_interval_s)
    dt0 = config.dt if config.dt is not None else sim.stable_dt()
    publisher, run, spec = _start_publishing(config, scene, sim, comm, log)
    if publisher is not None:
        sim.before_write = publisher.reclaim  # the arrays lent at the last due step
    say(f"sim: scene {scene.name}: {n_total} particles on {ranks} rank(s) "
        f"(x-blocks per rank {list(map(int, sim.starts[1:] - sim.starts[:-1]))}), "
        f"{len(frames)} frames, dt {dt0:.3g} s ({'fixed' if config.dt is not None else 'cfl'})")
    if publisher is not None and rank == 0:
        publisher.event(EventKind.RUN_START, f"sim of {scene.name} on {ranks} rank(s)", {
            "scene": scene.name, "ranks": ranks, "particles": n_total,
            "spec_version": spec.version if spec else None,
            "fields": list(spec.fields) if spec else [],
            "regions": [r.name for r in spec.regions] if spec else [],
            "stats_every_s": config.publish.stats_every_s,
            "rebalance_every": config.rebalance_every, "threads": numba.get_num_threads()})

    writer = None
    loop0 = time.perf_counter()
    try:
        if rank == 0 and config.out is not None:
            writer = TrajectoryWriter(config.out, scene, n_total, dt_s=dt0,
                                      dt_mode="fixed" if config.dt is not None else "cfl",
                                      attrs={"ranks": ranks,
                                             "rebalance_every": config.rebalance_every})
        written, stopped = _step_loop(sim, config, frames, writer, publisher, say, comm)
    except (NonFiniteError, TimeStepError) as exc:  # every rank saw it at the same step
        _fail(publisher, exc, rank)
        raise
    except BaseException as exc:
        _fail(publisher, exc, rank)
        if ranks > 1:
            print(f"minority sim: rank {rank}: error: {exc}; aborting all ranks", file=sys.stderr,
                  flush=True)
            comm.Abort(1)
        raise
    finally:
        if writer is not None:
            writer.close()
    loop_wall = time.perf_counter() - loop0
    if stopped:
        say(f"sim: stopped by {signal.Signals(stopped).name} at step {sim.step_count} "
            f"(t = {sim.time_s:.4f} s), {written} of {len(frames)} frames written")
    return _finish(sim, config, comm, publisher, run, spec, (written, stopped), wall0,
                   loop_wall, say)


def _start_publishing(config, scene, sim, comm, log):
    """Connect, agree on the run id and the spec, start every rank's publisher (collective).
    Returns (minority.insitu.InSitu or None, run, spec)."""
    if config.publish is None:
        return None, config.run, None
    from minority.insitu import connect
    from minority.protocol.spec import Spec

    rank, ranks = comm.Get_rank(), comm.Get_size()
    opts = config.publish

    def agree(spec, error):  # collective: one error stops every rank, rank 0's spec wins
        errors = comm.allgather(None if error is None else str(error))
        if any(errors):
            raise ValueError(next(e for e in errors if e))
        digests = comm.allgather(_spec_digest(spec))
        if len(set(digests)) > 1:  # e.g. the spec changed between the ranks' gets
            d = comm.bcast(spec.to_dict() if spec is not None else None, root=0)
            spec = Spec.from_dict(d) if d is not None else None
        return spec

    run = config.run or scene.name
    # shared memory for the largest chunk this rank could send: every particle, every field
    viz = connect(run, rank, ranks, connect=tuple(opts.network.connect), record=opts.record,
                  spec=opts.spec_file, wait_s=config.wait_s, particles=sim.n_total,
                  options=opts, agree=agree, log=log, report=False)
    spec = viz.spec
    reasons = comm.gather(viz.no_server_reason, root=0)
    if rank == 0:
        unpublished = not_published(reasons)
        if unpublished:
            print(warning_block([
                unpublished,
                "this run is NOT published: no render server observes it, nothing is "
                "rendered" + (f" (it is only recorded, to {opts.record} and the ranks' "
                              f"records beside it)" if opts.record else ""),
                f"--wait {config.wait_s:g}: " + (
                    "one try at start; start the server first, or give --wait S to keep "
                    "trying S seconds" if config.wait_s <= 0 else
                    "no server answered in that time")]), file=log, flush=True)
        if spec is None:
            print(f"minority sim: no spec for run {run!r} (no server serves one, no --spec; "
                  f"--run names the server's run): nothing is scheduled, nothing is published",
                  file=log, flush=True)
        else:
            regions = ", ".join(r.name for r in spec.regions) or "none (every particle)"
            print(f"minority sim: run {run!r}, spec version {spec.version}: "
                  f"{len(spec.views)} view(s), fields {', '.join(spec.fields)}, regions "
                  f"{regions}", file=log, flush=True)
    return viz, run, spec


def not_published(reasons: list[str]) -> str:
    """One line from the ranks' no_server_reason (index = rank; "" where the rank reached a
    server): the first reason and the ranks it concerns; "" when every rank reached one."""
    missing = [r for r, why in enumerate(reasons) if why]
    if not missing:
        return ""
    return (f"{reasons[missing[0]]} (rank{'s' if len(missing) > 1 else ''} "
            f"{', '.join(map(str, missing))} of {len(reasons)})")


def warning_block(lines: list[str], who: str = "minority sim") -> str:
    """Lines framed so that they stand out in a terminal's scroll of progress lines."""
    rule = f"{who}: WARNING " + "-" * 60
    return "\n".join([rule, *(f"{who}: WARNING: {line}" for line in lines), rule])


def _publish_step(viz, sim, spacing_m: float, bounds_m) -> None:
    """Ask the publisher whether this step is due; if so, lend it the particles' arrays and
    the fields it wants (computed ones as functions the sender calls): nothing is copied,
    and the step that next writes them waits until the sender has read them
    (Simulator.before_write = InSitu.reclaim)."""
    from minority.sim.publish import sim_fields

    if viz.due(sim.step_count, sim.time_s):
        ps = sim.particles  # lent: the sim's next write waits for the sender (before_write)
        viz.publish(sim.step_count, sim.time_s, ps.x, fields=sim_fields(ps, viz.wanted, lazy=True),
                    ids=ps.pid, spacing_m=spacing_m, bounds_m=bounds_m, copy=False)


def _stop_asked(sim, config, comm) -> int:
    """The signal number of a stop asked for on any rank (0: none). With more than one
    rank, what the last step's exchange agreed on (SlabSimulator.stop_signum): every rank
    stops after the same step, so none waits in an exchange for one that left."""
    if comm.Get_size() > 1:
        return sim.stop_signum
    return config.stop() if config.stop is not None else 0


def _step_loop(sim, config, frames, writer, publisher, say, comm) -> tuple[int, int]:
    """Step through the output frames; hand every step (0 included, in order) to the
    publisher, which needs each step's time as the next one's prev_time_s. Returns (frames
    written, the signal that stopped it early or 0)."""
    n_total = sim.n_total
    scene = sim.scene
    spacing, bounds = scene.particle_spacing_m, ((0.0, 0.0, 0.0), tuple(map(float, scene.size_m)))
    if publisher is not None:
        _publish_step(publisher, sim, spacing, bounds)
    last_print = time.perf_counter()
    start = last_print
    written = 0
    for k, t_frame in enumerate(frames):
        while not sim.reached(t_frame):
            if config.max_steps is not None and sim.step_count >= config.max_steps:
                return written, 0
            stopped = _stop_asked(sim, config, comm)
            if stopped:
                return written, stopped
            sim.advance_to(t_frame, max_steps=1)
            if publisher is not None:
                _publish_step(publisher, sim, spacing, bounds)
            now = time.perf_counter()
            if now - last_print > PROGRESS_EVERY_S:
                say(_progress(sim, n_total, now - start))
                last_print = now
        fields = sim.gather_fields()
        diag = sim.diagnostics()
        if writer is not None:
            writer.write_frame(time_s=sim.time_s, step=sim.step_count, fields=fields,
                               kinetic_energy_j=diag.kinetic_energy_j,
                               momentum=diag.momentum_kg_m_s)
        written += 1
        say(f"frame {k + 1}/{len(frames)}: " + _progress(sim, n_total, time.perf_counter() - start))
        last_print = time.perf_counter()
    return written, 0


def _progress(sim, n_total: int, wall_s: float) -> str:
    rate = n_total * sim.step_count / wall_s if wall_s > 0 else 0.0
    return (f"step {sim.step_count}, t = {sim.time_s:.4f} s, dt = {sim.stable_dt():.3g} s, "
            f"max speed {sim.max_speed_m_s:.3g} m/s, {rate:.3g} particle-steps/s")


def _fail(publisher, exc: BaseException, rank: int) -> None:
    if publisher is not None:
        publisher.fail(exc)  # an error event, then close


def _finish(sim, config, comm, publisher, run, spec, ended, wall0, loop_wall, say):
    """The end on every rank (collective): rank_done with the counts, then the totals.
    ended: (frames written, the signal that stopped the stepping or 0)."""
    import numba
    from mpi4py import MPI

    written, stopped = ended
    ranks = comm.Get_size()
    step_wall = comm.allreduce(sim.times.total, op=MPI.MAX)
    detail = {"steps": sim.step_count, "particles": sim.particles.n,
              "step_wall_s": round(sim.times.total, 6), "loop_wall_s": round(loop_wall, 6),
              "phases_s": {k: round(getattr(sim.times, k), 6)
                           for k in ("bin", "p2g", "grid", "g2p", "comm", "compute_cpu")},
              "migrated": sim.migrated, "clamped_particle_steps": sim.clamp_count}
    if stopped:
        detail["stopped"] = signal.Signals(stopped).name
    if publisher is not None:
        publisher.close(detail)
    pub_total: dict = {}
    parts = comm.allgather(publisher.summary() if publisher is not None else None)
    if parts[0] is not None:
        for part in parts:
            for key, value in part.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    if key in ("prepare_s", "stats_s"):  # the slowest rank's share costs time
                        pub_total[key] = max(pub_total.get(key, 0.0), value)
                    else:
                        pub_total[key] = pub_total.get(key, 0) + value
        pub_total["missing_fields"] = sorted({f for p in parts for f in p["missing_fields"]})
    n_total = sim.n_total
    phases = comm.allgather(detail["phases_s"])
    reasons = comm.allgather(publisher.no_server_reason if publisher is not None else "")
    summary = RankRunSummary(
        out_path=config.out, particles=n_total, ranks=ranks, steps=sim.step_count,
        frames=written, sim_time_s=sim.time_s, wall_s=time.perf_counter() - wall0,
        loop_wall_s=loop_wall, step_wall_s=step_wall,
        particle_steps_per_s=n_total * sim.step_count / step_wall if step_wall > 0 else 0.0,
        clamped_particle_steps=sim.total_count(sim.clamp_count),
        threads=numba.get_num_threads(), rebalances=sim.rebalances,
        migrated=sim.total_count(sim.migrated), run=run,
        spec_version=spec.version if spec is not None else None, publish=pub_total,
        not_published=not_published(reasons),
        rank_particles=comm.allgather(sim.particles.n),
        rank_compute_cpu_s=[p["compute_cpu"] for p in phases], rank_phases_s=phases,
        stopped=stopped)
    if pub_total:
        say(f"published: {pub_total['sent']} of {pub_total['scheduled']} scheduled chunks sent, "
            f"{pub_total['dropped']} dropped, {pub_total['bytes_sent'] / 1e6:.3g} MB, "
            f"{pub_total['particles_sent']} of {pub_total['particles_total']} particles"
            + (f", {pub_total['stats_sent']} of {pub_total['stats_due']} stats sent"
               if pub_total["stats_due"] else "")
            + (f", {pub_total['recorded']} messages recorded" if pub_total["recorded"] else ""))
    return summary
