"""The reference paper's table: the whole pipeline per in situ step, one JSON line per size.

    python -m bench.paper_table [--scenes column_13k column_100k column_1m] [--steps 2000 400 60]

Run as a module from the repository root, on a quiet machine. For each scene: the render
server runs in its own process pinned to core 1 (`minority serve --exit-when-done`, one
1024x768 view, every 20th step rendered, all particles with their displacement); the
simulation runs as 1 rank in this process, pinned to core 0 with one numba thread, twice
for --steps steps from rest: first without publishing, then publishing to the server.

{"bench": "paper_table", "scene", "particles", "steps", "repeats", "rendered_steps",
 "skipped_steps", "receive_s", "setup_s", "render_s", "total_s", "sim_step_s", "viz_overhead",
 "viz_overhead_median", "prepare_s", "stats_s", "sent_mb"}

    receive_s, setup_s, render_s, total_s   mean per rendered step, from the server's log
                                            (as `minority report` computes them)
    rendered_steps   steps rendered over all runs; skipped_steps: per publishing run, the
                     steps published but not rendered (a newer step replaced it before the
                     server was free: its first frame, cold, takes ~0.6 s at 13k)
    sim_step_s       the sim's stepping wall time per step without publishing (fastest run)
    viz_overhead     fastest stepping wall time when publishing / fastest without - 1, over
                     --repeats alternated runs (each publishing run with a fresh server);
                     viz_overhead_median the same from the medians
    prepare_s, stats_s, sent_mb   the sim thread's own share of publishing (cull, encode,
                     queue; Stats) in s and the MB it sent, medians over the publishing runs

The reference paper (Galaxy, 13k / 100k / 1M particles): 0.224 / 2.521 / 3.376 s per in situ
step; its companion paper reports a 2 % amortized cost to the simulation.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np

RUN = "paper"
EVERY = 20
SIM_CORE, SERVER_CORE = 0, 1
KEYS = {"paper_table": ("scene", "particles", "steps", "repeats", "rendered_steps",
                        "skipped_steps", "receive_s", "setup_s", "render_s", "total_s",
                        "sim_step_s", "viz_overhead", "viz_overhead_median", "prepare_s",
                        "stats_s", "sent_mb")}


def spec_for(scene: Path):
    from minority.gns.oracle import fit_camera
    from minority.protocol.spec import Spec

    size = np.array(tomllib.loads(scene.read_text())["domain"]["size_m"], float)
    lo, hi = np.zeros(3), np.array([size[0] * 0.6, size[1], size[2]])
    return Spec.from_dict({"version": 2, "run": RUN, "views": [{
        "name": "side", "camera": fit_camera(lo, hi, (0, 1, 0), (0, 0, 1), 4 / 3).to_dict(),
        "width": 1024, "height": 768, "field": "displacement", "range": [0.0, 0.4],
        "schedule": [{"every_steps": EVERY}]}]})


def run_sim(scene: Path, steps: int, publish) -> tuple[float, dict]:
    from minority.sim.ranks import RankRunConfig, run_ranks

    config = RankRunConfig(scene_path=scene, out=None, threads=1, progress=False,
                           publish=publish, run=RUN, wait_s=30.0 if publish else 0.0,
                           max_steps=steps)
    with open(os.devnull, "w") as quiet:
        summary = run_ranks(config, stream=quiet)
    return summary.loop_wall_s, summary.publish


def serve_and_publish(scene: Path, steps: int, spec_path: Path, log: Path,
                      work: Path) -> tuple[float, dict]:
    """Start a server (pinned to its core), run the sim publishing to it, wait for the
    server to render the last step and exit; returns the sim's stepping wall time (s) and
    its publishing summary."""
    from minority.demo import free_port
    from minority.insitu.publisher import PublishOptions
    from minority.protocol.session import NetworkOptions

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open(log.with_suffix(".server.log"), "w") as server_log:
        server = subprocess.Popen(
            [sys.executable, "-m", "minority", "serve", "--spec", str(spec_path), "--out",
             str(work / "frames"), "--record", str(log), "--listen", endpoint,
             "--exit-when-done"], stdout=subprocess.DEVNULL, stderr=server_log,
            preexec_fn=lambda: os.sched_setaffinity(0, {SERVER_CORE}),
            env={**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"})
        try:
            result = run_sim(scene, steps, PublishOptions(
                network=NetworkOptions(connect=[endpoint]), stats_every_s=0.005))
            server.wait(timeout=600)
        finally:
            if server.poll() is None:
                server.kill()
                server.wait()
    return result


def measure(scene_name: str, steps: int, work: Path, repeats: int) -> dict:
    from minority.protocol.costs import step_accounting
    from minority.report import load_run, timing_table
    from minority.sim.scene import builtin_scene_path

    scene = builtin_scene_path(scene_name)
    spec_path = work / f"{scene_name}.json"
    spec_for(scene).save(spec_path)
    quiet, loud, published = [], [], []
    for k in range(repeats):  # alternated, so that drift hits both alike
        quiet.append(run_sim(scene, steps, None)[0])
        wall, pub = serve_and_publish(scene, steps, spec_path, work / f"{scene_name}.{k}.mcap",
                                      work)
        loud.append(wall)
        published.append(pub)
    steps_timed, skipped = [], []
    for k in range(repeats):
        log = load_run(work / f"{scene_name}.{k}.mcap")
        table = timing_table(log)
        steps_timed += table.steps
        skipped.append(len(step_accounting(log, table).unrendered))
    mean = {p: float(np.mean([getattr(s, f"{p}_s") for s in steps_timed]))
            for p in ("receive", "setup", "render")}
    return {"bench": "paper_table", "scene": scene_name,
            "particles": max(s.particles for s in steps_timed), "steps": steps,
            "repeats": repeats, "rendered_steps": len(steps_timed), "skipped_steps": skipped,
            **{f"{p}_s": round(v, 4) for p, v in mean.items()},
            "total_s": round(sum(mean.values()), 4),
            "sim_step_s": round(min(quiet) / steps, 5),
            "viz_overhead": round(min(loud) / min(quiet) - 1.0, 4),
            "viz_overhead_median": round(float(np.median(loud) / np.median(quiet)) - 1.0, 4),
            # the sim thread's own share of publishing (cull, encode, queue; stats), median
            "prepare_s": round(float(np.median([p["prepare_s"] for p in published])), 4),
            "stats_s": round(float(np.median([p["stats_s"] for p in published])), 4),
            "sent_mb": round(float(np.median([p["bytes_sent"] for p in published])) / 1e6, 1)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", default=["column_13k", "column_100k", "column_1m"])
    p.add_argument("--steps", nargs="+", type=int, default=[2000, 400, 60],
                   help="steps per scene (every 20th is rendered)")
    p.add_argument("--repeats", type=int, default=3,
                   help="runs per scene with and without publishing (default 3; min is used)")
    p.add_argument("--keep", type=Path, metavar="DIR",
                   help="keep the specs, logs and frames in DIR (default: a temporary directory)")
    args = p.parse_args()
    if os.cpu_count() and os.cpu_count() < 2:
        sys.exit("bench.paper_table needs 2 cores (sim and server pinned apart)")
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    os.sched_setaffinity(0, {SIM_CORE})
    from minority.sim.scene import builtin_scene_path

    run_sim(builtin_scene_path("tiny"), 5, None)  # numba loads its kernels here, not in a run
    with tempfile.TemporaryDirectory(prefix="paper_table_") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for scene, steps in zip(args.scenes, args.steps, strict=True):
            print(json.dumps(measure(scene, steps, work, args.repeats)), flush=True)


if __name__ == "__main__":
    main()
