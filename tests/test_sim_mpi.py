"""MPM on MPI ranks: slab boundaries, and a run at 1, 2 and 3 ranks (with particle migration
and rebalancing every 10 steps) writing exactly the single-process trajectory.

The ranks run as `minority sim` subprocesses: 1 rank without a launcher, 2 ranks started by
the user as `mpiexec -n 2 minority sim`, 3 ranks through `--ranks 3` (which re-runs the
command under the venv's mpiexec). One numba thread per rank (CI has 2 cores).
"""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import free_port

from minority.insitu.publisher import STATS_EVERY_S
from minority.protocol.log import read_log
from minority.protocol.messages import speed_histogram
from minority.protocol.view import Window
from minority.sim.decomp import DEFAULT_REBALANCE_EVERY, balanced_starts
from minority.sim.driver import Simulator
from minority.sim.runner import run_scene
from minority.sim.scene import load_scene

TIMEOUT_S = 180
# A sand block thrown along x at 3 m/s while it collapses: in 0.03 s it crosses several
# 4-cell x-blocks (dx 0.01 m), so particles migrate and the slabs rebalance. 3,200 particles.
SLIDE_TOML = """
name = "slide"
[domain]
size_m = [0.4, 0.04, 0.16]
cell_size_m = 0.01
[particles]
per_cell_per_axis = 2
[material]
density_kg_m3 = 1800.0
youngs_modulus_pa = 1.0e6
poisson_ratio = 0.3
friction_angle_deg = 30.0
[[body]]
shape = "box"
lo_m = [0.02, 0.0, 0.0]
hi_m = [0.12, 0.04, 0.1]
velocity_m_s = [3.0, 0.0, 0.0]
[boundary]
friction = 0.5
y_min = 0.0
y_max = 0.0
[time]
duration_s = 0.03
output_interval_s = 0.01
"""


def largest_slab(counts, starts) -> int:
    return max(int(counts[a:b].sum()) for a, b in zip(starts[:-1], starts[1:], strict=True))


def test_balanced_starts_minimize_the_largest_slab():
    counts = np.array([0, 100, 100, 100, 100, 0, 0, 0])
    assert balanced_starts(counts, 1).tolist() == [0, 8]
    assert balanced_starts(counts, 2).tolist() == [0, 3, 8]
    assert balanced_starts(counts, 4).tolist() == [0, 2, 3, 4, 8]
    # every rank keeps at least one block, even without particles
    assert balanced_starts(np.array([0, 0, 400, 0, 0]), 3).tolist() == [0, 3, 4, 5]
    assert balanced_starts(np.zeros(3, np.int64), 3).tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="only 3 x-blocks"):
        balanced_starts(np.ones(3, np.int64), 4)
    # against every partition: the largest slab is as small as it can be
    from itertools import combinations

    rng = np.random.default_rng(5)
    for _ in range(50):
        size = int(rng.integers(3, 9))
        counts = rng.integers(0, 50, size) * (rng.random(size) < 0.7)  # some empty blocks
        for ranks in range(1, min(4, counts.size) + 1):
            starts = balanced_starts(counts, ranks).tolist()
            assert starts[0] == 0 and starts[-1] == counts.size
            assert all(b > a for a, b in zip(starts[:-1], starts[1:], strict=True))
            best = min(largest_slab(counts, [0, *cuts, counts.size])
                       for cuts in combinations(range(1, counts.size), ranks - 1))
            assert largest_slab(counts, starts) == best


def test_cli_default_matches_decomp():
    from minority.cli import DEFAULT_REBALANCE_EVERY as CLI_DEFAULT

    assert CLI_DEFAULT == DEFAULT_REBALANCE_EVERY


def sim_command(scene: Path, out: Path, *extra: str) -> list[str]:
    return ["-m", "minority", "sim", str(scene), "--out", str(out), "--threads", "1",
            "--rebalance-every", "10", "--no-publish", "-q", *extra]


def run(cmd: list[str]) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    return proc.stderr


@pytest.fixture(scope="module")
def slide(tmp_path_factory):
    d = tmp_path_factory.mktemp("mpi")
    scene = d / "slide.toml"
    scene.write_text(SLIDE_TOML)
    run_scene(scene, d / "reference.h5", threads=1, progress=False)  # the plain Simulator
    return d, scene


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_positions_do_not_depend_on_the_rank_count(slide, ranks):
    d, scene = slide
    out = d / f"ranks{ranks}.h5"
    if ranks == 2:  # started by the user under mpiexec, without --ranks
        mpiexec = str(Path(sys.executable).parent / "mpiexec")
        err = run([mpiexec, "-n", "2", sys.executable, *sim_command(scene, out)])
    else:
        err = run([sys.executable, *sim_command(scene, out, "--ranks", str(ranks))])
    assert f"3200 particles, {ranks} rank(s), 306 steps, 4 frames" in err
    if ranks > 1:  # the run exercised what it claims to
        rebalances, migrated = map(int, re.search(r"(\d+) rebalances, (\d+) particles migrated",
                                                  err).groups())
        assert rebalances >= 1 and migrated > 100
    with h5py.File(d / "reference.h5") as ref, h5py.File(out) as got:
        assert got.attrs["ranks"] == ranks
        assert np.array_equal(got["step"][:], ref["step"][:])
        assert np.array_equal(got["time"][:], ref["time"][:])
        # bitwise, not only to float32 round-off: the same sums in the same order
        for name in ("positions", "velocities", "displacements"):
            assert np.array_equal(got[name][:], ref[name][:]), name
        # energy and momentum are sums over ranks: equal to round-off
        np.testing.assert_allclose(got["kinetic_energy"][:], ref["kinetic_energy"][:],
                                   rtol=1e-12)
        np.testing.assert_allclose(got["momentum"][:], ref["momentum"][:], rtol=1e-12,
                                   atol=1e-15)


def test_rank_count_must_match_the_launcher(slide, tmp_path):
    _, scene = slide
    mpiexec = str(Path(sys.executable).parent / "mpiexec")
    proc = subprocess.run([mpiexec, "-n", "2", sys.executable,
                           *sim_command(scene, tmp_path / "x.h5", "--ranks", "3")],
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode != 0
    assert "--ranks 3, but the launcher started 2 processes" in proc.stderr


@pytest.mark.slow
def test_every_rank_publishes_its_stats(tmp_path):
    """2 ranks with a spec file and a record, no server: each rank records its own Stats at
    the default cadence (5 ms of simulated time, step 0 included); at each of those steps the
    ranks' counts and in-region histograms add up to the single-process particles."""
    scene = tmp_path / "slide.toml"
    scene.write_text(SLIDE_TOML)
    run_id, steps = "slide-stats", 120
    spec = {"version": 2, "run": run_id,
            "regions": [{"name": "front", "lo_m": [0.1, -1.0, -1.0], "hi_m": [1.0, 1.0, 1.0]}],
            "views": [{"name": "side", "camera": {"position": [0.2, -1.0, 0.08],
                                                  "focal_point": [0.2, 0.02, 0.08]},
                       "schedule": [{"every_steps": 50, "regions": ["front"]}]}]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    mpiexec = str(Path(sys.executable).parent / "mpiexec")
    run([mpiexec, "-n", "2", sys.executable, "-m", "minority", "sim", str(scene),
         "--out", str(tmp_path / "slide.h5"), "--threads", "1", "--rebalance-every", "10",
         "--steps", str(steps), "-q", "--run", run_id, "--spec", str(tmp_path / "spec.json"),
         "--record", str(tmp_path / "sim.mcap"), "--connect", f"tcp/127.0.0.1:{free_port()}"])
    by_rank = {rank: [r.decode() for r in read_log(tmp_path / name, [f"minority/{run_id}/stats"])]
               for rank, name in ((0, "sim.mcap"), (1, "sim.rank1.mcap"))}
    sim = Simulator(load_scene(scene))  # the single-process run, step by step, frame by frame
    cadence, prev, expected = Window(every_s=STATS_EVERY_S), None, {}
    for k in range(steps + 1):
        if k:
            sim.advance_to(next(f for f in (0.01, 0.02, 0.03) if not sim.reached(f)), 1)
        if cadence.wants(k, sim.time_s, prev):
            ps = sim.particles
            expected[k] = (sim.time_s, ps.x.copy(), ps.x0.copy(), np.linalg.norm(ps.v, axis=1))
        prev = sim.time_s
    assert next(iter(expected)) == 0 and len(expected) == 3  # t = 0, 5 ms, 10 ms (a frame)
    for rank, messages in by_rank.items():
        assert [m.step for m in messages] == list(expected)
        assert all(m.rank == rank and m.windows_open and m.count > 0 for m in messages)
    for i, (t, x, x0, speed) in enumerate(expected.values()):
        parts = [by_rank[0][i], by_rank[1][i]]
        assert all(m.time_s == t for m in parts)
        front = x[:, 0] >= 0.1
        assert sum(m.count for m in parts) == x.shape[0] == 3200
        hist_in = np.sum([m.hist_in_regions for m in parts], axis=0).tolist()
        hist_out = np.sum([m.hist_elsewhere for m in parts], axis=0).tolist()
        assert hist_in == speed_histogram(speed[front])
        assert hist_out == speed_histogram(speed[~front])
        assert max(m.max_displacement_m for m in parts) == pytest.approx(
            np.linalg.norm(x - x0, axis=1).max(), rel=1e-12, abs=1e-300)
