"""Colormaps as ParaView presets (RGBPoints + color space), rescaled to a value range.

Interpolation is VTK's vtkColorTransferFunction (RGB, HSV, Lab, Diverging/Msh), the same
code ParaView uses, sampled into a lookup table once per preset. Built-in presets: ParaView's
default "Cool to Warm", matplotlib's perceptual maps under ParaView's names, and grayscale,
whose tables VTK and matplotlib made ahead of time (TABLES); any ParaView preset JSON file
(one preset or a list) can be loaded.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cache, lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from minority.protocol.errors import SpecError
from minority.protocol.view import InlineColormap, check_colormap_name

LUT_SIZE = 1024
_SPACES = {"RGB": "SetColorSpaceToRGB", "HSV": "SetColorSpaceToHSV", "Lab": "SetColorSpaceToLab",
           "Lab/CIEDE2000": "SetColorSpaceToLabCIEDE2000", "Diverging": "SetColorSpaceToDiverging",
           "Step": "SetColorSpaceToStep"}


@dataclass(frozen=True)
class Colormap:
    name: str
    color_space: str
    rgb_points: tuple[float, ...]  # x0, r0, g0, b0, x1, ... (x in any units, rescaled)
    nan_color: tuple[float, float, float] = (1.0, 1.0, 0.0)
    _lut: list = field(default_factory=list, compare=False, repr=False)

    def lut(self) -> np.ndarray:
        """[LUT_SIZE, 3] float RGB in [0, 1] over the preset's own x range (the built-in
        presets' come from TABLES, the others are sampled with VTK once)."""
        if not self._lut:
            self._lut.append(self.sample_vtk())
        return self._lut[0]

    def sample_vtk(self) -> np.ndarray:
        """[LUT_SIZE, 3] VTK's vtkColorTransferFunction of the control points, sampled."""
        from vtkmodules.vtkRenderingCore import vtkColorTransferFunction

        f = vtkColorTransferFunction()
        getattr(f, _SPACES[self.color_space])()
        pts = np.asarray(self.rgb_points, dtype=np.float64).reshape(-1, 4)
        for x, r, g, b in pts:
            f.AddRGBPoint(x, r, g, b)
        xs = np.linspace(pts[0, 0], pts[-1, 0], LUT_SIZE)
        return np.array([f.GetColor(x) for x in xs])

    def map(self, values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
        """RGB [n, 3] float in [0, 1] of values [n] rescaled from [vmin, vmax]; values outside
        are clamped to the end colors, NaN gets nan_color."""
        lut = self.lut()
        scale = (LUT_SIZE - 1) / (vmax - vmin) if vmax > vmin else 0.0
        idx = np.clip((np.nan_to_num(values, nan=vmin) - vmin) * scale + 0.5, 0, LUT_SIZE - 1)
        rgb = lut[idx.astype(np.int64)]
        rgb[np.isnan(values)] = self.nan_color
        return rgb


def from_paraview(obj: dict, where: str = "preset") -> Colormap:
    """A Colormap from one ParaView preset object (as in ParaView's exported JSON), checked
    by protocol.view.InlineColormap."""
    return _from_inline(InlineColormap.from_preset(obj, where))


def _from_inline(c: InlineColormap) -> Colormap:
    return Colormap(c.name, c.color_space, c.rgb_points, c.nan_color)


def to_paraview(cmap: Colormap, vmin: float | None = None, vmax: float | None = None) -> dict:
    """ParaView preset JSON of a colormap, x rescaled to [vmin, vmax] when given."""
    pts = np.asarray(cmap.rgb_points, dtype=np.float64).reshape(-1, 4).copy()
    if vmin is not None and vmax is not None:
        x0, x1 = pts[0, 0], pts[-1, 0]
        pts[:, 0] = vmin + (pts[:, 0] - x0) * (vmax - vmin) / (x1 - x0)
    return {"Name": cmap.name, "ColorSpace": cmap.color_space,
            "RGBPoints": pts.reshape(-1).tolist(), "NanColor": list(cmap.nan_color)}


def load_presets(path: str | Path) -> dict[str, Colormap]:
    """Presets of a ParaView JSON file (one preset object or a list of them)."""
    try:
        obj = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SpecError(f"{path}: cannot read a ParaView preset file ({exc})") from None
    items = obj if isinstance(obj, list) else [obj]
    maps = [from_paraview(o, f"{path}[{i}]") for i, o in enumerate(items)]
    return {m.name: m for m in maps}


def _matplotlib(name: str, paraview_name: str, samples: int = 256) -> Colormap:
    from matplotlib import colormaps

    cmap = colormaps[name]
    xs = np.linspace(0.0, 1.0, samples)
    pts = np.c_[xs, cmap(xs)[:, :3]].reshape(-1)
    return Colormap(paraview_name, "RGB", tuple(pts.tolist()), (1.0, 0.0, 0.0))


# The built-in presets: how each is made (VTK's or matplotlib's definition)...
BUILTIN = {
    "Cool to Warm": lambda: Colormap(
        "Cool to Warm", "Diverging",
        (0.0, 0.231373, 0.298039, 0.752941, 0.5, 0.865003, 0.865003, 0.865003,
         1.0, 0.705882, 0.0156863, 0.14902), (1.0, 1.0, 0.0)),
    "Grayscale": lambda: Colormap("Grayscale", "RGB", (0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0),
                                  (1.0, 0.0, 0.0)),
    "Viridis (matplotlib)": lambda: _matplotlib("viridis", "Viridis (matplotlib)"),
    "Plasma (matplotlib)": lambda: _matplotlib("plasma", "Plasma (matplotlib)"),
    "Inferno (matplotlib)": lambda: _matplotlib("inferno", "Inferno (matplotlib)"),
    "Magma (matplotlib)": lambda: _matplotlib("magma", "Magma (matplotlib)"),
    "Turbo": lambda: _matplotlib("turbo", "Turbo"),
}
# ...and what that gives, shipped (`python -m minority.render_server.colormap` writes it;
# tests/test_render_colormap.py checks it against VTK and matplotlib): a process that renders
# a built-in preset imports neither (about 70 MB of a render rank's resident memory)
TABLES = Path(str(resources.files("minority.render_server").joinpath("colormap_tables.npz")))


@cache
def _tables() -> dict[str, np.ndarray]:
    with np.load(TABLES) as z:
        return {k: z[k] for k in z.files}


def builtin_preset(name: str) -> Colormap:
    """A built-in preset from TABLES: its control points, colours and lookup table."""
    t = _tables()
    meta = t[f"{name}/meta"]  # [4]: r, g, b of the NaN colour, then the colour space's index
    cmap = Colormap(name, list(_SPACES)[int(meta[3])], tuple(t[f"{name}/points"].tolist()),
                    tuple(meta[:3].tolist()))
    cmap._lut.append(t[f"{name}/lut"])
    return cmap


def tables_of(presets: dict[str, Colormap]) -> dict[str, np.ndarray]:
    """What TABLES holds for these presets (their luts sampled with VTK)."""
    out = {}
    for name, cmap in presets.items():
        out[f"{name}/points"] = np.asarray(cmap.rgb_points, dtype=np.float64)
        out[f"{name}/meta"] = np.array([*cmap.nan_color, list(_SPACES).index(cmap.color_space)],
                                       dtype=np.float64)
        out[f"{name}/lut"] = cmap.sample_vtk()
    return out


@cache
def builtin_presets() -> dict[str, Colormap]:
    return {name: builtin_preset(name) for name in BUILTIN}


@lru_cache(maxsize=64)
def preset(name: str) -> Colormap:
    """A built-in ParaView preset by its name, or a matplotlib colormap by its name (both
    checked by protocol.view.check_colormap_name)."""
    if name in BUILTIN:
        return builtin_presets()[name]
    return _matplotlib(check_colormap_name(name, "colormap"), name)


def view_colormap(colormap: str | InlineColormap) -> Colormap:
    """The Colormap of a view: a preset by name, or the view's inline ParaView preset (built
    once per distinct preset, so its lookup table is sampled once)."""
    return preset(colormap) if isinstance(colormap, str) else _inline(colormap)


@lru_cache(maxsize=256)
def _inline(colormap: InlineColormap) -> Colormap:
    return _from_inline(colormap.checked(f"colormap {colormap.name!r}"))


if __name__ == "__main__":  # writes TABLES from VTK and matplotlib
    np.savez_compressed(TABLES, **tables_of({n: make() for n, make in BUILTIN.items()}))
    print(f"wrote {TABLES}")
