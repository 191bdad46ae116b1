"""Stiff and extreme cases: each ends with finite state and bounded energy."""

import numpy as np
import pytest

from minority.sim.columns import ColumnSpec, channel_column
from minority.sim.driver import Simulator

# Tolerances, one table.
TOL = {
    "energy_gain": 0.05,  # (KE + PE)_end may exceed (KE + PE)_start by this fraction at most
}

CASES = {
    # name: (ColumnSpec, duration_s)
    "E=1e5 Pa": (ColumnSpec(youngs_modulus_pa=1e5), 0.3),
    "E=1e9 Pa": (ColumnSpec(youngs_modulus_pa=1e9), 0.03),
    "aspect 0.25": (ColumnSpec(length_m=0.2, height_m=0.05, cell_size_m=0.01,
                               width_m=0.02), 0.3),
    "aspect 10": (ColumnSpec(length_m=0.04, height_m=0.4, cell_size_m=0.01, width_m=0.02,
                             domain_length_m=0.6, domain_height_m=0.45), 0.4),
    "friction 10 deg": (ColumnSpec(friction_angle_deg=10.0), 0.3),
    "friction 60 deg": (ColumnSpec(friction_angle_deg=60.0), 0.3),
    "column touching top and far wall": (ColumnSpec(length_m=0.4, height_m=0.16), 0.2),
}


def _bodies_toml(lo, hi, velocity, gravity, size=(0.4, 0.16, 0.16)):
    return f"""
gravity_m_s2 = {list(gravity)}
[domain]
size_m = {list(size)}
cell_size_m = 0.02
[material]
density_kg_m3 = 1800.0
youngs_modulus_pa = 1.0e6
poisson_ratio = 0.3
friction_angle_deg = 30.0
[[body]]
shape = "box"
lo_m = {list(lo)}
hi_m = {list(hi)}
velocity_m_s = {list(velocity)}
[boundary]
friction = 0.5
[time]
duration_s = 0.1
output_interval_s = 0.01
"""


def _check(sim: Simulator, duration: float) -> None:
    d0 = sim.diagnostics()
    e0 = d0.kinetic_energy_j + d0.potential_energy_j
    sim.advance_to(duration)  # raises on non-finite state or an escaped particle
    ps = sim.particles
    for field in (ps.x, ps.v, ps.F, ps.tau):
        assert np.isfinite(field).all()
    assert (ps.x >= 0.0).all() and (ps.x <= np.array(sim.scene.size_m)).all()
    d1 = sim.diagnostics()
    e1 = d1.kinetic_energy_j + d1.potential_energy_j
    assert e1 <= e0 * (1.0 + TOL["energy_gain"])


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_extreme_column(name):
    spec, duration = CASES[name]
    _check(Simulator(channel_column(spec, name=name.replace(" ", "_"))), duration)


@pytest.mark.slow
def test_block_thrown_at_wall_at_10_m_s():
    from minority.sim.scene import loads_scene

    text = _bodies_toml((0.2, 0.04, 0.04), (0.28, 0.12, 0.12), (-10.0, 0.0, 0.0),
                        (0.0, 0.0, -9.81))
    sim = Simulator(loads_scene(text, name="thrown"))
    _check(sim, 0.1)
    assert sim.particles.x[:, 0].min() < 0.05  # it reached the wall (m)


@pytest.mark.slow
def test_single_particle_falls_and_rests():
    from minority.sim.scene import loads_scene

    text = _bodies_toml((0.2, 0.07, 0.1), (0.21, 0.08, 0.11), (0.5, 0.0, 0.0),
                        (0.0, 0.0, -9.81))
    sim = Simulator(loads_scene(text, name="single"))
    assert sim.particles.n == 1
    _check(sim, 0.4)
    assert sim.particles.x[0, 2] < 0.02  # on the floor (m)
