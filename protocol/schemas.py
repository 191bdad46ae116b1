"""Schemas stored in MCAP files: the wire layout of chunks, JSON Schemas for the rest."""

from __future__ import annotations

from minority.protocol import wire

WIRE_ENCODING = "minority-wire-v1"
WIRE_SCHEMA = (wire.__doc__ or "") + """
Chunk meta: run (str), step (int), time_s (simulated s), rank (int), ranks (int),
count (particles n), spacing_m (particle spacing, m), bounds_m ([[x,y,z] lo, [x,y,z] hi], m),
prev_time_s (optional: simulated time of the step before, s).
Chunk arrays: positions [n, 3] <f4 (m, required); other fields [n] or [n, k] with n rows,
e.g. displacement [n, 3] <f4 (m), velocity [n, 3] <f4 (m/s).
"""

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_STR = {"type": "string"}
_VEC3 = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}


def _obj(props: dict, required: list[str] | None = None) -> dict:
    """A closed object: exactly `props` may appear; `required` lists those that must (None:
    all of them; [] none)."""
    return {"type": "object", "properties": props,
            "required": list(props) if required is None else required,
            "additionalProperties": False}


_OPEN_OBJECT = {"type": "object"}  # free-form (provenance, event detail)


_CAMERA = _obj({"position": _VEC3, "focal_point": _VEC3, "view_up": _VEC3,
                "view_angle_deg": _NUM, "parallel_projection": {"type": "boolean"},
                "parallel_scale_m": _NUM}, ["position", "focal_point"])
_WINDOW = _obj({"t_start_s": _NUM, "t_end_s": {"type": ["number", "null"]}, "every_steps": _INT,
                "every_s": _NUM, "regions": {"type": "array", "items": _STR}}, [])
_COLORMAP = _obj({"Name": _STR, "ColorSpace": _STR, "RGBPoints": {"type": "array", "items": _NUM},
                  "NanColor": _VEC3}, ["RGBPoints"])
_VIEW = _obj({"name": _STR, "camera": _CAMERA, "width": _INT, "height": _INT,
              "background": _VEC3, "field": _STR,
              "colormap": {"oneOf": [_STR, _COLORMAP]},
              "range": {"type": "array", "items": _NUM, "minItems": 2, "maxItems": 2},
              "decimate": _INT, "occlusion_cull": {"type": "boolean"},
              "schedule": {"type": "array", "items": _WINDOW, "minItems": 1},
              # version 1 shorthand of a one-window schedule
              **{k: v for k, v in _WINDOW["properties"].items()}},
             ["name", "camera"])
_REGION = _obj({"name": _STR, "lo_m": _VEC3, "hi_m": _VEC3})

JSON_SCHEMAS: dict[str, dict] = {
    # Field names and types of Foxglove's CompressedImage, so viewers show frames.
    "foxglove.CompressedImage": _obj({
        "timestamp": _obj({"sec": _INT, "nsec": _INT}),
        "frame_id": _STR,
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": _STR,
        "run": _STR, "view": _STR, "step": _INT, "time_s": _NUM, "width": _INT, "height": _INT,
    }, ["timestamp", "frame_id", "data", "format"]),
    "minority.Spec": _obj({"version": _INT, "run": _STR, "sphere_radius_m": _NUM,
                           "views": {"type": "array", "items": _VIEW},
                           "regions": {"type": "array", "items": _REGION},
                           "events": {"type": "array", "items": _obj(
                               {"name": _STR, "time_s": _NUM, "tolerance_s": _NUM})},
                           "budget": _obj({"frames": {"type": ["integer", "null"]},
                                           "bytes": {"type": ["integer", "null"]}}, []),
                           "provenance": _OPEN_OBJECT},
                          ["version", "run", "views"]),
    "minority.Timing": _obj({"run": _STR, "step": _INT, "view": _STR, "time_s": _NUM,
                             "receive_s": _NUM, "setup_s": _NUM, "render_s": _NUM,
                             "bytes": _INT, "particles": _INT, "ranks_expected": _INT,
                             "ranks_received": _INT, "incomplete": {"type": "boolean"}}),
    "minority.Event": _obj({"run": _STR, "event": {"enum": ["run_start", "rank_done",
                                                            "run_end", "error"]},
                            "rank": _INT, "message": _STR, "detail": _OPEN_OBJECT}),
    "minority.Stats": _obj({"run": _STR, "rank": _INT, "step": _INT, "time_s": _NUM,
                            "count": _INT, "speed_sq_sum_m2_s2": _NUM, "max_speed_m_s": _NUM,
                            "max_displacement_m": _NUM, "windows_open": {"type": "boolean"},
                            "hist_in_regions": {"type": "array", "items": _INT},
                            "hist_elsewhere": {"type": "array", "items": _INT}}),
    "minority.Rejected": _obj({"key": _STR, "reason": _STR, "bytes": _INT,
                               "payload_b64": {"type": "string", "contentEncoding": "base64"}}),
}
