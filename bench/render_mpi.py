"""Distributed rendering benchmark (render_server.render_mpi): one step on N MPI ranks.

Steps: the 1M-particle showcase column (sim/scenes/column_1m.toml, its 829,440 particles as
the MPM seeds them, in the sim's order) and a synthetic 8M-particle step (uniform random
positions in the same column box, random order). One aerial view at 1024x768 and 2048x1536.
N = 1 with 2 numba threads, N = 2 with 1 thread each (on a 2-core machine: the same cores).
Each rank starts with its share as the wire bytes of one Chunk (1/N of the rows, as if it
had received them from its sim ranks).

    python -m bench.render_mpi [--large N] [--scene column_1m] [--sizes 1024x768 2048x1536]

(`--scene tiny --sizes 64x48 128x96 --large 0`: a smoke test in seconds.) Prints one JSON
line per configuration:

{"bench": "render_mpi", "particles", "width", "height", "ranks", "threads", "receive_s",
 "exchange_s", "setup_s", "render_s", "composite_s", "total_s", "peak_rss_bytes": [per rank],
 "counts": [particles per rank after the exchange], "message_s"}

receive_s: decoding the rank's chunk (protocol checks, no network); exchange_s: the slab
test, sample, k-d tree, classification and the packed Alltoallv rounds (render_server.
distribute); setup_s: bricks; render_s: ray casting and shading; composite_s: sparse
direct-send compositing and the gather to rank 0; total_s: receive plus the whole
distributed step; message_s: one small message per peer (an 8-byte Alltoall). Each phase
is the slowest rank's, the median of REPEATS steps after one warm-up step; peak RSS is each
process's maximum resident set (ru_maxrss), which includes the interpreter, numba and MPI
(the "baseline_rss_bytes" lines, at N = 1 and 2, say how much: a process that imported
everything and rendered a tiny step, measured after a first such run that compiled every
kernel, so no peak includes compilation; the same keys as "render_mpi").

"render_mpi_shadows" (first): why shadows are refused on several ranks (shadow_needs):
{"bench": "render_mpi_shadows", "particles", "ranks", "own", "extra_for_shadows",
 "extra_over_own", "ray_start_bytes_per_view"}

"render_mpi_ratio" lines compare N = 2 with N = 1 per step and size (total time, the
composite's share of the N = 2 total, peak RSS, peak RSS above each one's baseline, and
rss_if_halved_2_over_1: the ratio an N = 2 rank would reach holding exactly half of what the
N = 1 process holds above its baseline, on top of its own baseline: the floor's limit, which
falls as the per-particle bytes grow and rises as they shrink):
{"bench": "render_mpi_ratio", "particles", "width", "total_2_over_1", "composite_share_2",
 "rss_2_over_1", "rss_above_baseline_2_over_1", "rss_if_halved_2_over_1"}

"render_mpi_model" lines: each step's time per step for N = 1 .. 64 ranks at 1024x768 from
its N = 2 costs (bench.render_mpi.costs: per particle of receive, exchange, setup plus
render; per pixel of render and composite; per message; bytes per particle), one core per
rank, messages at the measured shared-memory cost:
t(N) = c_recv n/N + c_move n/N 2(N-1)/N + c_msg (N-1) + c_part n/N + c_pix P + c_comp P
+ 2 c_msg (N-1), peak RSS per rank = baseline + bytes_per_particle n/N:
{"bench": "render_mpi_model", "particles", "width", "height", "ranks", "receive_s",
 "exchange_s", "render_s", "composite_s", "total_s", "peak_rss_bytes_per_rank"}
"render_mpi_large": what a LARGE_RUN-particle run would need on that model (per-particle
costs and bytes of the random step, the larger per-pixel costs of the two steps): ranks,
peak RSS per rank, time per step at 1024x768:
{"bench": "render_mpi_large", "particles", "width", "height", "ranks", "receive_s",
 "exchange_s", "render_s", "composite_s", "total_s", "peak_rss_bytes_per_rank",
 "pixel_floor_s", "costs_from", "memory_per_rank_limit", "step_s_limit"}
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
SCENE = "column_1m"
_STEP = ("particles", "width", "height", "ranks", "threads", "receive_s", "exchange_s", "setup_s",
         "render_s", "composite_s", "total_s", "peak_rss_bytes", "counts", "message_s")
_MODEL = ("particles", "width", "height", "ranks", "receive_s", "exchange_s", "render_s",
          "composite_s", "total_s", "peak_rss_bytes_per_rank")
KEYS = {"render_mpi_shadows": ("particles", "ranks", "own", "extra_for_shadows", "extra_over_own",
                               "ray_start_bytes_per_view"),
        "baseline_rss_bytes": _STEP, "render_mpi": _STEP,
        "render_mpi_ratio": ("particles", "width", "total_2_over_1", "composite_share_2",
                             "rss_2_over_1", "rss_above_baseline_2_over_1",
                             "rss_if_halved_2_over_1"),
        "render_mpi_model": _MODEL,
        "render_mpi_large": (*_MODEL, "pixel_floor_s", "costs_from", "memory_per_rank_limit",
                             "step_s_limit")}
COLUMN_BOX_M = ((0.0, 0.0, 0.0), (0.144, 0.144, 0.32))
DOMAIN_M = ((0.0, 0.0, 0.0), (0.8, 0.144, 0.4))
REPEATS = 3
CAMERA = {"position": [0.55, -0.45, 0.45], "focal_point": [0.072, 0.072, 0.14],
          "view_up": [0, 0, 1], "view_angle_deg": 30}
MODEL_RANKS = (1, 2, 4, 8, 16, 32, 64)
LARGE_RUN = 100_000_000  # particles of the run the "render_mpi_large" line sizes
MEMORY_PER_RANK = 4 << 30  # bytes: a core's share of a typical HPC node (e.g. 256 GB / 64)
STEP_S = 1.0  # s: the time per step that line aims for
TIMEOUT_S = 1800


def column_share(rank: int, ranks: int, scene_name: str = SCENE
                 ) -> tuple[np.ndarray, np.ndarray, float]:
    """This rank's contiguous share of the showcase column's particles as the MPM seeds them
    (lattice points (i + 1/2) * spacing in the column's box, x-major, the sim's id order):
    positions [k, 3] float32 m, displacement [k, 3] float32 m (zero at seeding: a ramp in
    height instead, for colour), spacing m."""
    from minority.sim.scene import builtin_scene_path, load_scene

    scene = load_scene(builtin_scene_path(scene_name))
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
    pos = rng.random((k, 3), dtype=np.float32)  # in place: no float64 copy inflates the peak
    pos *= (hi - lo).astype(np.float32)
    pos += lo.astype(np.float32)
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


def worker(kind: str, n: int, threads: int, scene: str = SCENE, sizes=SIZES) -> None:
    """One mpiexec job: every image size, REPEATS + 1 steps each; rank 0 prints JSON."""
    import numba
    from mpi4py import MPI

    from minority.protocol import Chunk, decode_as
    from minority.render_server.render_mpi import Layers, render_step_distributed

    numba.set_num_threads(threads)
    comm = MPI.COMM_WORLD
    if kind == "baseline":  # what a process costs before any particle: tiny step
        pos, disp, spacing = random_share(4096, comm.rank, comm.size)
    else:
        pos, disp, spacing = (column_share(comm.rank, comm.size, scene) if kind == "column"
                              else random_share(n, comm.rank, comm.size))
    payload = Chunk(RUN, 1, 1e-3, comm.rank, comm.size, spacing, DOMAIN_M,
                    {"positions": pos, "displacement": disp}).encode()
    del pos, disp  # the rank holds its received bytes, as a server does
    msg_s = message_cost(comm)
    for width, height in (sizes[:1] if kind == "baseline" else sizes):
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


def shadow_needs(ranks: int = 2, scene: str = SCENE, size=SIZES[0]) -> dict:
    """Why shadows are refused on several ranks, measured on the 1M column: the particles
    each rank would have to hold besides its own brick to cast its own shadow rays (those
    lying between its brick and the key light: the ray from the particle away from the
    light meets the brick, grown by a radius), and the bytes of shadow-ray starts
    (3 float64 per lit pixel) each rank would receive per view if the rays crossed ranks."""
    from minority.render_server.distribute import build_tree, classify
    from minority.render_server.render import key_light

    pos, _, spacing = column_share(0, 1, scene)
    keys = np.arange(len(pos), dtype=np.int64)
    lo, hi = pos.min(axis=0).astype(np.float64), pos.max(axis=0).astype(np.float64)
    tree = build_tree(pos[::max(1, len(pos) // 65536)].astype(np.float64),
                      keys[::max(1, len(pos) // 65536)], ranks, lo, hi)
    owner = classify(pos, keys, tree)
    v = view(*size)
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
            "ray_start_bytes_per_view": size[0] * size[1] * 24}


def launch(kind: str, n: int, ranks: int, threads: int, scene: str = SCENE,
           sizes=SIZES) -> list[dict]:
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    cmd = [mpiexec, "-n", str(ranks), sys.executable, "-m", "bench.render_mpi", "--worker",
           kind, "--particles", str(n), "--threads", str(threads), "--scene", scene,
           "--sizes", *(f"{w}x{h}" for w, h in sizes)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "NUMBA_NUM_THREADS": str(threads)})
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


def costs(two: dict, big_two: dict, base_two: dict) -> dict:
    """Unit costs from the N = 2 runs of one step at two image sizes (one core per rank):
    per particle held (receive, exchange, setup plus render), per pixel (render: the shading
    and capture passes every rank makes over the whole image; composite: counting, packing,
    merging and the gather), per message, and bytes per particle held (peak RSS over the
    N = 2 baseline process)."""
    half = two["particles"] / 2
    pix = two["width"] * two["height"]
    big_pix = big_two["width"] * big_two["height"]
    drawn, big_drawn = two["render_s"] + two["setup_s"], big_two["render_s"] + big_two["setup_s"]
    c_pix = max(big_drawn - drawn, 0.0) / (big_pix - pix)
    c_msg = two["message_s"]
    return {"c_recv": two["receive_s"] / half,
            "c_move": two["exchange_s"] / half,  # at N = 2: (N - 1) / N of the input moves
            "c_part": max(drawn - c_pix * pix, 0.0) / half,
            "c_pix": c_pix,
            "c_comp": max(two["composite_s"] - 2 * c_msg, 0.0) / pix,
            "c_msg": c_msg,
            "bytes_per_particle": (max(two["peak_rss_bytes"]) - max(base_two["peak_rss_bytes"]))
            / half,
            "base_bytes": max(base_two["peak_rss_bytes"])}


def predict(c: dict, n: float, ranks: int, pix: int) -> dict:
    """Per-step phases on `ranks` ranks of n particles at pix pixels: receive and drawing
    divide by the rank count, the exchange moves (N - 1) / N of each rank's share (as in a
    random order; scaled from N = 2), messages grow as N - 1 per collective, and the
    per-pixel work stays on every rank (conservative: a brick covers less of the image the
    more ranks there are, which the sparse composite would turn into fewer bytes)."""
    share = n / ranks
    moved = (ranks - 1) / ranks / 0.5
    parts = {"receive_s": c["c_recv"] * share,
             "exchange_s": c["c_move"] * share * moved + c["c_msg"] * (ranks - 1)
             if ranks > 1 else 0.0,
             "render_s": c["c_part"] * share + c["c_pix"] * pix,
             "composite_s": c["c_comp"] * pix + 2 * c["c_msg"] * (ranks - 1) if ranks > 1
             else 0.0}
    return {**{k: round(v, 4) for k, v in parts.items()},
            "total_s": round(sum(parts.values()), 4),
            "peak_rss_bytes_per_rank": int(c["base_bytes"] + c["bytes_per_particle"] * share)}


def model(two: dict, big_two: dict, base_two: dict) -> list[dict]:
    """The step's time per step for N = 1 .. 64 ranks at the smaller image size."""
    c = costs(two, big_two, base_two)
    return [{"bench": "render_mpi_model", "particles": two["particles"], "width": two["width"],
             "height": two["height"], "ranks": ranks,
             **predict(c, two["particles"], ranks, two["width"] * two["height"])}
            for ranks in MODEL_RANKS]


def large_run(steps: list[tuple[dict, dict]], base_two: dict, n: int = LARGE_RUN) -> dict:
    """What n particles would need at the smaller image size: the per-particle costs and
    bytes of the last step (N = 2 runs at two sizes each), the largest per-pixel costs of
    any step (a step dominated by particles hides them); the fewest ranks (a power of two)
    whose peak RSS fits MEMORY_PER_RANK and whose step takes at most STEP_S, or the fastest
    rank count if none does."""
    each = [costs(two, big_two, base_two) for two, big_two in steps]
    c = {**each[-1], "c_pix": max(e["c_pix"] for e in each),
         "c_comp": max(e["c_comp"] for e in each)}
    two = steps[-1][0]
    pix = two["width"] * two["height"]
    options = [(ranks, predict(c, n, ranks, pix)) for ranks in (2 ** k for k in range(13))]
    fits = [(r, p) for r, p in options if p["peak_rss_bytes_per_rank"] <= MEMORY_PER_RANK]
    fits = fits or options
    good = [(r, p) for r, p in fits if p["total_s"] <= STEP_S]
    ranks, p = good[0] if good else min(fits, key=lambda rp: rp[1]["total_s"])
    return {"bench": "render_mpi_large", "particles": n, "width": two["width"],
            "height": two["height"], "ranks": ranks, **p,
            "pixel_floor_s": round((c["c_pix"] + c["c_comp"]) * pix, 4),
            "costs_from": f"{two['particles']} particles", "memory_per_rank_limit": MEMORY_PER_RANK,
            "step_s_limit": STEP_S}


def image_size(text: str) -> tuple[int, int]:
    """WxH (pixels) as (W, H); argparse's type for --sizes."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an image size WxH: {text!r}") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"an image size must be positive: {text!r}")
    return width, height


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m bench.render_mpi",
        description="Render one step on 1 MPI rank (2 numba threads) and on 2 ranks (1 thread "
                    "each): the 1M column and a random 8M step, at 1024x768 and 2048x1536. "
                    "Prints JSON lines: baseline_rss_bytes (a process's floor at N = 1 and "
                    "2), render_mpi (phase times, peak RSS per rank), render_mpi_ratio "
                    "(N = 2 over N = 1), render_mpi_model (time per step up to 64 ranks "
                    "from the measured costs), render_mpi_large (what a 100M-particle run "
                    "would need). Half a minute to two minutes on 2 cores.")
    parser.add_argument("--large", type=int, default=8_000_000,
                        help="particles of the synthetic step (default 8,000,000; 0: skip it)")
    parser.add_argument("--scene", default=SCENE,
                        help=f"the built-in scene whose column is rendered (default {SCENE})")
    parser.add_argument("--sizes", nargs=2, type=image_size, default=SIZES, metavar="WxH",
                        help="the two image sizes (default 1024x768 2048x1536)")
    parser.add_argument("--worker", choices=("column", "random", "baseline"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--particles", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        try:
            worker(args.worker, args.particles, args.threads, args.scene, args.sizes)
        except BaseException:  # one rank failing must not leave the others waiting
            import traceback

            from mpi4py import MPI

            traceback.print_exc()
            sys.stderr.flush()
            MPI.COMM_WORLD.Abort(1)
        return
    sizes, scene = args.sizes, args.scene
    print(json.dumps(shadow_needs(scene=scene, size=sizes[0])), flush=True)
    base = {}
    for ranks, threads in ((1, 2), (2, 1)):  # the first compiles (or loads) every kernel
        launch("baseline", 0, ranks, threads, scene, sizes)
        base[ranks] = launch("baseline", 0, ranks, threads, scene, sizes)[0]
        print(json.dumps(base[ranks]), flush=True)
    steps = [("column", 0)] + ([("random", args.large)] if args.large else [])
    w0, w1 = sizes[0][0], sizes[1][0]
    rows = {}
    for kind, n in steps:
        for ranks, threads in ((1, 2), (2, 1)):
            for line in launch(kind, n, ranks, threads, scene, sizes):
                rows[kind, ranks, line["width"]] = line
                print(json.dumps(line), flush=True)
        for width, _ in sizes:
            one, two = rows[kind, 1, width], rows[kind, 2, width]
            above = ((max(two["peak_rss_bytes"]) - max(base[2]["peak_rss_bytes"]))
                     / max(one["peak_rss_bytes"][0] - base[1]["peak_rss_bytes"][0], 1))
            ratio = {"bench": "render_mpi_ratio", "particles": one["particles"], "width": width,
                     "total_2_over_1": round(two["total_s"] / one["total_s"], 3),
                     "composite_share_2": round(two["composite_s"] / two["total_s"], 3),
                     "rss_2_over_1": round(max(two["peak_rss_bytes"])
                                           / one["peak_rss_bytes"][0], 3),
                     "rss_above_baseline_2_over_1": round(above, 3),
                     "rss_if_halved_2_over_1": round(
                         (max(base[2]["peak_rss_bytes"]) + (one["peak_rss_bytes"][0]
                                                            - base[1]["peak_rss_bytes"][0]) / 2)
                         / one["peak_rss_bytes"][0], 3)}
            print(json.dumps(ratio), flush=True)
        for line in model(rows[kind, 2, w0], rows[kind, 2, w1], base[2]):
            print(json.dumps(line), flush=True)
    steps_two = [(rows[kind, 2, w0], rows[kind, 2, w1]) for kind, _ in steps]
    print(json.dumps(large_run(steps_two, base[2])), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
