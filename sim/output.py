"""The HDF5 trajectory of a run (layout: minority.protocol.trajectory, format SIM_FORMAT), for
GNS training and post hoc rendering.

Frames are flushed as they are written, in SWMR mode: a killed run leaves a readable file with
every complete frame. One file at any rank count: rank 0 gathers every rank's particles per
frame (sim.ranks).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from minority.protocol.trajectory import (
    PARTICLE_TYPE_SAND,
    SIM_FORMAT,
    SIM_SERIES,
    UNITS,
    FrameWriter,
)
from minority.sim.scene import Scene


def scene_attrs(scene: Scene, *, dt_s: float, dt_mode: str) -> dict:
    """The file attributes a run takes from its scene and time step (s)."""
    mat = scene.material
    return {
        "dim": 3, "dt_s": dt_s, "dt_mode": dt_mode,
        "output_interval_s": scene.output_interval_s,
        "bounds_m": np.array([[0.0, s] for s in scene.size_m]),  # [3, 2] lo, hi per axis
        "particle_spacing_m": scene.particle_spacing_m, "cell_size_m": scene.cell_size_m,
        "scene_name": scene.name, "scene_toml": scene.toml_text,
        "material_table": json.dumps({
            "model": "drucker_prager", "density_kg_m3": mat.density_kg_m3,
            "youngs_modulus_pa": mat.youngs_modulus_pa, "poisson_ratio": mat.poisson_ratio,
            "friction_angle_deg": mat.friction_angle_deg, "dp_cone": mat.dp_cone.value}),
    }


class TrajectoryWriter:
    """Append frames of one run of `scene` (n particles, time step dt_s in s, dt_mode "cfl"
    or "fixed") to an HDF5 file; attrs: more file attributes (e.g. ranks, rebalance_every
    of a rank run). Use as a context manager."""

    def __init__(self, path: str | Path, scene: Scene, n: int, *, dt_s: float,
                 dt_mode: str, attrs: dict | None = None) -> None:
        self.path, self.n = Path(path), n
        self._w = FrameWriter(
            path, n, fmt=SIM_FORMAT, units=UNITS,
            attrs={**scene_attrs(scene, dt_s=dt_s, dt_mode=dt_mode), **(attrs or {})},
            particle_data={
                "particle_type": np.full(n, PARTICLE_TYPE_SAND, np.int32),
                "material": np.full(n, scene.material.friction_angle_deg, np.float32)},
            series=SIM_SERIES)

    @property
    def frames(self) -> int:
        return self._w.frames

    def write_frame(self, *, time_s: float, step: int, fields: dict[str, np.ndarray],
                    kinetic_energy_j: float, momentum: np.ndarray) -> None:
        """Append one frame: fields holds [n, 3] arrays named as FRAME_FIELDS (m, m/s, m);
        kinetic energy J, momentum [3] kg m/s."""
        self._w.write_frame(time_s, fields, step=step, kinetic_energy=kinetic_energy_j,
                            momentum=momentum)

    def close(self) -> None:
        self._w.close()

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
