"""MPM on MPI ranks: slab boundaries, and a run at 1, 2 and 3 ranks (with particle migration
and rebalancing every 10 steps) writing exactly the single-process trajectory.

The ranks run as `minority sim` subprocesses: 1 rank without a launcher, 2 ranks started by
the user as `mpiexec -n 2 minority sim`, 3 ranks through `--ranks 3` (which re-runs the
command under the venv's mpiexec). One numba thread per rank (CI has 2 cores).
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from sim.decomp import DEFAULT_REBALANCE_EVERY, balanced_starts
from sim.runner import run_scene

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
