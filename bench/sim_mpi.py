"""MPM on MPI ranks with publishing: one JSON line per rank count.

    python -m bench.sim_mpi [--ranks 1 2] [--steps 200] [--scene column_100k] [--every 20]

{"bench": "sim_mpi", "scene", "particles", "ranks", "threads_per_rank", "steps",
 "loop_wall_s", "particle_steps_per_s", "publish_fraction", "efficiency",
 "compute_cpu_efficiency", "chunks_sent", "chunks_dropped", "chunks_received", "bytes_sent",
 "rebalances", "migrated", "rank_particles", "rank_compute_cpu_s", "rank_phases_s"}

Run as a module from the repository root. The benchmark process is the server side: a
listening zenoh peer on loopback that serves a spec asking for every particle's
displacement every `--every` steps (a full publish) and counts the chunks it receives.
For each rank count it starts `mpiexec -n R python -m bench.sim_mpi --worker ...` (one
numba thread per rank); the ranks load the kernels on a tiny scene first, then step the
scene from rest for `--steps` steps through `sim.ranks.run_ranks`.

    particle_steps_per_s  particles * steps / wall time of the stepping loop (stepping,
                          exchanges, culling, encoding and queueing chunks)
    publish_fraction      share of that wall time the slowest rank spent preparing and
                          queueing chunks (the sender thread's puts are not in it)
    efficiency            particle_steps_per_s / (R * the 1-rank value); null without a
                          1-rank run before it
    compute_cpu_efficiency  the same from the CPU time each rank spent in the MPM phases
                          (bin, P2G, grid, G2P): load balance and per-rank work without
                          time lost to other processes on a shared machine, nor exchanges
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

RUN = "bench-mpi"
TIMEOUT_S = 600
KEYS = {"sim_mpi": ("scene", "particles", "ranks", "threads_per_rank", "steps", "loop_wall_s",
                    "particle_steps_per_s", "publish_fraction", "efficiency?",
                    "compute_cpu_efficiency?", "chunks_sent", "chunks_dropped",
                    "chunks_received", "bytes_sent", "rebalances", "migrated", "rank_particles",
                    "rank_compute_cpu_s", "rank_phases_s")}


def free_endpoint() -> str:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def bench_spec(every: int):
    from minority.protocol.spec import Spec

    return Spec.from_dict({"version": 1, "run": RUN, "views": [{
        "name": "side", "camera": {"position": [0.35, -1.2, 0.16],
                                   "focal_point": [0.35, 0.072, 0.12]},
        "field": "displacement", "range": [0.0, 0.38], "every_steps": every}]})


def worker(args: argparse.Namespace) -> None:
    """One rank (under mpiexec): warm up, run, rank 0 prints the JSON result."""
    from mpi4py import MPI

    from minority.insitu.publisher import PublishOptions
    from minority.protocol.session import NetworkOptions
    from minority.sim.ranks import RankRunConfig, run_ranks
    from minority.sim.scene import builtin_scene_path

    comm = MPI.COMM_WORLD
    warm = RankRunConfig(scene_path=builtin_scene_path("tiny"), out=None, threads=1,
                         progress=False, max_steps=25, rebalance_every=10)
    run_ranks(warm, comm)  # loads (or compiles) every kernel the run uses
    cfg = RankRunConfig(
        scene_path=builtin_scene_path(args.scene), out=None, threads=1, progress=False,
        run=RUN, max_steps=args.steps,
        publish=PublishOptions(network=NetworkOptions(connect=[args.connect])))
    s = run_ranks(cfg, comm)
    if comm.Get_rank() == 0:
        p = s.publish
        print(json.dumps({
            "bench": "sim_mpi", "particles": s.particles, "ranks": s.ranks,
            "particle_steps_per_s": round(s.particles * s.steps / s.loop_wall_s),
            "publish_fraction": round(p["prepare_s"] / s.loop_wall_s, 4),
            "steps": s.steps, "threads_per_rank": s.threads, "scene": args.scene,
            "loop_wall_s": round(s.loop_wall_s, 3), "chunks_sent": p["sent"],
            "chunks_dropped": p["dropped"], "bytes_sent": p["bytes_sent"],
            "rebalances": s.rebalances, "migrated": s.migrated,
            "rank_particles": s.rank_particles,
            "rank_compute_cpu_s": [round(c, 3) for c in s.rank_compute_cpu_s],
            "rank_phases_s": [{k: round(v, 3) for k, v in ph.items()} for ph in s.rank_phases_s]}),
              flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--scene", default="column_100k")
    parser.add_argument("--every", type=int, default=20, help="publish every N-th step")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--connect", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return

    from minority.protocol import keys
    from minority.protocol.session import NetworkOptions, Role, open_session
    from minority.sim.launcher import RELAUNCH_ENV, mpiexec_path

    endpoint = free_endpoint()
    session = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    spec = bench_spec(args.every).encode()
    received = {"chunks": 0, "bytes": 0}
    arrived = threading.Condition()

    def on_chunk(sample) -> None:
        with arrived:
            received["chunks"] += 1
            received["bytes"] += len(sample.payload)
            arrived.notify_all()

    queryable = session.declare_queryable(keys.spec(RUN), lambda q: q.reply(keys.spec(RUN),
                                                                             bytes(spec)))
    sink = session.declare_subscriber(keys.chunks(RUN), on_chunk)
    base = None
    try:
        for ranks in args.ranks:
            with arrived:
                received.update(chunks=0, bytes=0)
            cmd = [str(mpiexec_path()), "-n", str(ranks), sys.executable, "-m", "bench.sim_mpi",
                   "--worker", "--connect", endpoint, "--steps", str(args.steps), "--scene",
                   args.scene]
            env = {**RELAUNCH_ENV, **os.environ, "NUMBA_NUM_THREADS": "1"}
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S,
                                  env=env, cwd=Path(__file__).resolve().parent.parent)
            if proc.returncode != 0:
                sys.exit(f"bench.sim_mpi: {ranks} ranks failed:\n{proc.stderr[-4000:]}")
            result = json.loads(proc.stdout.strip().splitlines()[-1])
            with arrived:  # the sink's count catches up (reported, not required)
                sent = result["chunks_sent"]
                arrived.wait_for(lambda sent=sent: received["chunks"] >= sent, 10.0)
                result["chunks_received"] = received["chunks"]
            if ranks == 1:
                base = result
            result["efficiency"] = result["compute_cpu_efficiency"] = None
            if base:
                result["efficiency"] = round(result["particle_steps_per_s"]
                                             / (ranks * base["particle_steps_per_s"]), 3)
                # the same from the CPU time of the compute phases: what the ranks would
                # reach on cores of their own (exchanges not included)
                result["compute_cpu_efficiency"] = round(
                    base["rank_compute_cpu_s"][0] / (ranks * max(result["rank_compute_cpu_s"])), 3)
            print(json.dumps(result), flush=True)
    finally:
        sink.undeclare()
        queryable.undeclare()
        session.close()


if __name__ == "__main__":
    main()
