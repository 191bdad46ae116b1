"""Generators of scene TOML text for parameterized column collapses.

Used by the tests (validation, extreme cases), the demo, and the GNS training-data sweep
(minority.sweep) of varied geometry and friction. Lengths in m, angles in degrees, moduli in Pa.
"""

from __future__ import annotations

from dataclasses import dataclass

from minority.sim.scene import DEFAULT_DP_CONE, DEFAULT_FLIP, Scene, loads_scene


@dataclass(frozen=True)
class ColumnSpec:
    """Rectangular column against the back wall (x = 0) of a channel of width width_m."""

    length_m: float = 0.1  # L0, along the flow (x)
    height_m: float = 0.1  # H0
    width_m: float = 0.04  # channel width (y) = column width
    domain_length_m: float = 0.4
    domain_height_m: float = 0.16
    cell_size_m: float = 0.02
    per_cell_per_axis: int = 2
    density_kg_m3: float = 1800.0
    youngs_modulus_pa: float = 1.0e6
    poisson_ratio: float = 0.3
    friction_angle_deg: float = 30.0
    dp_cone: str = DEFAULT_DP_CONE.value  # sim.scene.DPCone value
    floor_friction: float = 0.5
    side_friction: float = 0.0
    top_friction: float | None = None  # the lid (z_max); None: floor_friction
    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.81)
    velocity_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    duration_s: float = 0.2
    output_interval_s: float = 0.02
    cfl: float = 0.3
    flip: float = DEFAULT_FLIP  # FLIP fraction of the particle velocity update (0: APIC)

    @property
    def aspect_ratio(self) -> float:
        return self.height_m / self.length_m


def _vec(v) -> str:
    return "[" + ", ".join(repr(float(c)) for c in v) + "]"


def channel_column_toml(c: ColumnSpec, name: str = "column") -> str:
    """TOML text of a channel column scene."""
    top = "" if c.top_friction is None else f"z_max = {float(c.top_friction)!r}\n"
    return f"""name = "{name}"
gravity_m_s2 = {_vec(c.gravity_m_s2)}

[domain]
size_m = {_vec((c.domain_length_m, c.width_m, c.domain_height_m))}
cell_size_m = {float(c.cell_size_m)!r}

[particles]
per_cell_per_axis = {c.per_cell_per_axis}

[material]
density_kg_m3 = {float(c.density_kg_m3)!r}
youngs_modulus_pa = {float(c.youngs_modulus_pa)!r}
poisson_ratio = {float(c.poisson_ratio)!r}
friction_angle_deg = {float(c.friction_angle_deg)!r}
dp_cone = "{c.dp_cone}"

[[body]]
shape = "box"
lo_m = [0.0, 0.0, 0.0]
hi_m = {_vec((c.length_m, c.width_m, c.height_m))}
velocity_m_s = {_vec(c.velocity_m_s)}

[boundary]
friction = {float(c.floor_friction)!r}
y_min = {float(c.side_friction)!r}
y_max = {float(c.side_friction)!r}
{top}
[time]
duration_s = {float(c.duration_s)!r}
output_interval_s = {float(c.output_interval_s)!r}
cfl = {float(c.cfl)!r}

[numerics]
flip = {float(c.flip)!r}
"""


def channel_column(c: ColumnSpec, name: str = "column") -> Scene:
    return loads_scene(channel_column_toml(c, name), name=name)
