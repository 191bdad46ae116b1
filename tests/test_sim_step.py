"""MPM step properties: conservation, symmetry, determinism, the NumPy reference, guards."""

import numba
import numpy as np
import pytest

from minority.sim import kernels
from minority.sim.columns import ColumnSpec, channel_column
from minority.sim.driver import NonFiniteError, Simulator, TimeStepError
from minority.sim.reference import ReferenceState, reference_step
from minority.sim.scene import builtin_scene_path, load_scene, loads_scene
from minority.sim.state import PARTICLE_FIELDS, seed_particles

# Tolerances, one table (float64 state).
TOL = {
    "mass_rel": 1e-13,  # grid mass vs particle mass after P2G
    "momentum_rel": 1e-12,  # free flight, per unit of sum m |v|
    "reference_abs": 1e-10,  # numba vs NumPy step, on O(1)-scaled fields
    "symmetry_m": 1e-9,  # mirror-image particle positions, m
}


FREE_BLOB_TOML = """
gravity_m_s2 = [0.0, 0.0, 0.0]
[domain]
size_m = [0.24, 0.24, 0.24]
cell_size_m = 0.02
[material]
density_kg_m3 = 1800.0
youngs_modulus_pa = 1.0e6
poisson_ratio = 0.3
friction_angle_deg = 30.0
[[body]]
shape = "box"
lo_m = [0.08, 0.08, 0.08]
hi_m = [0.16, 0.16, 0.16]
velocity_m_s = [0.3, -0.2, 0.1]
[boundary]
friction = 0.5
[time]
duration_s = 0.1
output_interval_s = 0.01
"""


def _free_blob(seed=0):
    """A stressed, spinning, flying blob: no gravity, far from every wall."""
    sim = Simulator(loads_scene(FREE_BLOB_TOML))
    ps = sim.particles
    r = ps.x - ps.x.mean(axis=0)  # m
    spin = np.cross([0.0, 0.0, 10.0], r)  # 10 rad/s about z
    squeeze = -5.0 * r  # converging at 5 1/s: compression builds stress
    noise = 0.05 * np.random.default_rng(seed).normal(size=r.shape)
    ps.v += spin + squeeze + noise
    return sim


def _momentum(sim):
    ps = sim.particles
    return (ps.mass[:, None] * ps.v).sum(axis=0)


def test_mass_conserved():
    sim = Simulator(load_scene(builtin_scene_path("tiny")))
    m0 = sim.particles.mass.sum()
    n0 = sim.particles.n
    for _ in range(100):
        sim.step(sim.next_dt(1.0))
        grid_mass = sim.grid.data[..., 3].sum()
        assert abs(grid_mass - m0) <= TOL["mass_rel"] * m0
    assert sim.particles.n == n0
    assert np.array_equal(np.sort(sim.particles.pid), np.arange(n0))
    assert sim.particles.mass.sum() == m0


def test_momentum_conserved_in_free_flight():
    sim = _free_blob()
    p0 = _momentum(sim)
    scale = (sim.particles.mass * np.linalg.norm(sim.particles.v, axis=1)).sum()
    peak_stress = 0.0
    for _ in range(60):
        sim.step(sim.next_dt(1.0))
        peak_stress = max(peak_stress, np.abs(sim.particles.tau).max())
    assert peak_stress > 1000.0  # the squeeze stressed the blob (Pa) before it rebounded
    assert np.abs(_momentum(sim) - p0).max() <= TOL["momentum_rel"] * scale
    assert sim.clamp_count == 0


def test_mirror_symmetric_cylinder_stays_symmetric():
    scene = load_scene(builtin_scene_path("cylinder_small"))
    sim = Simulator(scene)
    sim.advance_to(0.1)
    x = sim.fields_by_id()["positions"]
    x0 = seed_particles(scene).x
    size = np.array(scene.size_m)
    for axis in (0, 1):
        mirror = x0.copy()
        mirror[:, axis] = size[axis] - mirror[:, axis]
        # partner of each particle in the mirrored initial configuration
        key = {tuple(np.round(p, 9)): i for i, p in enumerate(x0)}
        partner = np.array([key[tuple(np.round(p, 9))] for p in mirror])
        xm = x[partner].copy()
        xm[:, axis] = size[axis] - xm[:, axis]
        assert np.abs(xm - x).max() < TOL["symmetry_m"]
    assert np.abs(x - x0).max() > 0.01  # it did collapse (m)


def test_result_independent_of_thread_count():
    results = []
    default = numba.get_num_threads()
    try:
        for threads in (1, numba.config.NUMBA_NUM_THREADS):
            sim = Simulator(load_scene(builtin_scene_path("tiny")), threads=threads)
            sim.advance_to(0.05)
            results.append(sim.fields_by_id()["positions"])
    finally:
        numba.set_num_threads(default)
    assert np.array_equal(results[0], results[1])


def _reference_state(sim):
    ps = sim.particles
    return ReferenceState(ps.x.copy(), ps.v.copy(), ps.C.copy(), ps.F.copy(), ps.tau.copy())


def test_numba_step_equals_numpy_reference():
    scene = channel_column(ColumnSpec(velocity_m_s=(0.8, 0.0, -0.3)))
    sim = Simulator(scene)
    sim.advance_to(0.03)  # develop stress, plastic flow and wall contact
    mat = scene.material
    lam, mu, alpha = mat.lame_lambda_pa, mat.shear_modulus_pa, mat.dp_alpha
    ref = _reference_state(sim)
    for _ in range(5):
        dt = sim.next_dt(1.0)
        ref, ref_grid = reference_step(
            ref, mass=sim.particles.mass, vol0=sim.particles.vol0, grid_shape=sim.grid.shape,
            origin=sim.grid.origin, dx=sim.grid.dx, dt=dt, gravity=sim._gravity,
            walls=sim.walls, lo=sim._lo, hi=sim._hi, lam=lam, mu=mu, alpha=alpha,
            flip=scene.flip)
        sim.step(dt)
    ps = sim.particles
    stress_scale = mat.youngs_modulus_pa
    assert np.abs(ps.x - ref.x).max() < TOL["reference_abs"]
    assert np.abs(ps.v - ref.v).max() < TOL["reference_abs"]
    assert np.abs(ps.C - ref.C).max() * sim.grid.dx < TOL["reference_abs"]
    assert np.abs(ps.F - ref.F).max() < TOL["reference_abs"]
    assert np.abs(ps.tau - ref.tau).max() / stress_scale < TOL["reference_abs"]
    fields = ref_grid.shape[-1]  # velocity, mass, velocity change; the rest is padding
    assert np.abs(sim.grid.data[..., :fields] - ref_grid).max() < TOL["reference_abs"]
    assert not sim.grid.data[..., fields:].any()
    # the comparison exercised plasticity: some particles sit on the yield surface
    U, sig, Vt = np.linalg.svd(ps.F)
    eps = np.log(sig)
    tr = eps.sum(axis=1)
    dev = np.linalg.norm(eps - tr[:, None] / 3, axis=1)
    yld = dev + (3 * lam + 2 * mu) / (2 * mu) * tr * alpha
    assert (np.abs(yld) < 1e-9).sum() > 10
    assert sim.walls.axis.size == 6 and (np.abs(ref_grid[..., :3]).max() > 0)


def test_user_dt_above_bound_is_refused_with_the_bound():
    scene = load_scene(builtin_scene_path("tiny"))
    bound = Simulator(scene).stable_dt()
    with pytest.raises(TimeStepError, match=f"stable bound {bound:.6g} s"):
        Simulator(scene, fixed_dt=2.0 * bound)
    sim = Simulator(scene, fixed_dt=0.5 * bound)
    sim.advance_to(0.01)
    assert sim.time_s == pytest.approx(0.01, abs=0.5 * bound)


def test_fixed_dt_that_becomes_unstable_stops_the_run():
    scene = channel_column(ColumnSpec(velocity_m_s=(0.0, 0.0, 0.0)))
    sim = Simulator(scene, fixed_dt=Simulator(scene).stable_dt())  # right at the bound
    with pytest.raises(TimeStepError, match="exceeds the stable bound"):
        sim.advance_to(0.2)


def test_nonfinite_guard_names_step_particle_and_field():
    sim = Simulator(load_scene(builtin_scene_path("tiny")))
    sim.advance_to(0.01)
    steps = sim.step_count
    victim = 123
    slot = int(np.flatnonzero(sim.particles.pid == victim)[0])
    sim.particles.v[slot, 2] = np.nan
    with pytest.raises(NonFiniteError, match=rf"non-finite velocity at step {steps + 1}") as e:
        sim.step(sim.next_dt(1.0))
    # the reported particle really is non-finite
    reported = int(str(e.value).split("particle ")[1].split(";")[0])
    slot = int(np.flatnonzero(sim.particles.pid == reported)[0])
    assert not np.isfinite(sim.particles.v[slot]).all()


def test_particles_g2p_could_not_update_stop_the_run(monkeypatch):
    """G2P leaves a particle that read a non-finite grid velocity where it was (finite) and
    counts it: the run stops naming the count, not going on with frozen particles."""
    sim = Simulator(load_scene(builtin_scene_path("tiny")))
    sim.advance_to(0.01)
    real = kernels.g2p

    def skipping(*args):
        real(*args)
        args[-1][1] = 3.0  # out_stats[1]: particles skipped

    monkeypatch.setattr(kernels, "g2p", skipping)
    with pytest.raises(NonFiniteError, match=r"non-finite grid velocity at step \d+ .*: 3 "
                                             r"particles could not be updated"):
        sim.step(sim.next_dt(1.0))


def test_find_nonfinite_reports_first_slot_and_field():
    ps = seed_particles(load_scene(builtin_scene_path("tiny")))
    assert kernels.find_nonfinite(ps.x, ps.v, ps.C, ps.F, ps.tau) == (-1, -1)
    ps.F[37, 1, 2] = np.inf
    ps.tau[200, 0, 0] = np.nan
    p, code = kernels.find_nonfinite(ps.x, ps.v, ps.C, ps.F, ps.tau)
    assert (p, kernels.FIELD_NAMES[code]) == (37, "deformation_gradient")


def test_parallel_counting_sort_is_the_stable_sort():
    sim = Simulator(load_scene(builtin_scene_path("column_13k")))
    sim.advance_to(0.02)
    ps, g, b = sim.particles, sim.grid, sim._bins
    rng = np.random.default_rng(3)
    x = ps.x[rng.permutation(ps.n)]  # scrambled storage order
    shape = np.array(g.shape, np.int64)
    off = np.zeros(3, np.int64)
    bad, n_active = kernels.bin_particles(x, g.x0, 1.0 / g.dx, shape, off, b.nblocks3,
                                          b.block_start, b.order, b.block_slot,
                                          b.active_blocks, b.key, b.counts, b.first_bad)
    assert bad == -1
    X = (x - g.x0) / g.dx
    cell = np.floor(X - 0.5).astype(np.int64) // kernels.BLOCK_CELLS
    nb3 = b.nblocks3
    key = (cell[:, 0] * nb3[1] + cell[:, 1]) * nb3[2] + cell[:, 2]
    assert np.array_equal(b.key, key)
    assert np.array_equal(b.order, np.argsort(key, kind="stable"))
    counts = np.bincount(key, minlength=int(nb3.prod()))
    assert np.array_equal(np.diff(b.block_start), counts)
    active = np.flatnonzero(counts)
    assert n_active == active.size
    assert np.array_equal(b.active_blocks[:n_active], active)
    assert np.array_equal(b.block_slot[active], np.arange(n_active))
    assert (b.block_slot[counts == 0] == -1).all()
    # the first particle (in storage order) whose stencil leaves the grid is reported
    x[[4000, 9000]] = [-1.0, 0.0, 0.0]
    bad, _ = kernels.bin_particles(x, g.x0, 1.0 / g.dx, shape, off, b.nblocks3, b.block_start,
                                   b.order, b.block_slot, b.active_blocks, b.key, b.counts,
                                   b.first_bad)
    assert bad == 4000


def test_permute_reorders_every_array_and_reuses_only_writable_spares():
    ps = seed_particles(load_scene(builtin_scene_path("tiny")))
    ps.v[:] = np.random.default_rng(1).normal(size=ps.v.shape)
    ps.F = np.broadcast_to(np.eye(3), ps.F.shape)  # read-only, as a broadcast can be
    before = {name: getattr(ps, name).copy() for name in ("x", "v", "F", "pid")}
    order = np.random.default_rng(2).permutation(ps.n)
    ps.permute(order)
    ps.permute(order)  # the read-only F is not reused as a destination
    for name, a in before.items():
        assert np.array_equal(getattr(ps, name), a[order][order])
        assert getattr(ps, name).flags.writeable


def test_particle_arrays_stay_c_contiguous():
    """The kernels are compiled per array layout and two layouts of one state round
    differently (a Fortran-ordered velocity once broke bitwise rank independence)."""
    scene = channel_column(ColumnSpec(velocity_m_s=(0.5, 0.0, 0.0)))
    sim = Simulator(scene)
    for _ in range(2):  # the seeded arrays, then the permuted ones (and their spares)
        for name in PARTICLE_FIELDS:
            assert getattr(sim.particles, name).flags.c_contiguous, name
        sim.particles.permute(np.arange(sim.particles.n)[::-1].copy())
