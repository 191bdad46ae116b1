"""The in situ API's cost to the simulation's thread: JSON lines per particle count and mode.

    python -m bench.insitu [--sizes 13k,100k,1m] [--calls N] [--threads T]

(--sizes tiny: the 400-particle test scene, a smoke test of the bench.)

{"bench": "insitu", "particles", "mode", "due_publish_s", "due_publish_cpu_s",
 "reclaim_wait_s", "snapshot_queue_s", "mpm_step_publishing_s", "chunk_bytes",
 "sender_build_s", "sent", "dropped", "full_outbox_publish_s", "idle_due_s", "mpm_step_s",
 "copy_floor_s", "due_publish_over_mpm_step", "threads", "scene"}

The particles are our column scene's (column_13k, column_100k, column_1m), seeded and
stepped by our MPM (`minority.sim.driver.Simulator`, warm-up steps and JIT excluded):
* mpm_step_s: the median wall time of one MPM step at that size (the CFL step) with nothing
  published, from steps interleaved with the published ones (same load, same minutes);
* due_publish_s: the median caller's time of a due step against a live `minority serve`
  process on loopback (a 320x240 view of every particle every step, coloured by
  displacement, plus Stats at every due step: the worst case): `viz.due` + building the
  wanted fields + `viz.publish`, plus, for mode "lend", the wait in `viz.reclaim` that the
  next MPM step makes before it writes the lent arrays (reclaim_wait_s; the sender builds
  beside the step, as in `minority sim`). mode "copy": publish copies what the step reads
  (the default); "lend": `publish(copy=False)`, the arrays read in place and the
  displacement computed by the sender (insitu.lend). The modes (and steps that publish
  nothing) alternate step by step.
  due_publish_cpu_s: the caller's thread CPU time of due + publish; snapshot_queue_s: of
  that, the publisher's snapshot (or loan) and queueing of the chunk and Stats;
  mpm_step_publishing_s: the MPM step meanwhile (the sender shares the cores), without the
  reclaim wait; chunk_bytes: per chunk; sender_build_s: the sender thread's culling and
  encoding per message (not the caller's); sent, dropped: chunks of the run;
* copy_floor_s: copying what such a step reads (positions, ids, displacement, velocity)
  into warm buffers: the least a copying hand-over costs;
* idle_due_s: `viz.due` at a step nothing is due (the cost at most steps);
* full_outbox_publish_s: the median of a due step's call when the outbox is full, against
  a server that stopped reading (its chunk callback never returns; shared memory off so the
  link fills): `due` refuses the step, so nothing is built nor copied.
Targets (issue 26): due_publish_s <= 2 % of mpm_step_s; full_outbox_publish_s <= 1 ms.
"""

from __future__ import annotations

import argparse
import io
import json
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numba
import numpy as np

from minority.insitu import PublishOptions, connect
from minority.protocol import Spec, keys
from minority.protocol.session import NetworkOptions, Role, open_session
from minority.sim.driver import Simulator
from minority.sim.publish import sim_fields
from minority.sim.scene import builtin_scene_path, load_scene

RUN = "bench-insitu"
SIZES = {"13k": "column_13k", "100k": "column_100k", "1m": "column_1m", "tiny": "tiny"}
KEYS = {"insitu": ("particles", "mode", "due_publish_s", "due_publish_cpu_s", "reclaim_wait_s",
                   "snapshot_queue_s", "mpm_step_publishing_s", "chunk_bytes", "sender_build_s",
                   "sent", "dropped", "full_outbox_publish_s", "idle_due_s", "mpm_step_s",
                   "copy_floor_s", "due_publish_over_mpm_step", "threads", "scene")}
CALLS = 20  # timed due + publish calls per size
WARMUP_CALLS = 3  # shared-memory pool, page mapping, numba (visibility) warm up
WARMUP_STEPS = 2
FULL_MAX_CALLS = 2000  # publishes at most until the outbox overflows
CLIENT_STALLED = """{
  mode: "client",
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },
  transport: { shared_memory: { enabled: false }, link: { tcp: { so_sndbuf: 65536 } } },
}
"""
SERVER_STALLED = ('{ mode: "peer", scouting: { multicast: { enabled: false } }, '
                  'transport: { link: { tcp: { so_rcvbuf: 65536 } } } }')


def spec(size_m) -> Spec:
    lx, ly, lz = size_m
    return Spec.from_dict({"version": 2, "run": RUN, "views": [{
        "name": "aerial", "camera": {"position": [1.5 * lx, -1.2 * lx, 0.9 * lx],
                                     "focal_point": [0.4 * lx, 0.5 * ly, 0.1 * lz],
                                     "view_up": [0, 0, 1], "view_angle_deg": 30},
        "width": 320, "height": 240, "field": "displacement", "range": [0.0, 0.3],
        "schedule": [{"every_steps": 1}]}]})


def step_once(viz, sim, step: int, time_s: float, spacing: float, bounds,
              lend: bool = False) -> tuple[float, float]:
    """One due step as sim.ranks makes it (copied, or lent as `minority sim` does): (wall s,
    thread CPU s) of the caller."""
    c0, t0 = time.thread_time(), time.perf_counter()
    if viz.due(step, time_s):
        ps = sim.particles
        viz.publish(step, time_s, ps.x, fields=sim_fields(ps, viz.wanted, lazy=lend),
                    ids=ps.pid, spacing_m=spacing, bounds_m=bounds, copy=not lend)
    return time.perf_counter() - t0, time.thread_time() - c0


def copy_floor_s(sim: Simulator, calls: int = 10) -> float:
    """The least a non-blocking hand-over costs the caller: copying the arrays a due step
    with Stats reads (positions, ids, displacement, velocity) into warm buffers, median s."""
    ps = sim.particles
    arrays = [ps.x, ps.pid, ps.x - ps.x0, ps.v]
    buffers = [np.empty_like(a) for a in arrays]
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        for a, b in zip(arrays, buffers, strict=True):
            np.copyto(b, a)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(name: str, calls: int, threads: int | None) -> list[dict]:
    scene = load_scene(builtin_scene_path(name))
    sim = Simulator(scene, threads=threads)
    for _ in range(WARMUP_STEPS):
        sim.step(sim.stable_dt())
    floor = copy_floor_s(sim)
    n = sim.particles.n
    spacing = scene.particle_spacing_m
    bounds = ((0.0, 0.0, 0.0), tuple(map(float, scene.size_m)))
    the_spec = spec(scene.size_m)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    with tempfile.TemporaryDirectory() as tmp:
        spec_path = Path(tmp) / "spec.json"
        the_spec.save(spec_path)
        # the render server in its own process, as deployed: its threads share the cores,
        # not the caller's interpreter
        server = subprocess.Popen(
            [sys.executable, "-m", "minority", "serve", "--spec", str(spec_path), "--out",
             str(Path(tmp) / "frames"), "--listen", endpoint],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            rows = publish_steps(sim, endpoint, n, calls, spacing, bounds,
                                 lambda stop: server.send_signal(
                                     signal.SIGSTOP if stop else signal.SIGCONT))
            idle = idle_due_s(n)
        finally:
            server.send_signal(signal.SIGINT)
            try:
                server.wait(timeout=60)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()
    full = full_outbox(sim, the_spec, calls, spacing, bounds)
    out = []
    for mode, row in rows.items():
        out.append({"bench": "insitu", "particles": n, "mode": mode, **row,
                    "full_outbox_publish_s": round(full, 6), "idle_due_s": round(idle, 9),
                    "copy_floor_s": round(floor, 6),
                    "threads": numba.get_num_threads(), "scene": name})
    return out


def publish_steps(sim, endpoint: str, n: int, calls: int, spacing, bounds,
                  pause_server: Callable[[bool], None]) -> dict:
    """Steps against the server at `endpoint`, copied, lent and not published in turn
    (`calls` of each after warm-up ones), each followed by an MPM step as in `minority sim`
    (the sender builds beside it; a lent step's particle writes wait for the sender's copy:
    `Simulator.before_write`), then waiting until the outbox is empty (so no step is
    refused). Per mode: medians of the caller's costs and of the MPM step, s; the steps not
    published give the MPM step alone, measured in the same minutes as the others with the
    server paused (`pause_server(True)`: SIGSTOP; its numba threads would otherwise share the
    cores with the MPM's, and spinning OpenMP threads of two processes slow both)."""
    options = PublishOptions(stats_every_s=1e-9)  # Stats at every step: the worst case
    modes = ("copy", "lend", "none")
    runs = {mode: {"wall": [], "cpu": [], "wait": [], "step": [], "prepare": []} for mode in modes}
    with connect(RUN, connect=(endpoint,), wait_s=60.0, particles=n, options=options) as viz:
        if viz.spec is None:
            raise RuntimeError("the render server did not answer within 60 s")
        sim.before_write = viz.reclaim
        try:
            for k in range(len(modes) * (WARMUP_CALLS + calls)):
                mode = modes[k % len(modes)]
                st = viz.stats
                prepare0 = st.prepare_s + st.stats_s
                w = c = 0.0
                if mode != "none":
                    w, c = step_once(viz, sim, sim.step_count, sim.time_s, spacing, bounds,
                                     mode == "lend")
                else:
                    viz.due(sim.step_count, sim.time_s)  # keeps the publisher's clock
                    pause_server(True)
                prepare = st.prepare_s + st.stats_s - prepare0
                lent0, t0 = sim.times.lent, time.perf_counter()
                sim.step(sim.stable_dt())
                step_s = time.perf_counter() - t0
                if mode == "none":
                    pause_server(False)
                if k >= len(modes) * WARMUP_CALLS:
                    wait = sim.times.lent - lent0  # the caller's, for this due step
                    r = runs[mode]
                    r["wall"].append(w + wait)
                    r["cpu"].append(c)
                    r["wait"].append(wait)
                    r["step"].append(step_s - wait)
                    r["prepare"].append(prepare)
                viz.wait_sent(60.0)  # one chunk at a time: never a drop
        finally:
            sim.before_write = None
        st = viz.stats
    alone = statistics.median(runs["none"]["step"])
    common = {"chunk_bytes": st.bytes_sent // max(st.sent, 1),
              "sender_build_s": round(st.build_s / max(st.scheduled + st.stats_due, 1), 6),
              "sent": st.sent, "dropped": st.dropped, "mpm_step_s": round(alone, 6)}
    out = {}
    for mode in ("copy", "lend"):
        r = runs[mode]
        wall = statistics.median(r["wall"])
        out[mode] = {"due_publish_s": round(wall, 6),
                     "due_publish_cpu_s": round(statistics.median(r["cpu"]), 6),
                     "reclaim_wait_s": round(statistics.median(r["wait"]), 6),
                     "snapshot_queue_s": round(statistics.median(r["prepare"]), 6),
                     "mpm_step_publishing_s": round(statistics.median(r["step"]), 6),
                     "due_publish_over_mpm_step": round(wall / alone, 4), **common}
    return out


def idle_due_s(n: int, calls: int = 10_000) -> float:
    """`due` at steps nothing is due (a spec whose one window opens at t = 1 s), per call."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "spec.json"
        d = spec((1.0, 1.0, 1.0)).to_dict()
        d["views"][0]["schedule"] = [{"t_start_s": 1.0, "every_steps": 1}]
        path.write_text(json.dumps(d))
        with connect(RUN, connect=(f"tcp/127.0.0.1:{_free_port()}",), spec=path,
                     record=Path(tmp) / "r.mcap", options=PublishOptions(stats_every_s=0.0),
                     log=io.StringIO()) as viz:
            t0 = time.perf_counter()
            for k in range(calls):
                viz.due(k, k * 1e-6)
            return (time.perf_counter() - t0) / calls


def full_outbox(sim, the_spec, calls: int, spacing, bounds) -> float:
    """Median caller time of a due step once the outbox has overflowed (a server whose
    chunk callback never returns)."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "server.json5").write_text(SERVER_STALLED)
        (Path(tmp) / "client.json5").write_text(CLIENT_STALLED)
        session = open_session(NetworkOptions(listen=[endpoint], config=Path(tmp) / "server.json5"),
                               Role.SERVER)
        gate = threading.Event()
        queryable = session.declare_queryable(keys.spec(RUN), lambda q: q.reply(
            keys.spec(RUN), bytes(the_spec.encode())))
        stuck = session.declare_subscriber(keys.chunks(RUN), lambda s: gate.wait())
        options = PublishOptions(network=NetworkOptions(config=Path(tmp) / "client.json5"),
                                 stats_every_s=0.0, drain_timeout_s=0.5)
        try:
            viz = connect(RUN, connect=(endpoint,), wait_s=10.0, options=options,
                          log=io.StringIO())
            k = 0
            while viz.stats.dropped_outbox == 0 and k < FULL_MAX_CALLS:
                step_once(viz, sim, k, k * 1e-5, spacing, bounds)
                k += 1
            if viz.stats.dropped_outbox == 0:
                raise RuntimeError(f"the outbox never overflowed in {k} calls")
            times = []
            for j in range(k, k + calls):
                times.append(step_once(viz, sim, j, j * 1e-5, spacing, bounds)[0])
            viz.close()
        finally:
            gate.set()
            stuck.undeclare()
            queryable.undeclare()
            session.close()
    return statistics.median(times)


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="13k,100k,1m",
                        help="comma-separated, of 13k, 100k, 1m, tiny (default: the first "
                             "three; 1m takes minutes)")
    parser.add_argument("--calls", type=int, default=CALLS,
                        help=f"timed due + publish calls per size (default {CALLS})")
    parser.add_argument("--threads", type=int, default=None,
                        help="numba threads of the MPM (default: numba's)")
    args = parser.parse_args()
    for size in args.sizes.split(","):
        if size not in SIZES:
            parser.error(f"--sizes: unknown size {size!r} (known: {', '.join(SIZES)})")
    for size in args.sizes.split(","):
        for row in measure(SIZES[size], args.calls, args.threads):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
