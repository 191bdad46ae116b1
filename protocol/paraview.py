"""ParaView interchange: camera files (.pvcc) and color-map presets (JSON), as pure data.

Cameras. ParaView's "Adjust Camera -> Save" writes a `.pvcc` with
vtkSMCameraConfigurationWriter: `<?xml version="1.0"?>`, a root
`<PVCameraConfiguration description="ParaView camera configuration" version="1.0">`,
one `<Proxy group="views" type="RenderView" id=.. servers=..>` and one
`<Property name=.. id="{proxy id}.{name}" number_of_elements=n>` with `<Element index=i
value=v/>` children for each of CameraPosition, CameraFocalPoint, CameraViewUp,
CenterOfRotation, RotationFactor, CameraViewAngle, CameraParallelScale and
CameraParallelProjection. Its reader (vtkSMProxyConfigurationReader) insists on the root
name and version "1.0" and loads the first Proxy whatever its type. The model is VTK's, the
same as `Camera`: lengths in m (the data's units), view angle in degrees (vertical).

Color maps. A ParaView preset is a JSON object with "Name", "ColorSpace" (RGB, HSV, Lab,
Diverging, Lab/CIEDE2000, Step), "RGBPoints" (x0, r0, g0, b0, x1, ...) and optionally
"NanColor"; ParaView's "Import" wants a JSON list of such objects. Presets are handled here
as plain dicts, checked by protocol.view.InlineColormap: the rules of a spec's inline
colormap and of the renderer's presets.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from xml.parsers import expat

from minority.protocol import check
from minority.protocol.errors import SpecError
from minority.protocol.view import Camera, InlineColormap

PVCC_ROOT = "PVCameraConfiguration"
PVCC_DESCRIPTION = "ParaView camera configuration"
PVCC_VERSION = "1.0"
PVCC_SUFFIX = ".pvcc"
PVCC_PROXY_ID = "256"  # any id; ParaView ignores it on load
MAX_PVCC_BYTES = 1 << 20  # ParaView's own files are ~2 kB
MAX_PRESET_BYTES = 16 << 20  # ParaView's full built-in preset export is a few MB

# ParaView property -> (Camera field, number of elements); all are required on read.
_PVCC_CAMERA = {
    "CameraPosition": ("position", 3),
    "CameraFocalPoint": ("focal_point", 3),
    "CameraViewUp": ("view_up", 3),
    "CameraViewAngle": ("view_angle_deg", 1),
    "CameraParallelScale": ("parallel_scale_m", 1),
    "CameraParallelProjection": ("parallel_projection", 1),
}
_NUMBER_RE = re.compile(r"\s*[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?\s*")
_INDEX_RE = re.compile(r"\s*[0-9]{1,9}\s*")



# ---------------------------------------------------------------------------- cameras

def read_pvcc(path: str | Path) -> list[Camera]:
    """The camera of a ParaView .pvcc file, as a one-element list. Raises SpecError naming the
    file and the property at fault; CenterOfRotation and RotationFactor are ignored."""
    root = _parse_xml(path)
    if root.tag != PVCC_ROOT:
        raise SpecError(f"{path}: root element is <{root.tag}>, not <{PVCC_ROOT}> "
                        f"(not a ParaView camera file)")
    version = root.get("version")
    if version != PVCC_VERSION:
        raise SpecError(f"{path}: {PVCC_ROOT} version {version!r} is not supported "
                        f"(ParaView writes and reads {PVCC_VERSION!r})")
    proxies = root.findall("Proxy")
    if len(proxies) != 1:
        raise SpecError(f"{path}: expected one <Proxy> (one camera), found {len(proxies)}")
    props: dict[str, ET.Element] = {}
    for prop in proxies[0].findall("Property"):
        name = prop.get("name")
        if name in props:
            raise SpecError(f"{path}: property {name} appears twice")
        props[name] = prop
    obj: dict = {}
    for name, (key, size) in _PVCC_CAMERA.items():
        if name not in props:
            raise SpecError(f"{path}: missing property {name}")
        values = _elements(props[name], size, f"{path}: {name}")
        if key == "parallel_projection":
            if values[0] not in (0.0, 1.0):
                raise SpecError(f"{path}: {name}: expected 0 or 1, got {values[0]!r}")
            obj[key] = values[0] == 1.0
        else:
            obj[key] = values if size > 1 else values[0]
    return [Camera.from_dict(obj, f"{path}: camera")]


def write_pvcc(path: str | Path, camera: Camera) -> None:
    """Write `camera` as ParaView writes a .pvcc (CenterOfRotation = focal point,
    RotationFactor 1). Raises SpecError for a camera that would not read back."""
    cam = Camera.from_dict(_camera_dict(camera), "camera")  # the checks read_pvcc applies
    values = {
        "CameraPosition": cam.position,
        "CameraFocalPoint": cam.focal_point,
        "CameraViewUp": cam.view_up,
        "CenterOfRotation": cam.focal_point,
        "RotationFactor": (1,),
        "CameraViewAngle": (cam.view_angle_deg,),
        "CameraParallelScale": (cam.parallel_scale_m,),
        "CameraParallelProjection": (int(cam.parallel_projection),),
    }
    root = ET.Element(PVCC_ROOT, {"description": PVCC_DESCRIPTION, "version": PVCC_VERSION})
    proxy = ET.SubElement(root, "Proxy", {"group": "views", "type": "RenderView",
                                          "id": PVCC_PROXY_ID, "servers": "21"})
    for name, vals in values.items():
        prop = ET.SubElement(proxy, "Property", {"name": name, "id": f"{PVCC_PROXY_ID}.{name}",
                                                 "number_of_elements": str(len(vals))})
        for i, v in enumerate(vals):
            ET.SubElement(prop, "Element", {"index": str(i), "value": repr(v)})
        if name == "CameraParallelProjection":
            ET.SubElement(prop, "Domain", {"name": "bool", "id": f"{PVCC_PROXY_ID}.{name}.bool"})
    ET.indent(root, "  ")
    body = ET.tostring(root, encoding="unicode").replace(" />", "/>")  # ParaView's empty tags
    Path(path).write_text(f'<?xml version="1.0"?>\n{body}\n', encoding="utf-8")


def write_pvcc_for_views(spec, out_dir: str | Path) -> list[Path]:
    """One `{view.name}.pvcc` per view of `spec` in `out_dir` (created); the paths in view
    order. Uses only `spec.views[i].name` and `.camera`."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, view in enumerate(spec.views):
        name = check.name(view.name, f"views[{i}].name", SpecError)  # no path separators
        path = out / f"{name}{PVCC_SUFFIX}"
        write_pvcc(path, view.camera)
        paths.append(path)
    return paths


def _camera_dict(camera: Camera) -> dict:
    return {"position": list(camera.position), "focal_point": list(camera.focal_point),
            "view_up": list(camera.view_up), "view_angle_deg": camera.view_angle_deg,
            "parallel_projection": camera.parallel_projection,
            "parallel_scale_m": camera.parallel_scale_m}


def _read_limited(path: str | Path, max_bytes: int, what: str) -> bytes:
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise SpecError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise SpecError(f"{path}: larger than {max_bytes} bytes, not a {what}")
    return data


def _reject_doctype(*_args) -> None:
    raise SpecError("document type declarations (DTD, entities) are not allowed")


def _parse_xml(path: str | Path) -> ET.Element:
    """Parse a small XML file; no DTD or entity declarations (ParaView writes none)."""
    data = _read_limited(path, MAX_PVCC_BYTES, "ParaView camera file")
    guard = expat.ParserCreate()
    guard.StartDoctypeDeclHandler = _reject_doctype
    guard.EntityDeclHandler = _reject_doctype
    try:
        guard.Parse(data, True)
        return ET.fromstring(data)
    except SpecError as exc:
        raise SpecError(f"{path}: {exc}") from None
    except (expat.ExpatError, ET.ParseError) as exc:
        raise SpecError(f"{path}: not well-formed XML ({exc})") from None


def _elements(prop: ET.Element, size: int, where: str) -> list[float]:
    """The `size` numeric Element values of a Property, by index."""
    declared = prop.get("number_of_elements")
    if declared is not None and declared.strip() != str(size):
        raise SpecError(f"{where}: number_of_elements is {declared!r}, expected {size}")
    elements = prop.findall("Element")
    if len(elements) != size:
        raise SpecError(f"{where}: expected {size} Element(s), found {len(elements)}")
    values: list[float | None] = [None] * size
    for e in elements:
        index, value = e.get("index"), e.get("value")
        if index is None or not _INDEX_RE.fullmatch(index) or int(index) >= size:
            raise SpecError(f"{where}: Element index {index!r} is not one of 0..{size - 1}")
        i = int(index)
        if values[i] is not None:
            raise SpecError(f"{where}: Element index {i} appears twice")
        if value is None or not _NUMBER_RE.fullmatch(value):
            raise SpecError(f"{where}[{i}]: value {value!r:.40} is not a number")
        values[i] = float(value)
        if not math.isfinite(values[i]):
            raise SpecError(f"{where}[{i}]: value {value!r:.40} is not finite")
    return values


# ---------------------------------------------------------------------------- color maps

def validate_colormap_preset(obj, where: str = "preset") -> dict:
    """A checked, normalized copy of one ParaView preset object (protocol.view.InlineColormap's
    rules): Name, RGBPoints (floats), ColorSpace and NanColor; other keys (Creator, Points,
    ...) dropped. Errors start with `where` and name the field."""
    return InlineColormap.from_preset(obj, where).to_dict()


def read_colormap_preset(path: str | Path, name: str | None = None) -> dict:
    """One preset of a ParaView preset JSON file (a list of presets or one object), checked by
    validate_colormap_preset. `name` picks by "Name" (first match, as ParaView does); it is
    required when the file holds several presets."""
    data = _read_limited(path, MAX_PRESET_BYTES, "ParaView preset file")
    try:
        obj = json.loads(data, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        raise SpecError(f"{path}: not valid JSON ({exc})") from None
    items = obj if isinstance(obj, list) else [obj]
    if not items:
        raise SpecError(f"{path}: holds no presets")
    names = [o.get("Name") if isinstance(o, dict) else None for o in items]
    shown = names if len(names) <= 20 else [*names[:20], f"... {len(names) - 20} more"]
    if name is not None:
        if name not in names:
            raise SpecError(f"{path}: no preset named {name!r}; presets: {shown}")
        i = names.index(name)
    elif len(items) == 1:
        i = 0
    else:
        raise SpecError(f"{path}: holds {len(items)} presets, pass a name; presets: {shown}")
    where = f"{path}[{i}]" if isinstance(obj, list) else str(path)
    if names[i] is not None:
        where += f" ({names[i]!r:.60})"
    return validate_colormap_preset(items[i], where)


def rescale_preset(preset: dict, lo: float, hi: float) -> dict:
    """A copy of `preset` with the x of its RGBPoints mapped linearly onto [lo, hi]
    (units of the colored field); colors and order unchanged."""
    out = validate_colormap_preset(preset, "preset")
    lo = check.number(lo, "lo", error=SpecError)
    hi = check.number(hi, "hi", error=SpecError)
    if not lo < hi:
        raise SpecError(f"range: lower bound {lo} must be below upper {hi}")
    pts = out["RGBPoints"]
    x0, x1 = pts[0], pts[-4]
    scale = (hi - lo) / (x1 - x0)
    for i in range(0, len(pts), 4):
        x = pts[i]
        # ends exact; clamping keeps rounding from leaving [lo, hi] (and keeps order)
        pts[i] = lo if x == x0 else hi if x == x1 else min(max(lo + (x - x0) * scale, lo), hi)
    return out


def write_colormap_preset(path: str | Path, preset: dict) -> None:
    """Write `preset` (checked) as a ParaView-importable JSON list holding that one preset."""
    out = validate_colormap_preset(preset, "preset")
    Path(path).write_text(json.dumps([out], indent=2, allow_nan=False) + "\n", encoding="utf-8")


def _reject_constant(token: str):
    raise ValueError(f"{token} is not a finite number")
