"""Run the DEM column collapse (dem.py): write its trajectory to HDF5 and publish it through
minority's in situ API (minority.insitu) to a running `minority serve`.

    python examples/dem_column/run.py --help
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dem  # noqa: E402  (this folder is not a package)

from minority.protocol.messages import EventKind  # noqa: E402
from minority.protocol.trajectory import (  # noqa: E402
    PARTICLE_TYPE_SAND,
    SIM_FORMAT,
    SIM_SERIES,
    UNITS,
    FrameWriter,
)

HERE = Path(__file__).resolve().parent
DEFAULT_SCENE = HERE / "scene.toml"
# per-frame datasets besides the MPM run's step, kinetic_energy and momentum
ENERGY_SERIES = {"potential_energy": ((), "f8"), "elastic_energy": ((), "f8")}
ENERGY_UNITS = {"potential_energy": "J", "elastic_energy": "J", "frame_interval_s": "s"}


@dataclass
class Options:
    """One run: the scene, where its frames go (out: HDF5, None: none) and what it publishes
    (publish False: no network at all)."""

    scene: dem.Scene
    out: Path | None = None
    run: str = "dem_column"
    publish: bool = True
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    spec: Path | None = None
    record: Path | None = None
    wait_s: float = 0.0
    progress: bool = True
    threads: int = 1  # numba threads for the contact forces, restored after the run


@dataclass
class Summary:
    """What a run did: particles, steps, frames written, wall times (s) and the publisher's
    counts (insitu.PublishStats as a dict; empty without publishing)."""

    particles: int
    diameter_m: float
    dt_s: float
    pour_steps: int
    steps: int
    frames: int
    pour_wall_s: float
    wall_s: float  # the collapse's loop, pour excluded
    insitu_s: float  # of which in due + publish
    runout_m: tuple[float, float]  # before, after (99th percentile of x)
    height_m: tuple[float, float]  # before, after (99th percentile of z)
    publish: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def trajectory_writer(path: Path, sim: dem.Simulation) -> FrameWriter:
    """The run's HDF5 file in minority's trajectory layout (protocol.trajectory, with every
    attribute an MPM run has, so every reader of the project takes it), plus the DEM's
    energies per frame."""
    s = sim.scene
    friction_angle_deg = math.degrees(math.atan(s.friction))
    attrs = {
        "dim": 3, "dt_s": sim.dt_s, "dt_mode": "fixed", "simulator": "DEM (examples/dem_column)",
        "output_interval_s": s.output_interval_s, "frame_interval_s": s.output_interval_s,
        "bounds_m": s.bounds_m, "particle_spacing_m": s.diameter_m, "cell_size_m": sim.cell_m,
        "scene_name": s.name, "scene_toml": s.to_toml(),
        "material_table": json.dumps({
            "model": "dem_linear_spring_dashpot_coulomb", "diameter_m": s.diameter_m,
            "density_kg_m3": s.density_kg_m3, "friction": s.friction,
            "friction_angle_deg": friction_angle_deg, "rolling_friction": s.rolling_friction,
            "restitution": s.restitution, "normal_stiffness_n_m": s.stiffness_n_m}),
        "pour_s": sim.pour_s,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    return FrameWriter(
        path, sim.n, fmt=SIM_FORMAT, units={**UNITS, **ENERGY_UNITS}, attrs=attrs,
        particle_data={"particle_type": np.full(sim.n, PARTICLE_TYPE_SAND, np.int32),
                       "material": np.full(sim.n, friction_angle_deg, np.float32)},
        series={**SIM_SERIES, **ENERGY_SERIES})


def write_frame(writer: FrameWriter, sim: dem.Simulation) -> None:
    writer.write_frame(sim.time_s, {"positions": sim.x, "velocities": sim.v,
                                    "displacements": sim.x - sim.x0},
                       step=sim.step, kinetic_energy=sim.kinetic_energy_j(),
                       momentum=sim.momentum(), potential_energy=sim.potential_energy_j(),
                       elastic_energy=sim.elastic_energy_j())


def fields_wanted(sim: dem.Simulation, wanted: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The fields the due step needs, built only then: velocity [n, 3] m/s, displacement
    [n, 3] m (a view of X_magnitude gets X; the API takes the magnitude)."""
    builders = {"velocity": lambda: sim.v, "displacement": lambda: sim.x - sim.x0}
    return {name: make() for name, make in builders.items()
            if name in wanted or f"{name}_magnitude" in wanted}


def run(opts: Options, log: TextIO | None = None) -> Summary:
    """Pour, lift the gate, collapse: a frame to opts.out every output_interval_s, and at
    every step `due`/`publish` through minority.insitu (when opts.publish)."""
    log = log if log is not None else sys.stderr
    scene = opts.scene

    def say(msg: str) -> None:
        if opts.progress:
            print(msg, file=log, flush=True)

    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(max(1, min(opts.threads, numba.config.NUMBA_NUM_THREADS)))
    try:
        return _run(opts, scene, say, log)
    finally:
        numba.set_num_threads(threads)


def _run(opts: Options, scene: dem.Scene, say, log: TextIO) -> Summary:
    sim = dem.Simulation(scene)
    say(f"dem_column: {sim.n} spheres of {scene.diameter_m * 1e3:.2f} mm, dt {sim.dt_s:.3g} s "
        f"({scene.steps_per_frame} steps per {scene.output_interval_s} s frame; contact period "
        f"{scene.contact_period_s:.3g} s), pouring ...")
    t0 = time.perf_counter()
    sim.pour()
    pour_wall = time.perf_counter() - t0
    runout0, height0 = dem.runout_m(sim.x), dem.height_m(sim.x)
    say(f"dem_column: poured in {sim.pour_s:.3f} s simulated ({pour_wall:.1f} s wall): column "
        f"{runout0:.3f} m long, {height0:.3f} m high; the gate lifts")
    bounds = (tuple(scene.bounds_m[:, 0]), tuple(scene.bounds_m[:, 1]))  # (lo, hi), m
    total_steps = (scene.frames - 1) * scene.steps_per_frame
    insitu_s = 0.0
    with contextlib.ExitStack() as stack:
        writer = (stack.enter_context(trajectory_writer(opts.out, sim))
                  if opts.out is not None else None)
        viz = None
        if opts.publish:
            from minority.insitu import connect

            viz = stack.enter_context(connect(
                opts.run, rank=0, ranks=1, connect=opts.connect, record=opts.record,
                spec=opts.spec, wait_s=opts.wait_s, particles=sim.n, log=log))
            viz.event(EventKind.RUN_START, f"DEM column collapse, {sim.n} spheres", {
                "scene": scene.name, "ranks": 1, "particles": sim.n,
                "simulator": "DEM (examples/dem_column)",
                "spec_version": viz.spec.version if viz.spec else None})
        loop0 = time.perf_counter()
        while True:
            if writer is not None and sim.step % scene.steps_per_frame == 0:
                write_frame(writer, sim)
            if viz is not None:
                c0 = time.perf_counter()
                if viz.due(sim.step, sim.time_s):
                    viz.publish(sim.step, sim.time_s, sim.x, fields_wanted(sim, viz.wanted),
                                ids=sim.ids, spacing_m=scene.diameter_m, bounds_m=bounds)
                insitu_s += time.perf_counter() - c0
            if sim.step >= total_steps:
                break
            sim.advance()
            if sim.step % (10 * scene.steps_per_frame) == 0:
                say(f"dem_column: t = {sim.time_s:.2f} s, runout {dem.runout_m(sim.x):.3f} m, "
                    f"height {dem.height_m(sim.x):.3f} m")
        wall = time.perf_counter() - loop0
    summary = Summary(sim.n, scene.diameter_m, sim.dt_s, sim.pour_steps, sim.step,
                      writer.frames if writer is not None else 0, pour_wall, wall, insitu_s,
                      (runout0, dem.runout_m(sim.x)), (height0, dem.height_m(sim.x)),
                      viz.summary() if viz is not None else {})
    say(f"dem_column: {sim.step} steps in {wall:.1f} s wall ({sim.n * sim.step / wall / 1e6:.2f} "
        f"M particle-steps/s), in situ calls {insitu_s:.2f} s; runout {runout0:.3f} -> "
        f"{summary.runout_m[1]:.3f} m, height {height0:.3f} -> {summary.height_m[1]:.3f} m"
        + (f"; {summary.frames} frames in {opts.out}" if opts.out is not None else ""))
    return summary


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python examples/dem_column/run.py",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="A DEM granular column collapse (spheres; spring-dashpot contacts with\n"
        "Coulomb friction, spin and rolling resistance; numba), poured behind a gate that\n"
        "lifts at t = 0. It writes its frames to HDF5 in minority's trajectory layout and\n"
        "publishes through minority.insitu as any simulation would: next to `minority serve`\n"
        "serving the run's spec it sends what the spec asks (frames rendered, everything\n"
        "logged to MCAP); without a server it runs on, recording to --record if given.",
        epilog="examples:\n"
        "  minority serve --spec examples/dem_column/spec.json --out frames/ &\n"
        "  python examples/dem_column/run.py --out dem.h5          # next to it: frames/dem_column/\n"
        "  python examples/dem_column/run.py --particles 500 --duration 0.3 --no-publish --out s.h5\n"
        "  python examples/dem_column/run.py --spec examples/dem_column/spec.json --record d.mcap\n"
        "method and costs: examples/dem_column/README.md")
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE,
                   metavar="FILE.toml",
                   help="a scene TOML of dem.Scene's fields (default: %(default)s)")
    p.add_argument("--particles", type=int, default=None,
                   metavar="N",
                   help="about this many spheres: the column's size stays, the diameter "
                   "shrinks to fit (default: the scene's diameter, 3,255 spheres)")
    p.add_argument("--duration", type=float, default=None,
                   metavar="S",
                   help="simulated time of the collapse after the gate lifts, s (default: "
                   "the scene's, 0.5)")
    p.add_argument("--out", type=Path, default=None,
                   metavar="FILE.h5",
                   help="write the trajectory to this HDF5 file (a frame every "
                   "output_interval_s; default: none)")
    p.add_argument("--run", default="dem_column",
                   metavar="ID",
                   help="run id: the server serves the spec of this run (default: %(default)s)")
    p.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="zenoh endpoint of the render server, repeatable (default: "
                   "tcp/127.0.0.1:7447)")
    p.add_argument("--spec", type=Path, default=None,
                   metavar="FILE.json",
                   help="a spec file to follow when no server serves the run's spec")
    p.add_argument("--record", type=Path, default=None, metavar="FILE.mcap",
                   help="record what is published (or would be, without a server) to MCAP")
    p.add_argument("--wait", type=float, default=0.0,
                   metavar="S",
                   help="keep trying to reach the server this long, s (default: 0)")
    p.add_argument("--no-publish", action="store_true", help="no network at all")
    p.add_argument("--threads", type=int, default=1,
                   metavar="N",
                   help="numba threads for the contact forces (default: %(default)s)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        scene = dem.load_scene(args.scene)
        if args.particles is not None:
            scene = scene.with_particles(args.particles)
        if args.duration is not None:
            scene = dem.replace_scene(scene, duration_s=args.duration)
        if args.threads < 1:
            raise ValueError(f"--threads must be at least 1, got {args.threads}")
    except ValueError as exc:
        print(f"run.py: error: {exc}", file=sys.stderr)
        return 2
    opts = Options(scene, args.out, args.run, not args.no_publish,
                   tuple(args.connect or ("tcp/127.0.0.1:7447",)), args.spec, args.record,
                   args.wait, threads=args.threads)
    summary = run(opts)
    if args.json:
        print(json.dumps(summary.to_dict()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
