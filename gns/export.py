"""Rollout output: HDF5 (positions, velocities per frame) and a VTK series for ParaView
(one binary .vtp per frame with displacement and velocity point arrays, plus a .pvd)."""

from __future__ import annotations

import json
from pathlib import Path
from xml.sax.saxutils import quoteattr

import h5py
import numpy as np

ROLLOUT_FORMAT = "minority-gns-rollout/1"
SIM_FORMAT = "minority-sim-trajectory/1"  # `minority sim` output, read as a prediction too


def velocities(positions: np.ndarray, frame_interval_s: float) -> np.ndarray:
    """Backward-difference velocity per frame [frames, n, 3], m/s (zero at frame 0)."""
    v = np.zeros_like(positions)
    v[1:] = (positions[1:] - positions[:-1]) / frame_interval_s
    return v


def write_hdf5(path: str | Path, positions: np.ndarray, frame_interval_s: float, *,
               attrs: dict) -> Path:
    """positions [frames, n, 3] (m) -> HDF5 with positions, velocities (m/s), time (s)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames, n, _ = positions.shape
    with h5py.File(path, "w") as f:
        f.create_dataset("positions", data=positions.astype(np.float32), chunks=(1, n, 3))
        f.create_dataset("velocities", data=velocities(positions, frame_interval_s)
                         .astype(np.float32), chunks=(1, n, 3))
        f.create_dataset("displacements", data=(positions - positions[0]).astype(np.float32),
                         chunks=(1, n, 3))
        f.create_dataset("time", data=np.arange(frames) * frame_interval_s)
        f.attrs["format"] = ROLLOUT_FORMAT
        f.attrs["frame_interval_s"] = frame_interval_s
        f.attrs["n_particles"] = n
        f.attrs["units"] = json.dumps({"positions": "m", "velocities": "m/s",
                                       "displacements": "m", "time": "s"})
        for k, v in attrs.items():
            f.attrs[k] = v if not isinstance(v, dict | list) else json.dumps(v)
    return path


def write_vtk_series(directory: str | Path, positions: np.ndarray, frame_interval_s: float,
                     *, stem: str = "rollout", every: int = 1) -> Path:
    """One .vtp per kept frame (points, vertex cells, displacement and velocity arrays, and
    their magnitudes) and stem.pvd listing them with their times (s)."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    frames, n, _ = positions.shape
    vel = velocities(positions, frame_interval_s)
    verts = vtkCellArray()
    offsets = np.arange(n + 1, dtype=np.int64)
    conn = np.arange(n, dtype=np.int64)
    verts.SetData(numpy_to_vtk(offsets, deep=True), numpy_to_vtk(conn, deep=True))
    entries = []
    for k in range(0, frames, every):
        poly = vtkPolyData()
        pts = vtkPoints()
        pts.SetData(numpy_to_vtk(np.ascontiguousarray(positions[k], np.float32), deep=True))
        poly.SetPoints(pts)
        poly.SetVerts(verts)
        disp = np.ascontiguousarray(positions[k] - positions[0], np.float32)
        for name, arr in (("displacement", disp), ("velocity", vel[k].astype(np.float32))):
            a = numpy_to_vtk(arr, deep=True)
            a.SetName(name)
            poly.GetPointData().AddArray(a)
            m = numpy_to_vtk(np.linalg.norm(arr, axis=1).astype(np.float32), deep=True)
            m.SetName(f"{name}_magnitude")
            poly.GetPointData().AddArray(m)
        name = f"{stem}_{k:05d}.vtp"
        w = vtkXMLPolyDataWriter()
        w.SetFileName(str(d / name))
        w.SetInputData(poly)
        w.SetDataModeToAppended()
        w.EncodeAppendedDataOff()
        if not w.Write():
            raise OSError(f"cannot write {d / name}")
        entries.append((k * frame_interval_s, name))
    pvd = d / f"{stem}.pvd"
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{t:.6g}" group="" part="0" file={quoteattr(f)}/>'
              for t, f in entries]
    lines += ["  </Collection>", "</VTKFile>", ""]
    pvd.write_text("\n".join(lines))
    return pvd


def _attribute(value):
    """An HDF5 attribute: JSON objects and lists decoded, other text (e.g. a scene's TOML,
    which may start with "[domain]") as it is."""
    if isinstance(value, str) and value[:1] in ("[", "{"):
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return value


def read_rollout(path: str | Path) -> dict:
    """A rollout written by write_hdf5, or an MPM run's HDF5 (`minority sim`, frames every
    output_interval_s): positions [frames, n, 3] (m), frame_interval_s (s), bounds_m [3, 2]
    (m), particle_spacing_m (m) and the other attributes, checked."""
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if fmt not in (ROLLOUT_FORMAT, SIM_FORMAT):
                raise ValueError(f"{path}: not a rollout (format {fmt!r}, expected "
                                 f"{ROLLOUT_FORMAT!r} or an MPM run's {SIM_FORMAT!r})")
            out = {k: _attribute(v) for k, v in f.attrs.items()}
            out["positions"] = f["positions"][()]
            if fmt == SIM_FORMAT:  # an MPM run (e.g. a coarse one) as the prediction
                out["frame_interval_s"] = float(out["output_interval_s"])
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the rollout ({exc})") from None
    pos = out["positions"]
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 3 or not np.isfinite(pos).all():
        raise ValueError(f"{path}: positions must be finite [frames >= 3, n, 3], got "
                         f"{list(pos.shape)}")
    out["bounds_m"] = np.asarray(out["bounds_m"], dtype=np.float64).reshape(3, 2)
    return out
