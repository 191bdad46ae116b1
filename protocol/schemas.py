"""Schemas stored in MCAP files: the wire layout of chunks, and JSON Schemas for the rest,
derived from the msgspec types the decoders check with."""

from __future__ import annotations

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

    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **inline(schema)}


JSON_SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": json_schema(CompressedImage),
    "minority.Spec": json_schema(SpecDocument),
    "minority.Timing": json_schema(TimingMeta),
    "minority.Event": json_schema(EventMeta),
    "minority.Stats": json_schema(StatsMeta),
    "minority.Rejected": json_schema(Rejected),
}
