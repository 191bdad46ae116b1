"""Particle frames as a VTK series for ParaView: one binary .vtp per frame and a .pvd.

Each {stem}_{step:06d}.vtp holds the particles as points with one vertex cell each, every
field as a point array (a vector field [n, 3] also as {name}_magnitude when asked), and the
frame's time (s) as the field-data array TimeValue. {stem}.pvd lists the files by time, so
ParaView's time controls step through them. vtk is imported when a frame is written.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

MAGNITUDE_SUFFIX = "_magnitude"


@dataclass
class ParticleFrame:
    """What a series writes: this, or any object with these attributes (e.g. the render
    server's AssembledStep)."""

    step: int  # the number in the file name: a sim step, or a frame of a rollout
    time_s: float  # s
    positions: np.ndarray  # [n, 3], m
    fields: dict[str, np.ndarray]  # name -> [n] or [n, k] point data


class VtkSeries:
    """Write frames with add(), then close() writes the .pvd (and returns its path).

    directory: created if missing. magnitudes: also write |v| of every [n, 3] field."""

    def __init__(self, directory: str | Path, stem: str, *, magnitudes: bool = False) -> None:
        self.directory, self.stem, self.magnitudes = Path(directory), stem, magnitudes
        self.directory.mkdir(parents=True, exist_ok=True)
        self.entries: list[tuple[float, str]] = []

    def add(self, frame: ParticleFrame) -> Path:
        """Write one frame as {stem}_{frame.step:06d}.vtp at frame.time_s (s); point data
        dtypes are kept. Returns the .vtp path."""
        from vtkmodules.util.numpy_support import numpy_to_vtk
        from vtkmodules.vtkCommonCore import vtkDoubleArray, vtkPoints
        from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
        from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

        positions, fields = frame.positions, frame.fields
        n = len(positions)
        poly, pts, verts = vtkPolyData(), vtkPoints(), vtkCellArray()
        pts.SetData(numpy_to_vtk(np.ascontiguousarray(positions), deep=True))
        verts.SetData(numpy_to_vtk(np.arange(n + 1, dtype=np.int64), deep=True),
                      numpy_to_vtk(np.arange(n, dtype=np.int64), deep=True))
        poly.SetPoints(pts)
        poly.SetVerts(verts)
        arrays = []
        for name, values in fields.items():
            arrays.append((name, values))
            if self.magnitudes and values.ndim == 2 and values.shape[1] == 3:
                norm = np.linalg.norm(values, axis=1).astype(values.dtype)
                arrays.append((name + MAGNITUDE_SUFFIX, norm))
        for name, values in arrays:
            array = numpy_to_vtk(np.ascontiguousarray(values), deep=True)
            array.SetName(name)
            poly.GetPointData().AddArray(array)
        t = vtkDoubleArray()
        t.SetName("TimeValue")
        t.InsertNextValue(frame.time_s)
        poly.GetFieldData().AddArray(t)
        path = self.directory / f"{self.stem}_{frame.step:06d}.vtp"
        w = vtkXMLPolyDataWriter()
        w.SetFileName(str(path))
        w.SetInputData(poly)
        w.SetDataModeToAppended()
        w.EncodeAppendedDataOff()
        if not w.Write():
            raise OSError(f"cannot write {path}")
        self.entries.append((float(frame.time_s), path.name))
        return path

    def close(self) -> Path:
        """Write {stem}.pvd listing the files by time (s, written exactly: repr)."""
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
                 "  <Collection>"]
        lines += [f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(f)}/>'
                  for t, f in sorted(self.entries)]
        lines += ["  </Collection>", "</VTKFile>", ""]
        pvd = self.directory / f"{self.stem}.pvd"
        pvd.write_text("\n".join(lines))
        return pvd
