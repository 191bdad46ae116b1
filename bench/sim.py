"""MPM throughput benchmark: two JSON lines per scene (13k, 100k, ~1M particles).

{"bench": "sim", "scene", "particles", "threads", "material", "window", "from_step",
 "from_time_s", "steps", "seconds", "particle_steps_per_s", "phase_fraction"}

    python -m bench.sim [--threads N] [--steps-13k S] [--steps-100k S] [--steps-1m S]
                        [--loaded-at-s T]

Run as a module from the repository root (as the Makefile does). JIT compilation and the
warm-up steps are excluded from the timing; the timed steps use the CFL time step of the
collapsing column (Drucker-Prager sand). Per scene, `window` "start" times the first S
steps from rest: at 100k and 1M they end within ~3 ms, before the P-wave (~39 m/s) has
crossed the 0.32 m column, so most particles are still unstressed and the return mapping
is cheap; at 13k (a larger time step) the 200 steps run to ~0.025 s, through the crossing.
"loaded" times S steps from sim time T s (default 0.015 s) or from where "start" ended,
whichever is later: every particle stressed, the collapse itself. `from_step` and
`from_time_s` give where each window began. `phase_fraction` splits the timed
wall time into binning (sort and the periodic permutation), P2G (scatter into per-block
buffers), grid (buffer sum per node fused with the grid update) and G2P (with the return
mapping).
"""

from __future__ import annotations

import argparse
import json
import time

import numba

from minority.sim.driver import PhaseTimes, Simulator
from minority.sim.scene import builtin_scene_path, load_scene

SCENES = (("column_13k", 200), ("column_100k", 50), ("column_1m", 5))
WARMUP_STEPS = 2
LOADED_AT_S = 0.015  # s; the P-wave (~39 m/s) crosses the 0.32 m column in ~8 ms
KEYS = {"sim": ("scene", "particles", "threads", "material", "window", "from_step",
                "from_time_s", "steps", "seconds", "particle_steps_per_s", "phase_fraction")}


def _timed(sim: Simulator, name: str, steps: int, threads: int, window: str) -> dict:
    sim.times = PhaseTimes()
    from_step, from_s = sim.step_count, sim.time_s
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step(sim.stable_dt())
    seconds = time.perf_counter() - t0
    n = sim.particles.n
    return {"bench": "sim", "particles": n, "threads": threads, "steps": steps,
            "seconds": round(seconds, 4), "particle_steps_per_s": round(n * steps / seconds),
            "material": "drucker_prager", "scene": name, "window": window,
            "from_step": from_step, "from_time_s": round(from_s, 6),
            "phase_fraction": {k: round(getattr(sim.times, k) / seconds, 3)
                               for k in ("bin", "p2g", "grid", "g2p")}}


def bench_scene(name: str, steps: int, threads: int, loaded_at_s: float):
    """Yield the "start" line, then (loaded_at_s > 0) the "loaded" one."""
    sim = Simulator(load_scene(builtin_scene_path(name)), threads=threads)
    for _ in range(WARMUP_STEPS):  # compile (or load the cache) and touch memory
        sim.step(sim.stable_dt())
    yield _timed(sim, name, steps, threads, "start")
    if loaded_at_s > 0.0:
        while sim.time_s < loaded_at_s:
            sim.step(sim.stable_dt())
        yield _timed(sim, name, steps, threads, "loaded")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=numba.config.NUMBA_NUM_THREADS)
    for name, steps in SCENES:
        parser.add_argument(f"--steps-{name.split('_')[1]}", type=int, default=steps)
    parser.add_argument("--loaded-at-s", type=float, default=LOADED_AT_S,
                        help="sim time (s) where the loaded window starts; 0 skips it "
                        f"(default {LOADED_AT_S})")
    args = parser.parse_args()
    for name, _ in SCENES:
        steps = getattr(args, f"steps_{name.split('_')[1]}")
        if steps > 0:
            for line in bench_scene(name, steps, args.threads, args.loaded_at_s):
                print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
