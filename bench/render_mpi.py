"""Distributed rendering benchmark (render_server.render_mpi): one step on N MPI ranks.

Steps: the 1M-particle showcase column (sim/scenes/column_1m.toml, its 829,440 particles as
the MPM seeds them, in the sim's order) and a synthetic 8M-particle step (uniform random
positions in the same column box, random order). One aerial view at 1024x768 and 2048x1536.
N = 1 with 2 numba threads, N = 2 with 1 thread each (on a 2-core machine: the same cores).
Each rank starts with its share as the wire bytes of one Chunk (1/N of the rows, as if it
had received them from its sim ranks). Prints one JSON line per configuration:

{"bench": "render_mpi", "particles", "width", "height", "ranks", "threads", "receive_s",
 "exchange_s", "setup_s", "render_s", "composite_s", "total_s", "peak_rss_bytes": [per rank],
 "counts": [particles per rank after the exchange]}

receive_s: decoding the rank's chunk (protocol checks, no network); exchange_s: sample, k-d
tree, classification, Alltoallv; setup_s: bricks; render_s: ray casting and shading;
composite_s: direct-send compositing and the gather to rank 0; total_s: receive plus the
whole distributed step. Each phase is the slowest rank's, the median of REPEATS steps after
one warm-up step; peak RSS is each process's maximum resident set (ru_maxrss), which includes
the interpreter, numba and MPI (the "baseline_rss_bytes" line says how much: a process that
imported everything and rendered a tiny step).

Then "render_mpi_model" lines: time per step for N = 1 .. 64 ranks from the measured costs
(per particle of setup and render, per pixel of render and compositing, per particle moved,
per message), one core per rank: t(N) = c_recv n/N + c_move n/N (N-1)/N + c_msg (N - 1)
+ c_part n/N + c_pix P + c_comp P (N-1)/N + c_gather P/N (N - 1).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

RUN = "bench-render-mpi"
SIZES = ((1024, 768), (2048, 1536))
COLUMN_BOX_M = ((0.0, 0.0, 0.0), (0.144, 0.144, 0.32))
DOMAIN_M = ((0.0, 0.0, 0.0), (0.8, 0.144, 0.4))
REPEATS = 3
CAMERA = {"position": [0.55, -0.45, 0.45], "focal_point": [0.072, 0.072, 0.14],
          "view_up": [0, 0, 1], "view_angle_deg": 30}
MODEL_RANKS = (1, 2, 4, 8, 16, 32, 64)
TIMEOUT_S = 1800


def column_share(rank: int, ranks: int) -> tuple[np.ndarray, np.ndarray, float]:
    """This rank's contiguous share of the showcase column's particles as the MPM seeds them
    (lattice points (i + 1/2) * spacing in the column's box, x-major, the sim's id order):
    positions [k, 3] float32 m, displacement [k, 3] float32 m (zero at seeding: a ramp in
    height instead, for colour), spacing m."""
    from minority.sim.scene import builtin_scene_path, load_scene

    scene = load_scene(builtin_scene_path("column_1m"))
    s = scene.particle_spacing_m
    body = scene.bodies[0]
    axes = [(np.arange(round(lo / s), round(hi / s)) + 0.5) * s
            for lo, hi in zip(body.lo_m, body.hi_m, strict=True)]
    counts = [len(a) for a in axes]
    n = int(np.prod(counts))
    rows = np.arange(n * rank // ranks, n * (rank + 1) // ranks)
    i, j, k = np.unravel_index(rows, counts)
    pos = np.c_[axes[0][i], axes[1][j], axes[2][k]].astype(np.float32)
    disp = np.zeros_like(pos)
    disp[:, 0] = pos[:, 2]
    return pos, disp, s


def random_share(n: int, rank: int, ranks: int) -> tuple[np.ndarray, np.ndarray, float]:
    """This rank's 1/N of n uniform random particles in the column box (generated here:
    no rank ever holds the whole step)."""
    rng = np.random.default_rng(1000 + rank)
    k = n * (rank + 1) // ranks - n * rank // ranks
    lo, hi = np.array(COLUMN_BOX_M)
    pos = (lo + (hi - lo) * rng.random((k, 3), dtype=np.float32)).astype(np.float32)
    disp = np.zeros_like(pos)
    disp[:, 0] = pos[:, 2]
    spacing = float(np.prod(hi - lo) / n) ** (1 / 3)
    return pos, disp, spacing


def view(width: int, height: int):
    from minority.protocol.spec import Spec

    return Spec.from_dict({"version": 2, "run": RUN, "views": [{
        "name": "aerial", "camera": CAMERA, "width": width, "height": height,
        "field": "displacement", "colormap": "Cool to Warm", "range": [0.0, 0.32],
        "annotations": False}]}).views[0]


def message_cost(comm, rounds: int = 200) -> float:
    """Seconds per small message: an 8-byte Alltoall, per peer."""
    from mpi4py import MPI

    if comm.size == 1:
        return 0.0
    send, recv = np.zeros(comm.size), np.zeros(comm.size)
    comm.Barrier()
    t0 = time.perf_counter()
    for _ in range(rounds):
        comm.Alltoall([send, MPI.DOUBLE], [recv, MPI.DOUBLE])
    return (time.perf_counter() - t0) / rounds / (comm.size - 1)


def worker(kind: str, n: int, threads: int) -> None:
    """One mpiexec job: every image size, REPEATS + 1 steps each; rank 0 prints JSON."""
    import numba
    from minority.protocol import Chunk, decode_as
    from minority.render_server.render_mpi import Layers, render_step_distributed
    from mpi4py import MPI

    numba.set_num_threads(threads)
    comm = MPI.COMM_WORLD
    if kind == "baseline":  # what a process costs before any particle: tiny step
        pos, disp, spacing = random_share(4096, comm.rank, comm.size)
    else:
        pos, disp, spacing = (column_share(comm.rank, comm.size) if kind == "column"
                              else random_share(n, comm.rank, comm.size))
    payload = Chunk(RUN, 1, 1e-3, comm.rank, comm.size, spacing, DOMAIN_M,
                    {"positions": pos, "displacement": disp}).encode()
    del pos, disp  # the rank holds its received bytes, as a server does
    msg_s = message_cost(comm)
    for width, height in (SIZES[:1] if kind == "baseline" else SIZES):
        v = view(width, height)
        canvases, layers, rows = {}, Layers(), []
        for rep in range(REPEATS + 1):
            comm.Barrier()
            t0 = time.perf_counter()
            chunk = decode_as(payload, Chunk)
            receive_s = time.perf_counter() - t0
            _, times = render_step_distributed(
                comm, chunk.positions, {"displacement": chunk.fields["displacement"]},
                0.5 * spacing, [v], canvases=canvases, layers=layers)
            total_s = time.perf_counter() - t0
            phases = [receive_s, times.exchange_s, times.setup_s, times.render_s,
                      times.composite_s, total_s]
            slowest = np.array(phases)
            comm.Allreduce(MPI.IN_PLACE, slowest, op=MPI.MAX)
            if rep:
                rows.append(slowest)
            del chunk
        rss = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, root=0)
        if comm.rank == 0:
            med = np.median(np.array(rows), axis=0)
            names = ("receive_s", "exchange_s", "setup_s", "render_s", "composite_s", "total_s")
            line = {"bench": "render_mpi" if kind != "baseline" else "baseline_rss_bytes",
                    "particles": int(sum(times.counts)), "width": width,
                    "height": height, "ranks": comm.size, "threads": threads,
                    **{k: round(float(x), 4) for k, x in zip(names, med, strict=True)},
                    "peak_rss_bytes": rss, "counts": times.counts, "message_s": msg_s}
            print(json.dumps(line), flush=True)


def shadow_needs(ranks: int = 2) -> dict:
    """Why shadows are refused on several ranks, measured on the 1M column: the particles
    each rank would have to hold besides its own brick to cast its own shadow rays (those
    lying between its brick and the key light: the ray from the particle away from the
    light meets the brick, grown by a radius), and the bytes of shadow-ray starts
    (3 float64 per lit pixel) each rank would receive per view if the rays crossed ranks."""
    from minority.render_server.distribute import build_tree, classify
    from minority.render_server.render import key_light

    pos, _, spacing = column_share(0, 1)
    keys = np.arange(len(pos), dtype=np.int64)
    lo, hi = pos.min(axis=0).astype(np.float64), pos.max(axis=0).astype(np.float64)
    tree = build_tree(pos[::max(1, len(pos) // 65536)].astype(np.float64),
                      keys[::max(1, len(pos) // 65536)], ranks, lo, hi)
    owner = classify(pos, keys, tree)
    v = view(*SIZES[0])
    toward = -key_light(v)  # from a blocker back toward the surface it shades
    r = 0.5 * spacing
    extra = []
    for rank in range(ranks):
        box_lo, box_hi = tree.boxes[rank, 0] - r, tree.boxes[rank, 1] + r
        p = pos[owner != rank].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (box_lo - p) / toward
            tb = (box_hi - p) / toward
        t0 = np.nanmax(np.minimum(ta, tb), axis=1)
        t1 = np.nanmin(np.maximum(ta, tb), axis=1)
        extra.append(int(np.count_nonzero(t1 >= np.maximum(t0, 0.0))))
    own = np.bincount(owner, minlength=ranks)
    return {"bench": "render_mpi_shadows", "particles": len(pos), "ranks": ranks,
            "own": own.tolist(), "extra_for_shadows": extra,
            "extra_over_own": [round(float(e / o), 3) for e, o in zip(extra, own, strict=True)],
            "ray_start_bytes_per_view": SIZES[0][0] * SIZES[0][1] * 24}


def launch(kind: str, n: int, ranks: int, threads: int) -> list[dict]:
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    cmd = [mpiexec, "-n", str(ranks), sys.executable, "-m", "bench.render_mpi", "--worker",
           kind, "--particles", str(n), "--threads", str(threads)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "NUMBA_NUM_THREADS": str(threads)})
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


def model(one: dict, two: dict, big_one: dict, big_two: dict) -> list[dict]:
    """Per-step time for N ranks from the N = 2 runs at two image sizes (same step), with
    the N = 1 run for receive (per particle)."""
    n, pix, big_pix = one["particles"], one["width"] * one["height"], big_one["width"] * big_one["height"]
    half = n / 2
    c_recv = two["receive_s"] / half
    c_move = two["exchange_s"] / (half / 2)  # per particle moved; about half move at N = 2
    c_pix = max(big_two["render_s"] - two["render_s"], 0.0) / (big_pix - pix)
    c_part = max(two["render_s"] + two["setup_s"] - c_pix * pix, 0.0) / half
    c_comp = two["composite_s"] / (pix / 2)
    c_msg = two["message_s"]
    out = []
    for ranks in MODEL_RANKS:
        share, other = n / ranks, (ranks - 1) / ranks
        parts = {"receive_s": c_recv * share,
                 "exchange_s": (c_move * share * other + c_msg * (ranks - 1)) if ranks > 1 else 0.0,
                 "render_s": c_part * share + c_pix * pix,
                 "composite_s": (c_comp * pix * other + c_msg * 2 * (ranks - 1)) if ranks > 1
                 else 0.0}
        out.append({"bench": "render_mpi_model", "particles": n, "width": one["width"],
                    "height": one["height"], "ranks": ranks,
                    **{k: round(v, 4) for k, v in parts.items()},
                    "total_s": round(sum(parts.values()), 4)})
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m bench.render_mpi",
        description="Render one step on 1 and 2 MPI ranks (the 1M column, a random 8M step; "
                    "1024x768 and 2048x1536): phase times, peak RSS, and a model for up to "
                    "64 ranks. Prints JSON lines.")
    parser.add_argument("--large", type=int, default=8_000_000,
                        help="particles of the synthetic step (default 8,000,000; 0: skip it)")
    parser.add_argument("--worker", choices=("column", "random", "baseline"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--particles", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        try:
            worker(args.worker, args.particles, args.threads)
        except BaseException:  # one rank failing must not leave the others waiting
            import traceback

            from mpi4py import MPI

            traceback.print_exc()
            sys.stderr.flush()
            MPI.COMM_WORLD.Abort(1)
        return
    print(json.dumps(shadow_needs()), flush=True)
    for line in launch("baseline", 0, 1, 2):
        print(json.dumps(line), flush=True)
    steps = [("column", 0)] + ([("random", args.large)] if args.large else [])
    for kind, n in steps:
        rows = {}
        for ranks, threads in ((1, 2), (2, 1)):
            for line in launch(kind, n, ranks, threads):
                rows[ranks, line["width"]] = line
                print(json.dumps(line), flush=True)
        for width, _ in SIZES:
            one, two = rows[1, width], rows[2, width]
            ratio = {"bench": "render_mpi_ratio", "particles": one["particles"], "width": width,
                     "total_2_over_1": round(two["total_s"] / one["total_s"], 3),
                     "composite_share_2": round(two["composite_s"] / two["total_s"], 3),
                     "rss_2_over_1": round(max(two["peak_rss_bytes"])
                                           / one["peak_rss_bytes"][0], 3)}
            print(json.dumps(ratio), flush=True)
        w0, w1 = SIZES[0][0], SIZES[1][0]
        for line in model(rows[1, w0], rows[2, w0], rows[1, w1], rows[2, w1]):
            print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
