"""Colormaps: ParaView preset semantics, rescaling, NaN, JSON round trip."""

import json

import numpy as np
import pytest

from minority.protocol import SpecError
from minority.render_server.colormap import builtin_presets, from_paraview, load_presets, preset, to_paraview


def test_cool_to_warm_matches_paraview_control_points():
    cmap = preset("Cool to Warm")
    rgb = cmap.map(np.array([0.0, 0.19, 0.38]), 0.0, 0.38)  # rescaled to 0-0.38 m
    np.testing.assert_allclose(rgb[0], [0.231373, 0.298039, 0.752941], atol=2e-3)
    np.testing.assert_allclose(rgb[1], [0.865003, 0.865003, 0.865003], atol=2e-3)
    np.testing.assert_allclose(rgb[2], [0.705882, 0.0156863, 0.14902], atol=2e-3)


def test_clamping_and_nan():
    cmap = preset("Grayscale")
    rgb = cmap.map(np.array([-5.0, 0.5, 9.0, np.nan]), 0.0, 1.0)
    np.testing.assert_allclose(rgb[:3, 0], [0.0, 0.5, 1.0], atol=1e-3)
    np.testing.assert_allclose(rgb[3], cmap.nan_color)


def test_viridis_ends():
    rgb = preset("Viridis (matplotlib)").map(np.array([0.0, 1.0]), 0.0, 1.0)
    np.testing.assert_allclose(rgb, [[0.267004, 0.004874, 0.329415], [0.993248, 0.906157, 0.143936]],
                               atol=1e-3)


def test_paraview_json_round_trip(tmp_path):
    data = [to_paraview(m, 0.0, 0.38) for m in builtin_presets().values()]
    (tmp_path / "presets.json").write_text(json.dumps(data))
    loaded = load_presets(tmp_path / "presets.json")
    assert set(loaded) == set(builtin_presets())
    values = np.linspace(0.0, 0.38, 50)
    for name, cmap in builtin_presets().items():
        np.testing.assert_allclose(loaded[name].map(values, 0.0, 0.38), cmap.map(values, 0.0, 0.38),
                                   atol=2e-3)


@pytest.mark.parametrize("obj,message", [
    ({"Name": "x"}, "preset: missing RGBPoints"),
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, 1]}, r"preset.RGBPoints: expected array of length >= 8"),
    ({"RGBPoints": [1, 0, 0, 0, 0, 1, 1, 1]}, "x values must increase"),
    ({"RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1], "ColorSpace": "CMYK"}, "ColorSpace"),
])
def test_bad_presets(obj, message):
    with pytest.raises(SpecError, match=message):
        from_paraview(obj)


def test_unknown_builtin_names_the_known_ones():
    with pytest.raises(SpecError, match="Cool to Warm"):
        preset("Jet (made up)")


def test_shipped_tables_are_what_vtk_and_matplotlib_give():
    """render_server/colormap_tables.npz is `python -m minority.render_server.colormap`'s
    output: the same control points, NaN colours, spaces and lookup tables, exactly."""
    from minority.render_server.colormap import BUILTIN, TABLES, tables_of

    fresh = tables_of({name: make() for name, make in BUILTIN.items()})
    with np.load(TABLES) as shipped:
        assert set(shipped.files) == set(fresh)
        for key, value in fresh.items():
            np.testing.assert_array_equal(shipped[key], value, err_msg=key)
    for name, make in BUILTIN.items():
        assert preset(name) == make()  # same fields (the lut is no field)


def test_a_built_in_preset_needs_neither_vtk_nor_matplotlib():
    import subprocess
    import sys

    code = ("import sys\nimport numpy as np\nfrom minority.render_server.colormap import preset\n"
            "for name in ('Cool to Warm', 'Turbo'):\n"
            "    preset(name).map(np.linspace(0, 1, 5), 0.0, 1.0)\n"
            "print(sorted(m for m in ('vtkmodules', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert preset("coolwarm").lut().shape == (1024, 3)  # any other matplotlib name: sampled
