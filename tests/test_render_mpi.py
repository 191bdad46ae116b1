"""Rendering one step on N MPI ranks (render_server.render_mpi): frames pixel-identical to
the one-process render_views of the same step and spec, for a lattice, a random heap with
duplicated particles (exact depth ties across ranks), a collapsed-column-like step with
the showcase's kind of views (perspective and parallel, regions, decimation, annotations),
and a replayed showcase step: the demo's column collapse (1,800 particles) simulated by
`minority sim` on 2 ranks against `minority serve` on loopback, its mid-collapse step read
back out of the server's log as `minority replay` reads it; balanced bricks; the pieces
(k-d tree, compositing) in one process.

The ranks run under the venv's mpiexec (this file is the worker: `python
tests/test_render_mpi.py OUT_DIR [scale [LOG]]`), one numba thread each, as in test_sim_mpi.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port

from minority.demo import DemoOptions, demo_column
from minority.protocol import keys
from minority.protocol.log import read_log
from minority.protocol.spec import Spec
from minority.render_server.assemble import AssembledStep, StepAssembler
from minority.render_server.composite import bands, composite
from minority.render_server.distribute import build_tree
from minority.render_server.frames import render_views
from minority.render_server.particles import ParticleCache, complete_step
from minority.render_server.render_mpi import SHADOWS_REFUSED, render_views_distributed
from minority.render_server.rerender import MAX_PENDING_STEPS, recorded_steps

TIMEOUT_S = 600
CASES = ("lattice", "heap", "column")
# the replayed showcase step as the server rendered it (completed from its particle cache:
# every view draws the whole column), and its fresh rows alone (what a `--no-context` run
# sends: the particles in the due views' regions; each view draws its own regions)
REPLAYED = ("replayed", "replayed_fresh")
SIDE = {"position": [0.35, -1.2, 0.16], "focal_point": [0.35, 0.072, 0.12],
        "view_up": [0, 0, 1], "view_angle_deg": 30}
TOP = {"position": [0.4, 0.072, 1.5], "focal_point": [0.4, 0.072, 0.0], "view_up": [0, 1, 0],
       "parallel_projection": True, "parallel_scale_m": 0.3}
AERIAL = {"position": [1.15, -0.8, 0.8], "focal_point": [0.3, 0.072, 0.1], "view_up": [0, 0, 1],
          "view_angle_deg": 30}
# looking straight down the lattice's y rows: many exact depth ties between neighbours
ALONG_Y = {"position": [0.3, -1.0, 0.15], "focal_point": [0.3, 0.0, 0.15], "view_up": [0, 0, 1],
           "parallel_projection": True, "parallel_scale_m": 0.2}
REGIONS = [{"name": "front", "lo_m": [0.0, 0.0, 0.0], "hi_m": [0.25, 0.144, 0.4]},
           {"name": "toe", "lo_m": [0.35, 0.0, 0.0], "hi_m": [1.0, 0.144, 0.1]},
           {"name": "nowhere", "lo_m": [5.0, 5.0, 5.0], "hi_m": [6.0, 6.0, 6.0]}]


def view(name: str, camera: dict, **kw) -> dict:
    return {"name": name, "camera": camera, "width": 160, "height": 120,
            "field": "displacement", "colormap": "Cool to Warm", "range": [0.0, 0.4], **kw}


# The replayed showcase: minority/demo.py's column (column_13k's geometry and material) at
# `minority demo --cell-size 0.032` (1,800 particles) in its channel x 0..0.8 m (flow),
# y 0..0.16 m, z 0..0.416 m, simulated to SHOWCASE_END_S. The spec asks for a step every
# 0.05 s from 0.15 s; the last, at 0.25 s, is mid-collapse: the front at about 0.27 m,
# moving at about 1 m/s, the heap 0.25 m high (the demo's runout ends near 0.62 s).
SHOWCASE_RUN = "column"
SHOWCASE_CELL_M = 0.032
SHOWCASE_END_S = 0.26
SHOWCASE_REGIONS = [
    {"name": "front", "lo_m": [0.2, 0.0, 0.0], "hi_m": [0.8, 0.16, 0.416]},  # the runout
    {"name": "base", "lo_m": [0.0, 0.0, 0.0], "hi_m": [0.2, 0.16, 0.1]},  # the foot of the wall
    {"name": "nowhere", "lo_m": [5.0, 5.0, 5.0], "hi_m": [6.0, 6.0, 6.0]}]


def showcase_view(name: str, camera: dict, regions: list[str], **kw) -> dict:
    window = {"t_start_s": 0.15, "t_end_s": 0.25, "every_s": 0.05, "regions": regions}
    return view(name, camera, range=[0.0, 0.2], schedule=[window], **kw)


# the column above the base (x < 0.2 m, z > 0.1 m) is in no region: sent as context rows
SHOWCASE_SPEC = {"version": 2, "run": SHOWCASE_RUN, "regions": SHOWCASE_REGIONS, "views": [
    showcase_view("side", SIDE, ["front"]),
    showcase_view("top", TOP, ["front", "base"], decimate=3),
    showcase_view("aerial", AERIAL, ["base"], decimate=2, annotations=False),
    showcase_view("empty", AERIAL, ["nowhere"], background=[0, 0, 1])]}


@functools.lru_cache(maxsize=2)
def replayed(log: Path) -> dict:
    """The showcase log read as `minority replay` reads it (rerender.recorded_steps, then the
    particle cache): "history", each logged step's (time s, front x m); and for the last
    step, for each name of REPLAYED, (step, the recorded spec in force, each row's sim rank).
    A step's rows: the fresh rows of its chunks in sim-rank order, then the cached rows."""
    cache = ParticleCache()
    history = []
    steps = recorded_steps(log, SHOWCASE_RUN, StepAssembler(max_pending=MAX_PENDING_STEPS))
    for step, recorded in steps:
        full = complete_step(cache, step)  # as the server completed it from its cache
        history.append((step.time_s, float(full.positions[:, 0].max())))
        spec = recorded
    fresh = {}  # sim rank -> fresh rows of its chunk of the last step
    for record in read_log(log, topics=[keys.log_topic(SHOWCASE_RUN, keys.Topic.CHUNK)]):
        chunk = record.decode()
        if chunk.step == step.step:
            fresh[chunk.rank] = chunk.fresh
    sim_ranks = sorted(fresh)
    fresh_rank = np.repeat(np.array(sim_ranks, np.int64), [fresh[r] for r in sim_ranks])
    step = dataclasses.replace(step, context=[])
    return {"history": history, "replayed_fresh": (step, spec, fresh_rank),
            "replayed": (full, spec, np.concatenate([fresh_rank, cache.rank.astype(np.int64)]))}


def case(name: str, scale: int = 1, log: Path | None = None
         ) -> tuple[AssembledStep, Spec, np.ndarray]:
    """The whole step, its spec, and the rank (of 3 groups, folded onto the rank count) each
    row starts on. Same on every rank: seeded, or read from the showcase `log` (a row starts
    on the render rank of its sim rank, as in `minority serve --ranks N`)."""
    if name in REPLAYED:
        if log is None:
            raise ValueError(f"case {name!r} needs the showcase log")
        return replayed(log)[name]
    rng = np.random.default_rng(7)
    if name == "lattice":
        # 35 x 8 x 20 sites, every site twice (the second copy another colour), overlapping
        # neighbours (radius 0.6 spacing); 35 layers along x: the split planes cut a layer and
        # break it by key, so copies of one site land on different ranks (ties across ranks)
        h = 0.018
        g = np.stack(np.meshgrid(np.arange(35), np.arange(8), np.arange(20), indexing="ij"), -1)
        pos = (g.reshape(-1, 3) * h + h / 2).astype(np.float32)
        pos = np.concatenate([pos, pos])
        disp = (pos[:, 0] * 0.5).astype(np.float32)
        disp[len(disp) // 2:] = 0.4 - disp[len(disp) // 2:]
        spec = {"sphere_radius_m": 0.6 * h, "views": [
            view("along", ALONG_Y, annotations=False), view("side", SIDE, annotations=False),
            view("top", TOP, annotations=False)]}
        start = np.arange(len(pos)) * 3 // len(pos)  # contiguous thirds
    elif name == "heap":  # random heap; a third of its particles twice, other value, other rank
        n = 12_000 * scale
        x = 0.6 * (1.0 - np.sqrt(rng.random(n)))
        pos = np.c_[x, 0.144 * rng.random(n), 0.32 * (1.0 - x / 0.6) ** 2 * rng.random(n)]
        twice = rng.choice(n, n // 3, replace=False)
        pos = np.concatenate([pos, pos[twice]]).astype(np.float32)
        disp = rng.random((len(pos), 3)).astype(np.float32) * 0.25
        spec = {"views": [view("aerial", AERIAL, annotations=False),
                          view("top", TOP, annotations=False, colormap="viridis")]}
        start = rng.integers(0, 3, len(pos))  # rows scattered over the ranks
    elif name == "column":  # a collapsing column's shape, with ids; the showcase's views
        n = 13_000 * scale
        x = 0.6 * rng.random(n) ** 1.5
        pos = np.c_[x, 0.144 * rng.random(n), 0.3 * np.exp(-4 * x) * rng.random(n)]
        pos = pos.astype(np.float32)
        disp = np.c_[x, np.zeros(n), pos[:, 2] - 0.3].astype(np.float32)
        spec = {"views": [
            view("side", SIDE, schedule=[{"regions": ["front", "toe"]}]),
            view("top", TOP, decimate=3),
            view("aerial", AERIAL, decimate=2, schedule=[{"regions": ["toe"]}]),
            view("empty", AERIAL, schedule=[{"regions": ["nowhere"]}], background=[0, 0, 1])]}
        start = np.zeros(len(pos), np.int64)
        start[len(pos) * 7 // 10:] = 1  # rank 0 holds 70 % at first, rank 2 nothing
    else:
        raise ValueError(name)
    fields = {"displacement": disp}
    if name == "column":
        fields["id"] = rng.permutation(len(pos)).astype(np.int64)
    spacing = 0.018 if name == "lattice" else float((0.6 * 0.144 * 0.3 / 3 / len(pos)) ** (1 / 3))
    step = AssembledStep(40, 0.02, pos, fields, spacing, 1, 1, 0, 0.0, False, 0.019,
                         bounds_m=((0.0, 0.0, 0.0), (1.0, 0.144, 0.4)))
    spec = Spec.from_dict({"version": 2, "run": "mpi", "regions": REGIONS, **spec})
    return step, spec, start


def worker(out: Path, scale: int, log: Path | None) -> None:
    """Under mpiexec: render every case of CASES and check the exchange, or with a log the
    REPLAYED cases, on this communicator; rank 0 writes the frames."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    meta = {}
    for name in CASES if log is None else REPLAYED:
        step, spec, start = case(name, scale, log)
        rows = np.flatnonzero(start % comm.size == comm.rank)
        mine = dataclasses.replace(step, positions=step.positions[rows],
                                   fields={k: v[rows] for k, v in step.fields.items()})
        frames, times = render_views_distributed(comm, mine, spec, {}, keys=rows)
        if comm.rank == 0:
            np.savez(out / f"{name}.npz", **{f.view.name: f.image for f in frames})
            meta[name] = {"counts": times.counts,
                          "particles": {f.view.name: f.particles for f in frames}}
    if log is None:
        meta["exchange"] = exchange_checks(comm)
    if comm.rank == 0:
        (out / "meta.json").write_text(json.dumps(meta))


def exchange_checks(comm) -> dict:
    """Under mpiexec: balanced slabs in rank order stay where they are (the input arrays
    themselves); scattered rows moved in many small rounds equal one round, every particle
    ends on the rank of its brick, each exactly once."""
    from minority.render_server import distribute

    rng = np.random.default_rng(11 + comm.rank)
    n = 3000
    x = (comm.rank + rng.random(n)) / comm.size  # rank r: x in [r/N, (r+1)/N); z longest
    slab = np.c_[x, 0.1 * rng.random(n), 2.0 * rng.random(n)].astype(np.float32)
    values = rng.random(n).astype(np.float32)
    part = distribute.exchange(comm, slab, {"v": values})
    checks = {"slabs_in_place": part.positions is slab and part.fields["v"] is values,
              "slab_axis": int(part.tree.axis[0])}
    mixed = rng.random((n, 3)).astype(np.float32)
    fields = {"v": values, "pair": rng.random((n, 2)), "flag": rng.integers(0, 100, n, np.int8)}
    one = distribute.exchange(comm, mixed, fields, pool=distribute.Pool())
    saved, distribute.ROUND_BYTES = distribute.ROUND_BYTES, 256  # a round: a few rows a rank
    try:
        many = distribute.exchange(comm, mixed, fields)
    finally:
        distribute.ROUND_BYTES = saved
    checks["rounds_equal"] = bool(np.array_equal(one.positions, many.positions)
                                  and np.array_equal(one.keys, many.keys)
                                  and all(np.array_equal(one.fields[k], many.fields[k])
                                          for k in fields))
    owner = distribute.classify(many.positions, many.keys, many.tree)
    checks["on_own_brick"] = bool(np.all(owner == comm.rank))
    every = np.sort(np.concatenate(comm.allgather(many.keys)))
    checks["each_once"] = bool(np.array_equal(every, np.arange(n * comm.size)))
    # the fields travelled with their particles: rows of the input, by key
    rows = many.keys - n * comm.rank  # this rank's rows where the key is its own
    mine = (rows >= 0) & (rows < n)
    checks["rows_intact"] = bool(np.array_equal(many.fields["flag"][mine], fields["flag"][rows[mine]])
                                 and np.array_equal(many.positions[mine], mixed[rows[mine]]))
    return checks


def run_ranks(ranks: int, out: Path, scale: int = 1, log: Path | None = None) -> dict:
    mpiexec = str(Path(sys.executable).parent / "mpiexec")
    proc = subprocess.run([mpiexec, "-n", str(ranks), sys.executable, __file__, str(out),
                           str(scale), *([str(log)] if log is not None else [])],
                          capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads((out / "meta.json").read_text())


@pytest.fixture(scope="module")
def showcase_log(tmp_path_factory) -> Path:
    """The server's log of the showcase column: `minority serve --spec SHOWCASE_SPEC` on
    loopback and `minority sim` of the demo's column on 2 ranks, to SHOWCASE_END_S (a few
    seconds). The server's frames are in the log's folder, {run}/{view}/{step:06d}.png."""
    tmp = tmp_path_factory.mktemp("showcase")
    (tmp / "spec.json").write_text(json.dumps(SHOWCASE_SPEC))
    scene = demo_column(DemoOptions(cell_size_m=SHOWCASE_CELL_M, duration_s=SHOWCASE_END_S))
    (tmp / "column.toml").write_text(scene)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    err = tmp / "serve.err"
    server = subprocess.Popen(
        [sys.executable, "-m", "minority", "serve", "--spec", str(tmp / "spec.json"), "--out",
         str(tmp / "out"), "--timeout", "30", "--listen", endpoint, "--exit-when-done"],
        stderr=err.open("w"), env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while "serving run" not in err.read_text():  # its line once it serves the spec
            assert server.poll() is None, err.read_text()[-3000:]
            assert time.monotonic() < deadline, "the server did not start"
            time.sleep(0.1)
        # context rows resent once they moved 2 mm: the last step draws rows cached at
        # earlier steps too, appended to the cache in several releases
        sim = subprocess.run(
            [sys.executable, "-m", "minority", "sim", str(tmp / "column.toml"), "--ranks", "2",
             "--run", SHOWCASE_RUN, "--out", str(tmp / "column.h5"), "--quiet", "--connect",
             endpoint, "--wait", "30", "--context-tolerance", "0.002"],
            capture_output=True, text=True, timeout=300, env=env)
        assert sim.returncode == 0, sim.stderr[-3000:]
        assert server.wait(300) == 0, err.read_text()[-3000:]
    finally:
        try:  # what is left of the server's process group
            os.killpg(server.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        server.wait()
    return tmp / "out" / f"{SHOWCASE_RUN}.mcap"


@pytest.fixture(scope="module", params=[2, 3])
def distributed(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(f"ranks{request.param}")
    return request.param, out, run_ranks(request.param, out)


@pytest.fixture(scope="module", params=[2, 3])
def distributed_replay(request, tmp_path_factory, showcase_log):
    """The REPLAYED cases on 2 and 3 ranks (apart: the other cases need no sim or server)."""
    out = tmp_path_factory.mktemp(f"replay{request.param}")
    return request.param, out, run_ranks(request.param, out, log=showcase_log)


@pytest.mark.parametrize("name", CASES)
def test_frames_are_pixel_identical_to_one_process(distributed, name):
    check_pixel_identical(*distributed, name)


@pytest.mark.parametrize("name", REPLAYED)
def test_replayed_showcase_step_is_pixel_identical_to_one_process(distributed_replay,
                                                                  showcase_log, name):
    check_pixel_identical(*distributed_replay, name, showcase_log)


def check_pixel_identical(ranks: int, out: Path, meta: dict, name: str, log: Path | None = None):
    step, spec, _ = case(name, log=log)
    reference = {f.view.name: f for f in render_views(step, spec, {})}
    got = np.load(out / f"{name}.npz")
    assert sorted(got.files) == sorted(reference)
    for view_name, ref in reference.items():
        diff = np.any(got[view_name] != ref.image, axis=-1)
        assert not diff.any(), f"{ranks} ranks, {name}/{view_name}: {diff.sum()} pixels differ"
        assert meta[name]["particles"][view_name] == ref.particles
    drawn = [ref for ref in reference.values() if ref.particles]
    assert all(len(np.unique(r.image.reshape(-1, 3), axis=0)) > 20 for r in drawn)


def test_bricks_are_balanced(distributed):
    check_balanced(*distributed, CASES)


def test_replayed_showcase_bricks_are_balanced(distributed_replay, showcase_log):
    check_balanced(*distributed_replay, REPLAYED, showcase_log)


def check_balanced(ranks: int, out: Path, meta: dict, names: tuple[str, ...],
                   log: Path | None = None) -> None:
    """Every particle in one brick; each rank's within 3 % of an even share."""
    for name in names:
        counts = np.array(meta[name]["counts"])
        total = len(case(name, log=log)[0].positions)
        assert counts.sum() == total
        assert np.abs(counts - total / ranks).max() <= 0.03 * total / ranks, (name, counts)


def test_replayed_step_is_the_servers_mid_collapse_step(showcase_log):
    """The replayed case is what it claims: the step the server rendered (its own frames,
    pixel for pixel), mid-collapse, completed from the cache (rows of several steps), every
    view's regions holding particles of it and leaving others out, a chunk from each of the
    2 sim ranks."""
    from PIL import Image

    history = replayed(showcase_log)["history"]  # (time s, front x m) of 0.15, 0.2, 0.25 s
    assert len(history) == 3, history
    (t0, front0), (t1, front1) = history[-2:]
    assert abs(t1 - 0.25) < 0.01, history
    assert 0.24 < front1 < 0.4 and front1 - front0 > 0.02, history  # the front moving
    full, spec, start = case("replayed", log=showcase_log)
    fresh = case("replayed_fresh", log=showcase_log)[0]
    assert full.completed and full.cached > 0 and len(full.positions) == 1800
    assert full.cache_age_steps > 0  # some cached rows were sent at an earlier step
    assert np.array_equal(full.positions[:len(fresh.positions)], fresh.positions)
    assert "id" in full.fields and sorted(np.unique(start)) == [0, 1]
    assert not fresh.completed and 0 < len(fresh.positions) < len(full.positions)
    frames = showcase_log.parent / SHOWCASE_RUN
    for ref in render_views(full, spec, {}):
        server = np.asarray(Image.open(frames / ref.view.name / f"{full.step:06d}.png"))
        assert np.array_equal(server, ref.image), ref.view.name
    for v in spec.views:  # each view's regions: some of the column, not all (empty: none)
        inside = np.zeros(len(full.positions), bool)
        for b in spec.view_regions(v, full.step, full.time_s, full.prev_time_s):
            inside |= np.all((full.positions >= b.lo_m) & (full.positions <= b.hi_m), axis=1)
        low, high = (0, 0) if v.name == "empty" else (1, len(inside) - 1)
        assert low <= inside.sum() <= high, (v.name, inside.sum())
    shown = {r.view.name: r.particles for r in render_views(fresh, spec, {})}
    assert shown["empty"] == 0 and all(shown[k] > 0 for k in ("side", "top", "aerial"))


def test_exchange_keeps_slabs_and_moves_rows_in_rounds(distributed):
    ranks, _, meta = distributed
    assert meta["exchange"] == {"slabs_in_place": True, "slab_axis": 0, "rounds_equal": True,
                                "on_own_brick": True, "each_once": True, "rows_intact": True}


def test_ties_decide_pixels():
    """The heap's duplicated particles tie at equal depth with other colours: the frame
    depends on how ties break, so the pixel identity above checks the tie rule."""
    step, spec, _ = case("heap")
    ref = render_views(step, spec, {})[0].image.copy()
    flipped = np.arange(len(step.positions))[::-1]  # same particles, reversed rows
    rev = AssembledStep(step.step, step.time_s, step.positions[flipped],
                        {k: v[flipped] for k, v in step.fields.items()}, step.spacing_m, 1, 1,
                        0, 0.0, False, step.prev_time_s)
    other = render_views(rev, spec, {})[0].image
    assert np.any(other != ref)


@pytest.mark.slow
def test_large_heap_is_pixel_identical(tmp_path):
    run_ranks(3, tmp_path, scale=10)
    step, spec, _ = case("heap", 10)
    got = np.load(tmp_path / "heap.npz")
    for ref in render_views(step, spec, {}):
        assert np.array_equal(got[ref.view.name], ref.image), ref.view.name


def test_tree_splits_counts_for_any_rank_count():
    rng = np.random.default_rng(3)
    sample = rng.random((9000, 3)) * [1.0, 0.2, 0.4]
    keys = np.arange(len(sample), dtype=np.int64)
    for ranks in (1, 2, 3, 5, 7):
        tree = build_tree(sample, keys, ranks, sample.min(0), sample.max(0))
        assert sorted(tree.rank[tree.rank >= 0]) == list(range(ranks))
        assert np.all(tree.boxes[:, 0] <= tree.boxes[:, 1])
    # lattice: thousands of particles on each plane; keys split a plane's layer
    g = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.1
    from minority.render_server.distribute import classify
    tree = build_tree(g, np.arange(len(g), dtype=np.int64), 3, g.min(0), g.max(0))
    counts = np.bincount(classify(g, np.arange(len(g), dtype=np.int64), tree), minlength=3)
    assert counts.tolist() == [576, 576, 576]


def test_slab_tree_keeps_ordered_balanced_slabs_only():
    from minority.render_server.distribute import classify, slab_tree

    # 3 ranks along y; rank 1's last particle and rank 2's first share a coordinate
    coord = np.zeros((3, 3, 2))
    key = np.zeros((3, 3, 2), np.int64)
    coord[:, 0] = [[0.0, 1.0]] * 3  # x overlaps: not slabs along x
    coord[:, 2] = [[0.0, 1.0]] * 3
    coord[:, 1] = [[0.0, 0.3], [0.31, 0.6], [0.6, 0.9]]
    key[:, 1] = [[0, 9], [3, 7], [8, 2]]  # on y = 0.6, rank 1's key 7 comes before rank 2's 8
    lo, hi = np.zeros(3), np.ones(3)
    tree = slab_tree(coord, key, np.array([100, 100, 100]), lo, hi)
    assert tree is not None and tree.axis[0] == 1
    pts = np.array([[0.5, 0.6, 0.5], [0.5, 0.6, 0.5], [0.5, 0.3, 0.5]])
    assert classify(pts, np.array([7, 8, 9], np.int64), tree).tolist() == [1, 2, 0]
    assert slab_tree(coord, key, np.array([100, 100, 120]), lo, hi) is None  # unbalanced
    key[2, 1, 0] = 6  # rank 2's first now comes before rank 1's last: overlapping
    assert slab_tree(coord, key, np.array([100, 100, 100]), lo, hi) is None


def test_tree_splits_along_the_axis_that_keeps_particles_in_place():
    rng = np.random.default_rng(5)
    sample = rng.random((8000, 3)) * [1.0, 0.2, 2.0]  # z longest
    keys = np.arange(len(sample), dtype=np.int64)
    lo, hi = sample.min(0), sample.max(0)
    assert build_tree(sample, keys, 2, lo, hi).axis[0] == 2
    sources = (sample[:, 0] > 0.5).astype(np.int64)  # rank 0 holds x < 0.5, rank 1 the rest
    tree = build_tree(sample, keys, 2, lo, hi, sources)
    assert tree.axis[0] == 0 and abs(tree.plane[0] - 0.5) < 0.02
    mixed = rng.integers(0, 2, len(sample))  # random holders: no axis keeps more
    assert build_tree(sample, keys, 2, lo, hi, mixed).axis[0] == 2


def test_pool_reuses_its_buffers():
    from minority.render_server.distribute import Pool

    pool = Pool()
    a = pool.get("x", (100, 3), np.float32)
    b = pool.get("x", (80, 3), np.float32)  # smaller: the same memory
    assert a.shape == (100, 3) and b.shape == (80, 3) and np.shares_memory(a, b)
    c = pool.get("x", (1000, 3), np.float32)  # larger: a new buffer
    assert not np.shares_memory(a, c) and pool.nbytes >= c.nbytes


def test_composite_keeps_the_nearest_then_the_lowest_key():
    """Three ranks' layers of 4 pixels: rank 0's own, ranks 1 and 2 packed as the records
    they send; the merge keeps the nearest depth, then the lowest key, in any record order."""
    from minority.render_server.composite import _count_hits, _merge_records, _pack

    rgb = np.array([[[10, 0, 0]] * 4, [[20, 0, 0]] * 4, [[30, 0, 0]] * 4], np.uint8)  # [3, 4, 3]
    depth = np.array([[1.0, 2.0, np.inf, 5.0], [1.0, 1.0, np.inf, 5.0],
                      [0.5, 2.0, np.inf, 5.0]])
    key = np.array([[7, 1, 9, 4], [3, 8, 9, 2], [9, 0, 9, 6]], np.int64)
    starts = np.array([0, 4], np.int64)  # one band: all 4 pixels
    packed = []
    for s in (1, 2):
        count = np.empty(1, np.int64)
        _count_hits(depth[s], starts, count)
        records = np.empty((int(count[0]), 3), np.uint64)
        _pack(rgb[s], depth[s], key[s], starts, np.zeros(1, np.int64), -1, records)
        packed.append(records)
    records = np.concatenate(packed)
    assert len(records) == 6  # pixel 2 is hit nowhere: never sent
    for order in (records, records[::-1].copy()):
        band_rgb, band_hit = np.empty((4, 3), np.uint8), np.empty(4, np.bool_)
        d, k = depth[0].copy(), key[0].copy()
        _merge_records(rgb[0], d, k, 0, order, order.view(np.float64), band_rgb, band_hit)
        assert band_rgb[:, 0].tolist() == [30, 20, 10, 20]  # nearest; nearest; own; lowest key
        assert band_hit.tolist() == [True, True, False, True]
        assert d[:2].tolist() == [0.5, 1.0] and k.tolist() == [9, 8, 9, 2]


def test_composite_on_one_rank_and_bands():
    rgb = np.zeros((4, 5, 3), np.uint8)
    depth = np.full(20, np.inf)
    depth[3] = 1.0
    frame, hit = composite(None, rgb, depth, np.zeros(20, np.int64))
    assert frame.shape == (4, 5, 3) and hit.sum() == 1 and hit[3]
    assert bands(10, 3).tolist() == [0, 3, 6, 10]
    with pytest.raises(ValueError, match="depth and key must be"):
        composite(None, rgb, depth[:5], np.zeros(20, np.int64))


def test_shadows_on_several_ranks_are_refused():
    class TwoRanks:
        size, rank = 2, 0

    step, spec, _ = case("lattice")
    with pytest.raises(ValueError, match="shadows are not drawn on more than one render rank"):
        render_views_distributed(TwoRanks(), step, spec, {}, shadows=True)
    assert "one rank" in SHADOWS_REFUSED


if __name__ == "__main__":
    try:
        worker(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 1,
               Path(sys.argv[3]) if len(sys.argv) > 3 else None)
    except BaseException:  # one rank failing must not leave the others waiting
        import traceback

        from mpi4py import MPI

        traceback.print_exc()
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(1)
