"""Schemas stored in MCAP files: the wire layout of chunks, and JSON Schemas for the rest,
derived from the msgspec types the decoders check with."""

from __future__ import annotations

import re

import msgspec

from minority.protocol import wire
from minority.protocol.check import Base64, Count
from minority.protocol.messages import CompressedImage, EventMeta, StatsMeta, TimingMeta
from minority.protocol.spec import SpecDocument

WIRE_ENCODING = "minority-wire-v1"
WIRE_SCHEMA = (wire.__doc__ or "") + """
Chunk meta: run (str), step (int), time_s (simulated s), rank (int), ranks (int),
count (particles n), spacing_m (particle spacing, m), bounds_m ([[x,y,z] lo, [x,y,z] hi], m),
prev_time_s (optional: simulated time of the step before, s).
Chunk arrays: positions [n, 3] <f4 (m, required); other fields [n] or [n, k] with n rows,
e.g. displacement [n, 3] <f4 (m), velocity [n, 3] <f4 (m/s).
"""

class Rejected(msgspec.Struct, forbid_unknown_fields=True):
    """A payload that failed to decode, kept whole (protocol.log)."""

    key: str
    reason: str
    bytes: Count
    payload_b64: Base64


def json_schema(kind: type) -> dict:
    """The JSON Schema (Draft 2020-12) of a msgspec type, with its definitions inlined (one
    self-contained object per channel, as MCAP viewers read them)."""
    schema = msgspec.json.schema(kind)
    defs = schema.pop("$defs", {})

    def inline(node):
        if isinstance(node, dict):
            if "$ref" in node:
                return inline(defs[node["$ref"].rsplit("/", 1)[-1]])
            return {k: inline(v) for k, v in node.items()}
        if isinstance(node, list):
            return [inline(v) for v in node]
        return node

    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            **foxglove_compatible(inline(schema))}


def foxglove_compatible(schema: dict) -> dict:
    """The same constraints in the subset of JSON Schema that Foxglove's (and Lichtblick's)
    parseJsonSchema reads, so a viewer shows the channel instead of refusing it. That parser
    walks `properties` only and needs, for each, a `type` of boolean, string, number, integer,
    object (with `properties`) or array (whose `items` has one of those types); `oneOf` only
    as a numeric enum. What changes, validating the same values:

    - a fixed-length tuple (prefixItems, items false) of equal item schemas becomes `items`
      with minItems = maxItems;
    - an enum without a type gets its values' type;
    - an object without properties (a free-form map) gets `"properties": {}`;
    - a property with no type of its own (a union: a name or an inline colormap, a value or
      null) moves to `patternProperties` as `^name$`: JSON Schema validates it exactly as
      before (and `required`, `additionalProperties` still see it), the viewer's parser
      does not read it and shows its value as JSON.
    """
    if isinstance(schema, list):
        return [foxglove_compatible(v) for v in schema]
    if not isinstance(schema, dict):
        return schema
    node = {k: foxglove_compatible(v) for k, v in schema.items()}
    if "prefixItems" in node:
        items = node.pop("prefixItems")
        if node.get("items") is not False or any(item != items[0] for item in items):
            raise ValueError(f"a tuple of unequal items has no Foxglove form: {items}")
        node.update(items=items[0], minItems=len(items), maxItems=len(items))
    if "enum" in node and "type" not in node:
        kinds = {_JSON_TYPE[type(v)] for v in node["enum"]}
        if len(kinds) != 1:
            raise ValueError(f"an enum of mixed types has no Foxglove form: {node['enum']}")
        node["type"] = kinds.pop()
    if node.get("type") == "object" and "properties" not in node:
        node["properties"] = {}
    if node.get("type") == "object":
        untyped = {k: v for k, v in node["properties"].items() if "type" not in v}
        if untyped:
            node["properties"] = {k: v for k, v in node["properties"].items()
                                  if k not in untyped}
            for name in untyped:
                if not _PLAIN_NAME.fullmatch(name):
                    raise ValueError(f"property {name!r} cannot be matched by a plain pattern")
            node["patternProperties"] = {**node.get("patternProperties", {}),
                                         **{f"^{k}$": v for k, v in untyped.items()}}
    return node


_JSON_TYPE = {str: "string", bool: "boolean", int: "integer", float: "number"}
_PLAIN_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


JSON_SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": json_schema(CompressedImage),
    "minority.Spec": json_schema(SpecDocument),
    "minority.Timing": json_schema(TimingMeta),
    "minority.Event": json_schema(EventMeta),
    "minority.Stats": json_schema(StatsMeta),
    "minority.Rejected": json_schema(Rejected),
}


# --- Foxglove's message schemas (foxglove/schemas, JSON Schema form), for the exported view
# of a log (protocol.foxglove): open objects, no required keys, enums as oneOf of consts.
def _object(title: str, properties: dict) -> dict:
    return {"title": title, "type": "object", "properties": properties}


def _numbers(title: str, names: str) -> dict:
    return _object(title, {n: {"type": "number"} for n in names})


def _enum(title: str, names: list[str]) -> dict:
    return {"title": title, "oneOf": [{"title": n, "const": i} for i, n in enumerate(names)]}


def _array(items: dict) -> dict:
    return {"type": "array", "items": items}


_TIME = {"type": "object", "title": "time", "properties": {
    "sec": {"type": "integer", "minimum": 0},
    "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}
_DURATION = {"type": "object", "title": "duration", "properties": {
    "sec": {"type": "integer"}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}
_VECTOR3 = _numbers("foxglove.Vector3", "xyz")
_POINT3 = _numbers("foxglove.Point3", "xyz")
_COLOR = _numbers("foxglove.Color", "rgba")
_POSE = _object("foxglove.Pose", {"position": _VECTOR3,
                                  "orientation": _numbers("foxglove.Quaternion", "xyzw")})
_BASE64 = {"type": "string", "contentEncoding": "base64"}
NUMERIC_TYPES = ["UNKNOWN", "UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "FLOAT32",
                 "FLOAT64"]
"""foxglove.NumericType: a PackedElementField's `type` is its index here."""

POINT_CLOUD_SCHEMA = {"$schema": "https://json-schema.org/draft/2020-12/schema", **_object(
    "foxglove.PointCloud", {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _POSE,
        "point_stride": {"type": "integer", "minimum": 0},
        "fields": _array(_object("foxglove.PackedElementField", {
            "name": {"type": "string"},
            "offset": {"type": "integer", "minimum": 0},
            "type": _enum("foxglove.NumericType", NUMERIC_TYPES)})),
        "data": _BASE64})}

_LINE_TYPES = ["LINE_STRIP", "LINE_LOOP", "LINE_LIST"]
"""foxglove.LineType: a LinePrimitive's `type` is its index here."""
_POINTS_AND_COLORS = {"points": _array(_POINT3), "color": _COLOR, "colors": _array(_COLOR),
                      "indices": _array({"type": "integer", "minimum": 0})}
_SCENE_ENTITY = _object("foxglove.SceneEntity", {
    "timestamp": _TIME,
    "frame_id": {"type": "string"},
    "id": {"type": "string"},
    "lifetime": _DURATION,
    "frame_locked": {"type": "boolean"},
    "metadata": _array(_object("foxglove.KeyValuePair", {"key": {"type": "string"},
                                                         "value": {"type": "string"}})),
    "arrows": _array(_object("foxglove.ArrowPrimitive", {
        "pose": _POSE, **{k: {"type": "number"} for k in (
            "shaft_length", "shaft_diameter", "head_length", "head_diameter")},
        "color": _COLOR})),
    "cubes": _array(_object("foxglove.CubePrimitive",
                            {"pose": _POSE, "size": _VECTOR3, "color": _COLOR})),
    "spheres": _array(_object("foxglove.SpherePrimitive",
                              {"pose": _POSE, "size": _VECTOR3, "color": _COLOR})),
    "cylinders": _array(_object("foxglove.CylinderPrimitive", {
        "pose": _POSE, "size": _VECTOR3, "bottom_scale": {"type": "number"},
        "top_scale": {"type": "number"}, "color": _COLOR})),
    "lines": _array(_object("foxglove.LinePrimitive", {
        "type": _enum("foxglove.LineType", _LINE_TYPES), "pose": _POSE,
        "thickness": {"type": "number"}, "scale_invariant": {"type": "boolean"},
        **_POINTS_AND_COLORS})),
    "triangles": _array(_object("foxglove.TriangleListPrimitive",
                                {"pose": _POSE, **_POINTS_AND_COLORS})),
    "texts": _array(_object("foxglove.TextPrimitive", {
        "pose": _POSE, "billboard": {"type": "boolean"}, "font_size": {"type": "number"},
        "scale_invariant": {"type": "boolean"}, "color": _COLOR, "text": {"type": "string"}})),
    "models": _array(_object("foxglove.ModelPrimitive", {
        "pose": _POSE, "scale": _VECTOR3, "color": _COLOR,
        "override_color": {"type": "boolean"}, "url": {"type": "string"},
        "media_type": {"type": "string"}, "data": _BASE64})),
})
SCENE_UPDATE_SCHEMA = {"$schema": "https://json-schema.org/draft/2020-12/schema", **_object(
    "foxglove.SceneUpdate", {
        "deletions": _array(_object("foxglove.SceneEntityDeletion", {
            "timestamp": _TIME, "type": _enum("foxglove.SceneEntityDeletionType",
                                              ["MATCHING_ID", "ALL"]),
            "id": {"type": "string"}})),
        "entities": _array(_SCENE_ENTITY)})}

FOXGLOVE_SCHEMAS: dict[str, dict] = {"foxglove.PointCloud": POINT_CLOUD_SCHEMA,
                                     "foxglove.SceneUpdate": SCENE_UPDATE_SCHEMA}
"""The Foxglove schemas `minority log export --foxglove` writes besides JSON_SCHEMAS."""
