"""MPM throughput benchmark: one JSON line per scene (13k, 100k, ~1M particles).

    python -P bench/sim.py [--threads N] [--steps-13k S] [--steps-100k S] [--steps-1m S]

Run with -P (safe path): otherwise this file, named sim.py, shadows the sim package.
JIT compilation and the first step are excluded from the timing; the timed steps use the
CFL time step of the collapsing column (Drucker-Prager sand) from rest.
"""

from __future__ import annotations

import argparse
import json
import time

import numba

from sim.driver import Simulator
from sim.scene import builtin_scene_path, load_scene

SCENES = (("column_13k", 200), ("column_100k", 50), ("column_1m", 5))
WARMUP_STEPS = 2


def bench_scene(name: str, steps: int, threads: int) -> dict:
    sim = Simulator(load_scene(builtin_scene_path(name)), threads=threads)
    for _ in range(WARMUP_STEPS):  # compile (or load the cache) and touch memory
        sim.step(sim.stable_dt())
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step(sim.stable_dt())
    seconds = time.perf_counter() - t0
    n = sim.particles.n
    return {"bench": "sim", "particles": n, "threads": threads, "steps": steps,
            "seconds": round(seconds, 4), "particle_steps_per_s": round(n * steps / seconds),
            "material": "drucker_prager", "scene": name}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=numba.config.NUMBA_NUM_THREADS)
    for name, steps in SCENES:
        parser.add_argument(f"--steps-{name.split('_')[1]}", type=int, default=steps)
    args = parser.parse_args()
    for name, _ in SCENES:
        steps = getattr(args, f"steps_{name.split('_')[1]}")
        if steps > 0:
            print(json.dumps(bench_scene(name, steps, args.threads)), flush=True)


if __name__ == "__main__":
    main()
