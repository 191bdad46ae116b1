"""HDF5 trajectory writer (h5py) for GNS training and post hoc rendering.

Layout (frames grow along axis 0, one chunk per frame, flushed after every frame; the
file is written in SWMR mode so a killed run leaves a readable file with every completed
frame; `time` is written last, so len(time) is the number of complete frames):

    positions      [frames, n, 3] float32, m
    velocities     [frames, n, 3] float32, m/s
    displacements  [frames, n, 3] float32, m (from the initial position)
    time           [frames] float64, s
    step           [frames] int64, MPM steps taken
    kinetic_energy [frames] float64, J
    momentum       [frames, 3] float64, kg m/s
    particle_type  [n] int32 (PARTICLE_TYPE_SAND)
    material       [n] float32, friction angle in degrees
    attrs: units (JSON), dt_s, dt_mode, output_interval_s, bounds_m, particle_spacing_m,
           cell_size_m, n_particles, dim, scene_toml, material_table (JSON), format, and
           from `minority sim` (sim.ranks) also ranks, rebalance_every

One file at any rank count: rank 0 gathers every rank's particles per frame (sim.ranks).
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
from minority.sim.scene import Scene

FORMAT = "minority-sim-trajectory/1"
PARTICLE_TYPE_SAND = 6  # the id GNS (learning_to_simulate lineage) uses for sand
FRAME_FIELDS = ("positions", "velocities", "displacements")
UNITS = {
    "positions": "m", "velocities": "m/s", "displacements": "m", "time": "s",
    "kinetic_energy": "J", "momentum": "kg m/s", "material": "deg (friction angle)",
    "bounds_m": "m", "particle_spacing_m": "m", "cell_size_m": "m", "dt_s": "s",
    "output_interval_s": "s", "step": "1", "particle_type": "1",
}


class TrajectoryWriter:
    """Append frames of one run to an HDF5 file. Use as a context manager."""

    def __init__(self, path: str | Path, scene: Scene, n: int, *, dt_s: float,
                 dt_mode: str, attrs: dict | None = None) -> None:
        self.path = Path(path)
        self.n = n
        self.frames = 0
        self._f = h5py.File(self.path, "w", libver="latest")
        f = self._f
        for name in FRAME_FIELDS:
            f.create_dataset(name, shape=(0, n, 3), maxshape=(None, n, 3), dtype="f4",
                             chunks=(1, n, 3))
        f.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(1024,))
        f.create_dataset("step", shape=(0,), maxshape=(None,), dtype="i8", chunks=(1024,))
        f.create_dataset("kinetic_energy", shape=(0,), maxshape=(None,), dtype="f8",
                         chunks=(1024,))
        f.create_dataset("momentum", shape=(0, 3), maxshape=(None, 3), dtype="f8",
                         chunks=(1024, 3))
        f.create_dataset("particle_type", data=np.full(n, PARTICLE_TYPE_SAND, np.int32))
        mat = scene.material
        f.create_dataset("material", data=np.full(n, mat.friction_angle_deg, np.float32))
        a = f.attrs
        a["format"] = FORMAT
        a["units"] = json.dumps(UNITS)
        a["dim"] = 3
        a["n_particles"] = n
        a["dt_s"] = dt_s
        a["dt_mode"] = dt_mode
        a["output_interval_s"] = scene.output_interval_s
        a["bounds_m"] = np.array([[0.0, s] for s in scene.size_m])  # [3, 2] lo, hi per axis
        a["particle_spacing_m"] = scene.particle_spacing_m
        a["cell_size_m"] = scene.cell_size_m
        a["scene_name"] = scene.name
        a["scene_toml"] = scene.toml_text
        a["material_table"] = json.dumps({
            "model": "drucker_prager", "density_kg_m3": mat.density_kg_m3,
            "youngs_modulus_pa": mat.youngs_modulus_pa, "poisson_ratio": mat.poisson_ratio,
            "friction_angle_deg": mat.friction_angle_deg, "dp_cone": mat.dp_cone.value})
        for key, value in (attrs or {}).items():  # e.g. ranks, rebalance_every of a rank run
            a[key] = value
        f.swmr_mode = True
        f.flush()

    def write_frame(self, *, time_s: float, step: int, fields: dict[str, np.ndarray],
                    kinetic_energy_j: float, momentum: np.ndarray) -> None:
        """Append one frame; fields holds [n, 3] arrays named as FRAME_FIELDS."""
        f, k = self._f, self.frames
        for name in FRAME_FIELDS:
            ds = f[name]
            ds.resize(k + 1, axis=0)
            ds[k] = fields[name].astype(np.float32)
        for name, value in (("step", step), ("kinetic_energy", kinetic_energy_j),
                            ("momentum", momentum), ("time", time_s)):
            ds = f[name]
            ds.resize(k + 1, axis=0)
            ds[k] = value
        f.flush()
        self.frames = k + 1

    def close(self) -> None:
        if self._f.id.valid:
            self._f.close()

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_trajectory(path: str | Path) -> h5py.File:
    """Open a trajectory for reading, also one whose writer was killed (SWMR read; a plain
    h5py.File(path, 'r') refuses such a file as 'already open for write')."""
    return h5py.File(path, "r", swmr=True)
