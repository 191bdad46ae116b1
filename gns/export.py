"""Rollout output: an HDF5 trajectory (layout: minority.protocol.trajectory, format
ROLLOUT_FORMAT) and a VTK series for ParaView (minority.protocol.vtkseries: one binary .vtp
per frame with displacement and velocity point arrays and their magnitudes, plus a .pvd)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from minority.protocol.trajectory import write_rollout
from minority.protocol.vtkseries import ParticleFrame, VtkSeries


def velocities(positions: np.ndarray, frame_interval_s: float) -> np.ndarray:
    """Backward-difference velocity per frame [frames, n, 3], m/s (zero at frame 0)."""
    v = np.zeros_like(positions)
    v[1:] = (positions[1:] - positions[:-1]) / frame_interval_s
    return v


def write_hdf5(path: str | Path, positions: np.ndarray, frame_interval_s: float, *,
               attrs: dict) -> Path:
    """positions [frames, n, 3] (m) -> a rollout file with positions, backward-difference
    velocities (m/s), displacements (m) and time (s)."""
    return write_rollout(path, positions, velocities(positions, frame_interval_s),
                         frame_interval_s, attrs=attrs)


def write_vtk_series(directory: str | Path, positions: np.ndarray, frame_interval_s: float,
                     *, stem: str = "rollout", every: int = 1) -> Path:
    """Every `every`-th frame of positions [frames, n, 3] (m, frames frame_interval_s apart)
    as {stem}_{frame:06d}.vtp with displacement (m) and velocity (m/s) arrays and their
    magnitudes, and {stem}.pvd listing them with their times (s)."""
    vel = velocities(positions, frame_interval_s)
    series = VtkSeries(directory, stem, magnitudes=True)
    for k in range(0, len(positions), every):
        series.add(ParticleFrame(k, k * frame_interval_s, positions[k].astype(np.float32), {
            "displacement": (positions[k] - positions[0]).astype(np.float32),
            "velocity": vel[k].astype(np.float32)}))
    return series.close()
