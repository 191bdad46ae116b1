"""VTK series (protocol.vtkseries): each .vtp read back with vtk's own reader holds the points,
one vertex per particle, every field, the asked magnitudes and TimeValue; the .pvd is a
ParaView collection listing the files by time."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from minority.protocol.vtkseries import ParticleFrame, VtkSeries

pytest.importorskip("vtkmodules")


def read_vtp(path):
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    pd = poly.GetPointData()
    arrays = {pd.GetArrayName(i): vtk_to_numpy(pd.GetArray(i))
              for i in range(pd.GetNumberOfArrays())}
    t = poly.GetFieldData().GetArray("TimeValue")
    return poly, vtk_to_numpy(poly.GetPoints().GetData()), arrays, t.GetValue(0)


def frame(k, t, n=40):
    rng = np.random.default_rng(k)
    pos = rng.uniform(0.0, 0.1, (n, 3)).astype(np.float32)
    return ParticleFrame(k, t, pos, {"velocity": rng.normal(0, 1, (n, 3)).astype(np.float32),
                             "id": np.arange(n, dtype=np.uint32),
                             "stress_pa": rng.normal(0, 1e3, n).astype(np.float64)})


def test_frames_read_back_with_their_fields_and_time(tmp_path):
    series = VtkSeries(tmp_path / "vtk", "run", magnitudes=True)
    for k, t in ((0, 0.0), (7, 0.0175)):
        f = frame(k, t)
        pos, fields = f.positions, f.fields
        path = series.add(f)
        assert path == tmp_path / "vtk" / f"run_{k:06d}.vtp"
        poly, points, arrays, time_s = read_vtp(path)
        assert poly.GetNumberOfPoints() == 40 and poly.GetNumberOfVerts() == 40
        np.testing.assert_array_equal(points, pos)
        assert time_s == t
        assert set(arrays) == {"velocity", "velocity_magnitude", "id", "stress_pa"}
        for name, values in fields.items():
            np.testing.assert_array_equal(arrays[name], values)
            assert arrays[name].dtype == values.dtype
        np.testing.assert_allclose(arrays["velocity_magnitude"],
                                   np.linalg.norm(fields["velocity"], axis=1), rtol=1e-6)


def test_magnitudes_only_when_asked(tmp_path):
    series = VtkSeries(tmp_path, "plain")
    f = frame(1, 0.5)
    _, _, arrays, _ = read_vtp(series.add(f))
    assert set(arrays) == set(f.fields)


def test_the_pvd_lists_the_files_by_time(tmp_path):
    series = VtkSeries(tmp_path, "r&d")  # a stem that XML must escape
    times = {3: 0.30000000000000004, 1: 0.1, 2: 0.2}  # added out of order; exact times
    for k, t in times.items():
        series.add(frame(k, t))
    pvd = series.close()
    assert pvd == tmp_path / "r&d.pvd"
    root = ET.parse(pvd).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    sets = root.find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in sets] == sorted(times.values())
    assert [d.get("file") for d in sets] == [f"r&d_{k:06d}.vtp" for k in (1, 2, 3)]
    assert all((tmp_path / d.get("file")).is_file() for d in sets)


def test_an_assembled_step_is_a_frame(tmp_path):
    """replay exports the render server's assembled steps as they are."""
    from minority.render_server.assemble import AssembledStep

    f = frame(12, 0.06)
    step = AssembledStep(step=12, time_s=0.06, positions=f.positions, fields=f.fields,
                         spacing_m=0.01, ranks_expected=1, ranks_received=1, nbytes=0,
                         receive_s=0.0, incomplete=False)
    series = VtkSeries(tmp_path, "run")
    _, points, arrays, time_s = read_vtp(series.add(step))
    np.testing.assert_array_equal(points, f.positions)
    assert set(arrays) == set(f.fields) and time_s == 0.06
    assert 'file="run_000012.vtp"' in series.close().read_text()
