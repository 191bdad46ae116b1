"""ParaView interchange: .pvcc cameras and color-map preset JSON (protocol/paraview.py)."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import numpy as np
import pytest

from minority.protocol.errors import SpecError
from minority.protocol.paraview import (
    MAX_PVCC_BYTES,
    read_colormap_preset,
    read_pvcc,
    rescale_preset,
    validate_colormap_preset,
    write_colormap_preset,
    write_pvcc,
    write_pvcc_for_views,
)
from minority.protocol.spec import Camera

PERSPECTIVE = Camera(position=(0.45, -1.2, 0.35), focal_point=(0.3, 0.1, 0.08),
                     view_up=(0.0, 0.2, 0.98), view_angle_deg=27.5)
PARALLEL = Camera(position=(0.2, 0.1, 2.0), focal_point=(0.2, 0.1, 0.0), view_up=(0.0, 1.0, 0.0),
                  parallel_projection=True, parallel_scale_m=0.125)

# As ParaView 5.x "Adjust Camera -> Save" writes it (vtkSMCameraConfigurationWriter).
PARAVIEW_PVCC = """<?xml version="1.0"?>
<PVCameraConfiguration description="ParaView camera configuration" version="1.0">
  <Proxy group="views" type="RenderView" id="4713" servers="21">
    <Property name="CameraPosition" id="4713.CameraPosition" number_of_elements="3">
      <Element index="0" value="1.28734529018402"/>
      <Element index="1" value="-0.861205339431763"/>
      <Element index="2" value="0.642617881298065"/>
    </Property>
    <Property name="CameraFocalPoint" id="4713.CameraFocalPoint" number_of_elements="3">
      <Element index="0" value="0.25"/>
      <Element index="1" value="0.125"/>
      <Element index="2" value="0.0500000007450581"/>
    </Property>
    <Property name="CameraViewUp" id="4713.CameraViewUp" number_of_elements="3">
      <Element index="0" value="-0.317302608489990"/>
      <Element index="1" value="0.210489168763161"/>
      <Element index="2" value="0.924664974212646"/>
    </Property>
    <Property name="CenterOfRotation" id="4713.CenterOfRotation" number_of_elements="3">
      <Element index="0" value="0.25"/>
      <Element index="1" value="0.125"/>
      <Element index="2" value="0.0500000007450581"/>
    </Property>
    <Property name="RotationFactor" id="4713.RotationFactor" number_of_elements="1">
      <Element index="0" value="1"/>
    </Property>
    <Property name="CameraViewAngle" id="4713.CameraViewAngle" number_of_elements="1">
      <Element index="0" value="30"/>
    </Property>
    <Property name="CameraParallelScale" id="4713.CameraParallelScale" number_of_elements="1">
      <Element index="0" value="0.384057283401489"/>
    </Property>
    <Property name="CameraParallelProjection" id="4713.CameraParallelProjection" number_of_elements="1">
      <Element index="0" value="0"/>
      <Domain name="bool" id="4713.CameraParallelProjection.bool"/>
    </Property>
  </Proxy>
</PVCameraConfiguration>
"""  # noqa: E501

# As ParaView's "Choose Preset -> Export" writes presets (a list; extra keys we ignore).
PARAVIEW_PRESETS = """[
\t{
\t\t"ColorSpace" : "Diverging",
\t\t"Creator" : "Moreland",
\t\t"Name" : "Cool to Warm",
\t\t"NanColor" : [ 1, 1, 0 ],
\t\t"RGBPoints" : [ 0, 0.23137254902, 0.298039215686, 0.752941176471,
\t\t\t0.5, 0.865, 0.865, 0.865, 1, 0.705882352941, 0.0156862745098, 0.149019607843 ]
\t},
\t{
\t\t"ColorSpace" : "Lab",
\t\t"Name" : "Blue to White",
\t\t"NanColor" : [ 1, 0, 0 ],
\t\t"Points" : [ -1, 0, 0.5, 0, 1, 1, 0.5, 0 ],
\t\t"RGBPoints" : [ -1, 0.0, 0.0, 0.4, 0, 0.2, 0.4, 0.8, 0, 0.3, 0.5, 0.9, 3, 1, 1, 1 ]
\t}
]
"""


# ------------------------------------------------------------------------------ pvcc

@pytest.mark.parametrize("camera", [PERSPECTIVE, PARALLEL], ids=["perspective", "parallel"])
def test_pvcc_round_trip(tmp_path, camera):
    path = tmp_path / "view.pvcc"
    write_pvcc(path, camera)
    assert read_pvcc(path) == [camera]


def test_written_pvcc_has_paraviews_layout(tmp_path):
    path = tmp_path / "view.pvcc"
    write_pvcc(path, PARALLEL)
    text = path.read_text()
    assert text.startswith('<?xml version="1.0"?>\n<PVCameraConfiguration ')
    root = ET.fromstring(text)
    assert root.tag == "PVCameraConfiguration"
    assert root.attrib == {"description": "ParaView camera configuration", "version": "1.0"}
    (proxy,) = root
    assert (proxy.tag, proxy.get("group"), proxy.get("type")) == ("Proxy", "views", "RenderView")
    names = [p.get("name") for p in proxy]
    assert names == ["CameraPosition", "CameraFocalPoint", "CameraViewUp", "CenterOfRotation",
                     "RotationFactor", "CameraViewAngle", "CameraParallelScale",
                     "CameraParallelProjection"]  # vtkSMCameraConfigurationWriter's order
    for prop in proxy:
        assert prop.get("id") == f"{proxy.get('id')}.{prop.get('name')}"
        elements = prop.findall("Element")
        assert prop.get("number_of_elements") == str(len(elements))
        assert [e.get("index") for e in elements] == [str(i) for i in range(len(elements))]
    center = [float(e.get("value")) for e in proxy[3]]
    assert center == list(PARALLEL.focal_point)
    assert proxy[7].find("Element").get("value") == "1"
    assert proxy[7].find("Domain").attrib["name"] == "bool"


def test_reads_paraview_written_pvcc(tmp_path):
    path = tmp_path / "paraview.pvcc"
    path.write_text(PARAVIEW_PVCC)
    (cam,) = read_pvcc(path)
    assert cam.position == (1.28734529018402, -0.861205339431763, 0.642617881298065)
    assert cam.focal_point == (0.25, 0.125, 0.0500000007450581)
    assert cam.view_up == (-0.317302608489990, 0.210489168763161, 0.924664974212646)
    assert cam.view_angle_deg == 30.0
    assert cam.parallel_scale_m == 0.384057283401489
    assert cam.parallel_projection is False


def _edit(old: str, new: str, count: int = 1) -> str:
    assert old in PARAVIEW_PVCC
    return PARAVIEW_PVCC.replace(old, new, count)


_POSITION = PARAVIEW_PVCC[PARAVIEW_PVCC.index('    <Property name="CameraPosition"'):
                          PARAVIEW_PVCC.index('    <Property name="CameraFocalPoint"')]


@pytest.mark.parametrize("text,message", [
    ("this is not xml", "not well-formed XML"),
    (PARAVIEW_PVCC[:-40], "not well-formed XML"),
    (_edit(_POSITION, ""), "missing property CameraPosition"),
    (_edit('<Element index="2" value="0.642617881298065"/>', ""),
     r"CameraPosition: expected 3 Element\(s\), found 2"),
    (_edit('id="4713.CameraViewAngle" number_of_elements="1"', 'number_of_elements="2"'),
     "CameraViewAngle: number_of_elements is '2', expected 1"),
    (_edit('value="0.125"/>', 'value="0.125 m"/>'),
     r"CameraFocalPoint\[1\]: value '0.125 m' is not a number"),
    (_edit('value="30"', 'value="nan"'), r"CameraViewAngle\[0\]: value 'nan' is not a number"),
    (_edit('value="30"', 'value="1e999"'), r"CameraViewAngle\[0\]: value '1e999' is not finite"),
    (_edit('<Element index="1" value="-0.861205339431763"/>',
           '<Element index="0" value="-0.861205339431763"/>'), "Element index 0 appears twice"),
    (_edit('<Element index="0" value="0"/>', '<Element index="0" value="2"/>'),
     "CameraParallelProjection: expected 0 or 1"),
    (_edit('version="1.0">', 'version="2.0">'), "version '2.0' is not supported"),
    (_edit("<PVCameraConfiguration ", "<PVCameraConfigurationX ").replace(
        "</PVCameraConfiguration>", "</PVCameraConfigurationX>"), "not a ParaView camera file"),
    (_edit("</Proxy>", "</Proxy>\n  <Proxy/>"), "expected one <Proxy>"),
    (_edit('<?xml version="1.0"?>', '<?xml version="1.0"?>\n<!DOCTYPE x [<!ENTITY a "aaaa">]>'),
     "document type declarations"),
    (_edit('value="30"', 'value="0"'), r"camera\.view_angle_deg: expected float >= 0\.1, got 0\.0"),
    (_edit('value="-0.317302608489990"', 'value="0"').replace(
        'value="0.210489168763161"', 'value="0"').replace('value="0.924664974212646"', 'value="0"'),
     r"camera\.view_up: parallel to the view direction \(or zero\)"),
])
def test_bad_pvcc_names_file_and_problem(tmp_path, text, message):
    path = tmp_path / "bad.pvcc"
    path.write_text(text)
    with pytest.raises(SpecError, match=message) as err:
        read_pvcc(path)
    assert str(err.value).startswith(str(path))


def test_pvcc_too_large_or_missing(tmp_path):
    path = tmp_path / "big.pvcc"
    path.write_text(PARAVIEW_PVCC + "<!--" + "x" * MAX_PVCC_BYTES + "-->")
    with pytest.raises(SpecError, match="larger than"):
        read_pvcc(path)
    with pytest.raises(SpecError, match="cannot read"):
        read_pvcc(tmp_path / "absent.pvcc")


def test_write_pvcc_rejects_cameras_that_would_not_read_back(tmp_path):
    bad = Camera(position=(0.0, 0.0, 1.0), focal_point=(0.0, 0.0, 1.0))
    with pytest.raises(SpecError, match="coincide"):
        write_pvcc(tmp_path / "bad.pvcc", bad)
    assert not (tmp_path / "bad.pvcc").exists()


def test_pvcc_for_each_view(tmp_path):
    spec = SimpleNamespace(views=(SimpleNamespace(name="overview", camera=PERSPECTIVE),
                                  SimpleNamespace(name="front.ortho", camera=PARALLEL)))
    paths = write_pvcc_for_views(spec, tmp_path / "cams")
    assert [p.name for p in paths] == ["overview.pvcc", "front.ortho.pvcc"]
    assert [read_pvcc(p)[0] for p in paths] == [PERSPECTIVE, PARALLEL]
    evil = SimpleNamespace(views=(SimpleNamespace(name="../escape", camera=PERSPECTIVE),))
    with pytest.raises(SpecError, match=r"views\[0\]\.name"):
        write_pvcc_for_views(evil, tmp_path / "cams")


# ------------------------------------------------------------------------------ presets

@pytest.fixture
def presets_file(tmp_path):
    path = tmp_path / "presets.json"
    path.write_text(PARAVIEW_PRESETS)
    return path


def test_read_preset_by_name(presets_file):
    p = read_colormap_preset(presets_file, "Blue to White")
    assert p == {"Name": "Blue to White", "ColorSpace": "Lab",
                 "RGBPoints": [-1.0, 0.0, 0.0, 0.4, 0.0, 0.2, 0.4, 0.8, 0.0, 0.3, 0.5, 0.9,
                               3.0, 1.0, 1.0, 1.0],
                 "NanColor": [1.0, 0.0, 0.0]}
    assert read_colormap_preset(presets_file, "Cool to Warm")["ColorSpace"] == "Diverging"
    with pytest.raises(SpecError, match="holds 2 presets, pass a name"):
        read_colormap_preset(presets_file)
    with pytest.raises(SpecError, match="no preset named 'Jet'.*Cool to Warm"):
        read_colormap_preset(presets_file, "Jet")


def test_preset_round_trip_and_single_object(tmp_path, presets_file):
    preset = read_colormap_preset(presets_file, "Cool to Warm")
    out = tmp_path / "out.json"
    write_colormap_preset(out, preset)
    assert isinstance(json.loads(out.read_text()), list)  # ParaView's Import wants a list
    assert read_colormap_preset(out) == preset
    single = tmp_path / "single.json"
    single.write_text(json.dumps(preset))
    assert read_colormap_preset(single) == preset


def test_rescale(presets_file):
    preset = read_colormap_preset(presets_file, "Blue to White")
    scaled = rescale_preset(preset, 0.0, 0.38)  # m, e.g. displacement magnitude
    xs = scaled["RGBPoints"][0::4]
    np.testing.assert_allclose(xs, [0.0, 0.095, 0.095, 0.38])
    assert xs[0] == 0.0 and xs[-1] == 0.38
    assert scaled["RGBPoints"][1::4] == preset["RGBPoints"][1::4]
    assert preset["RGBPoints"][0] == -1.0  # input untouched
    back = rescale_preset(scaled, -1.0, 3.0)
    np.testing.assert_allclose(back["RGBPoints"], preset["RGBPoints"], atol=1e-15)
    with pytest.raises(SpecError, match="lower bound 1.0 must be below upper 1.0"):
        rescale_preset(preset, 1.0, 1.0)


GOOD = {"Name": "m", "ColorSpace": "RGB", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1]}


@pytest.mark.parametrize("change,message", [
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, 1]}, r"RGBPoints: expected array of length >= 8, got \[0, 0"),
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1, 2]}, r"RGBPoints: expected x, r, g, b quadruples .* got 9"),
    ({"RGBPoints": [0, 0, 0, 0]}, r"RGBPoints: expected array of length >= 8, got \[0, 0, 0, 0\]"),
    ({"RGBPoints": "0 0 0 0"}, r"RGBPoints: expected array, got str"),
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, "1", 1]}, r"RGBPoints\[6\]: expected float, got str"),
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, True, 1]}, r"RGBPoints\[6\]: expected float, got bool"),
    ({"RGBPoints": [1, 0, 0, 0, 0, 1, 1, 1]}, r"RGBPoints\[4\]: x 0.0 is below the previous"),
    ({"RGBPoints": [1, 0, 0, 0, 1, 1, 1, 1]}, r"RGBPoints: x range \[1.0, 1.0\] is empty"),
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, 1.5, 1]}, r"RGBPoints\[6\]: color component 1.5 is outside"),
    ({"RGBPoints": [0, -0.1, 0, 0, 1, 1, 1, 1]}, r"RGBPoints\[1\]: color component -0.1"),
    ({"ColorSpace": "CMYK"}, r"ColorSpace: invalid enum value 'CMYK'"),
    ({"NanColor": [1, 1]}, r"NanColor: expected array of length 3, got 2"),
    ({"NanColor": [1, 2, 0]}, r"NanColor\[1\]: expected float <= 1.0, got 2"),
    ({"Name": 7}, r"Name: expected str, got int"),
    ({"Name": ""}, r"Name: expected str of length >= 1, got ''"),
    ({"RGBPoints": None}, r"RGBPoints: expected array, got null"),
])
def test_bad_presets_name_the_field(tmp_path, change, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps([{**GOOD, **change}]))
    with pytest.raises(SpecError, match=message) as err:
        read_colormap_preset(path)
    assert str(err.value).startswith(f"{path}[0]")  # file and preset


def test_bad_preset_files(tmp_path):
    path = tmp_path / "bad.json"
    for text, message in [("[", "not valid JSON"), ("[]", "holds no presets"),
                          ('[{"Name": "x"}]', r"\[0\] \('x'\): missing RGBPoints"),
                          ('{"RGBPoints": [0, 0, 0, 0, NaN, 1, 1, 1]}', "NaN is not a finite")]:
        path.write_text(text)
        with pytest.raises(SpecError, match=message):
            read_colormap_preset(path)
    with pytest.raises(SpecError, match="preset: expected a preset object"):
        validate_colormap_preset([1, 2])
    with pytest.raises(SpecError, match=r"preset\.ColorSpace"):
        write_colormap_preset(tmp_path / "x.json", {**GOOD, "ColorSpace": "cmyk"})


def test_written_preset_loads_in_render_server(tmp_path, presets_file):
    from minority.render_server.colormap import load_presets, preset

    out = tmp_path / "scaled.json"
    write_colormap_preset(out, rescale_preset(read_colormap_preset(presets_file, "Cool to Warm"),
                                              0.0, 0.38))
    cmap = load_presets(out)["Cool to Warm"]
    assert cmap.color_space == "Diverging"
    assert cmap.rgb_points[0] == 0.0 and cmap.rgb_points[-4] == 0.38
    values = np.linspace(0.0, 0.38, 20)
    np.testing.assert_allclose(cmap.map(values, 0.0, 0.38),
                               preset("Cool to Warm").map(values, 0.0, 0.38), atol=2e-3)
