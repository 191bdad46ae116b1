"""A Foxglove view of a log: `minority log export --foxglove LOG -o OUT.mcap`.

Foxglove (and Lichtblick) show the log's frames, timing, stats, events and spec as they are
(JSON with the schemas of protocol.schemas), but not its chunks: `minority-wire-v1` is ours.
The export writes one run's messages to a new MCAP file under run-independent topics, so one
layout (deploy/foxglove/minority.json) fits every run:

- `/particles`: foxglove.PointCloud, one per step: every particle the render server draws at
  that step (the fresh rows of every rank's chunk plus the context rows it keeps cached), in
  the `world` frame (m), with x, y, z, every field of the chunks as a float32 channel (a
  vector field as its magnitude, as the renderer colours it) and, when every row has one, the
  particle id (float64, exact below 2^53);
- `/scene`: foxglove.SceneUpdate, one per spec: a cube per region of interest and a frustum
  (lines from the camera to its focal plane) per view's camera, each with its name;
- `/frame/{view}`, `/timing`, `/stats`, `/events`, `/spec`: the log's records, data unchanged.

The log stays the source of truth for replay: the export is a viewer's copy, written whole or
not at all (a temporary file renamed at the end).
"""

from __future__ import annotations

import base64
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

from minority.protocol import keys
from minority.protocol.errors import ProtocolError
from minority.protocol.logread import MCAP_MAGIC, read_log
from minority.protocol.messages import POSITIONS, Chunk
from minority.protocol.projection import camera_basis, half_extents
from minority.protocol.schemas import FOXGLOVE_SCHEMAS, JSON_SCHEMAS, NUMERIC_TYPES
from minority.protocol.spec import ID_FIELD as ID_FIELD_NAME
from minority.protocol.spec import Spec

PARTICLES_TOPIC = "/particles"
SCENE_TOPIC = "/scene"
FRAME_ID = "world"
_COPIED = {keys.Topic.TIMING: "/timing", keys.Topic.STATS: "/stats",
           keys.Topic.EVENT: "/events", keys.Topic.SPEC: "/spec"}
_FLOAT32, _FLOAT64 = NUMERIC_TYPES.index("FLOAT32"), NUMERIC_TYPES.index("FLOAT64")
_LINE_LIST = 2  # foxglove.LineType
_DELETE_ALL = 1  # foxglove.SceneEntityDeletionType
MAX_PENDING_STEPS = 8  # steps waiting for a rank's chunk before the oldest is written partial
_REGION_RGBA = (1.0, 0.55, 0.1, 0.25)
_CAMERA_RGBA = (0.2, 0.5, 1.0, 1.0)


def frame_topic(view: str) -> str:
    return f"/frame/{view}"


@dataclass
class ExportResult:
    run: str
    steps: int = 0  # point clouds written
    points: int = 0  # particles in them, summed over steps
    partial_steps: int = 0  # steps written without every rank's chunk (the log lacks some)
    scenes: int = 0  # scene updates written (one per spec)
    copied: dict[str, int] = field(default_factory=dict)  # records copied, per topic
    skipped: int = 0  # records not exported: rejected payloads


# --- particles ------------------------------------------------------------------------------
class _StepAssembler:
    """The particles the render server draws at each step: fresh rows of every rank's chunk
    and, for ranks that track context (insitu.context), the rows it keeps by particle id."""

    def __init__(self):
        self._pending: dict[int, list[tuple[Chunk, int]]] = {}  # step -> (chunk, log_ns)
        self._cache: dict[int, dict[str, np.ndarray]] = {}  # rank -> context rows by column

    def add(self, chunk: Chunk, log_ns: int
            ) -> list[tuple[int, list[tuple[Chunk, int]], bool]]:
        """Take a chunk; returns the steps to write now, each with whether it is partial:
        a step once every rank's chunk is in, and the oldest waiting steps, partial, while
        more than MAX_PENDING_STEPS wait (a rank that stopped sending: memory stays
        bounded)."""
        chunks = self._pending.setdefault(chunk.step, [])
        chunks.append((chunk, log_ns))
        ready = []
        while len(self._pending) > MAX_PENDING_STEPS:
            oldest = min(self._pending)
            ready.append((oldest, self._pending.pop(oldest), True))
        if chunk.step in self._pending and len({c.rank for c, _ in chunks}) >= chunk.ranks:
            ready.append((chunk.step, self._pending.pop(chunk.step), False))
        return ready

    def rest(self) -> list[tuple[int, list[tuple[Chunk, int]]]]:
        """The steps still waiting for a chunk, in step order (the log lacks some)."""
        steps = sorted(self._pending.items())
        self._pending.clear()
        return steps

    def columns(self, chunks: list[Chunk]) -> dict[str, np.ndarray]:
        """The step's columns: positions [n, 3] float32 (m), one [n] column per field and
        `id` [n] int64 when every row has one; the caches are updated with the step."""
        parts = []
        for c in sorted(chunks, key=lambda c: c.rank):
            rows = _rows(c)
            if c.context_ids is None:
                parts.append(rows)
                continue
            fresh = {k: v[:c.fresh] for k, v in rows.items()}
            context = {k: v[c.fresh:] for k, v in rows.items()}
            context.setdefault(ID_FIELD_NAME, np.asarray(c.context_ids, np.int64))
            cached = {} if c.context_reset else self._cache.get(c.rank, {})
            if cached:
                gone = np.concatenate([context[ID_FIELD_NAME], np.asarray(
                    c.evict_ids if c.evict_ids is not None else [], np.int64)])
                keep = ~np.isin(cached[ID_FIELD_NAME], gone)
                cached = _concat([{k: v[keep] for k, v in cached.items()}, context])
            else:
                cached = context
            self._cache[c.rank] = cached
            parts.append(fresh)
        return _concat(parts + [self._cache[c.rank] for c in sorted(chunks, key=lambda c: c.rank)
                                if c.context_ids is not None])


def _rows(chunk: Chunk) -> dict[str, np.ndarray]:
    """A chunk's rows as columns: positions [n, 3], `id` [n] int64 if sent, every other field
    as [n] float32 (a field [n, k] as its magnitude)."""
    out = {POSITIONS: np.asarray(chunk.positions, np.float32)}
    for name, values in chunk.fields.items():
        if name == POSITIONS:
            continue
        if name == ID_FIELD_NAME:
            out[name] = np.asarray(values, np.int64)
        elif values.ndim == 2:
            out[name] = np.linalg.norm(np.asarray(values, np.float64), axis=1).astype(np.float32)
        else:
            out[name] = np.asarray(values, np.float32)
    return out


def _concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Rows of several column sets; a column some part lacks is left out."""
    parts = [p for p in parts if p]
    if not parts:
        return {POSITIONS: np.zeros((0, 3), np.float32)}
    names = [k for k in parts[0] if all(k in p for p in parts)]
    return {k: np.concatenate([p[k] for p in parts]) for k in names}


def point_cloud(columns: dict[str, np.ndarray], sent_ns: int) -> dict:
    """A foxglove.PointCloud (JSON form) of a step's columns (see _StepAssembler.columns)."""
    names = [k for k in columns if k not in (POSITIONS, ID_FIELD_NAME)]
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), *((k, "<f4") for k in names)]
    if ID_FIELD_NAME in columns:
        dtype.append((ID_FIELD_NAME, "<f8"))
    packed = np.empty(len(columns[POSITIONS]), np.dtype(dtype))
    for axis, name in enumerate("xyz"):
        packed[name] = columns[POSITIONS][:, axis]
    for name in names + ([ID_FIELD_NAME] if ID_FIELD_NAME in columns else []):
        packed[name] = columns[name]
    return {"timestamp": _time(sent_ns), "frame_id": FRAME_ID, "pose": _pose((0.0, 0.0, 0.0)),
            "point_stride": packed.dtype.itemsize,
            "fields": [{"name": name, "offset": packed.dtype.fields[name][1],
                        "type": _FLOAT64 if name == ID_FIELD_NAME else _FLOAT32}
                       for name in packed.dtype.names],
            "data": base64.b64encode(packed.tobytes()).decode("ascii")}


# --- regions and cameras ---------------------------------------------------------------------
def scene_update(spec: Spec, sent_ns: int) -> dict:
    """A foxglove.SceneUpdate (JSON form) of a spec: it replaces every entity of the scene
    with one cube per region (`region/{name}`) and one frustum per view (`camera/{view}`)."""
    stamp = _time(sent_ns)
    entities = []
    for region in spec.regions:
        lo, hi = np.asarray(region.lo_m, float), np.asarray(region.hi_m, float)
        entities.append(_entity(stamp, f"region/{region.name}", cubes=[{
            "pose": _pose((lo + hi) / 2), "size": _xyz(hi - lo), "color": _rgba(_REGION_RGBA)}],
            texts=[_label(hi, region.name)]))
    for view in spec.views:
        entities.append(_entity(stamp, f"camera/{view.name}", lines=[{
            "type": _LINE_LIST, "pose": _pose((0.0, 0.0, 0.0)), "thickness": 2.0,
            "scale_invariant": True, "points": [_xyz(p) for p in frustum_segments(view)],
            "color": _rgba(_CAMERA_RGBA), "colors": [], "indices": []}],
            texts=[_label(view.camera.position, view.name)]))
    return {"deletions": [{"timestamp": stamp, "type": _DELETE_ALL, "id": ""}],
            "entities": entities}


def frustum_segments(view) -> np.ndarray:
    """The edges of a view's frustum from the camera to its focal plane, as line-list point
    pairs [2 * e, 3] (m): apex to the four corners and the focal rectangle (perspective), or
    the near rectangle, the four side edges and the focal rectangle (parallel projection)."""
    basis = camera_basis(view.camera)
    half_w, half_h = half_extents(view.camera, view.width / view.height)
    corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
    d = basis.distance
    scale = 1.0 if view.camera.parallel_projection else d  # tangents span d times as many m
    far = [basis.position + d * basis.forward + scale * (sx * half_w * basis.right
                                                         + sy * half_h * basis.up)
           for sx, sy in corners]
    if view.camera.parallel_projection:
        near = [f - d * basis.forward for f in far]
    else:
        near = [basis.position] * 4
    segments = []
    for i in range(4):
        segments += [near[i], far[i], far[i], far[(i + 1) % 4]]
        if view.camera.parallel_projection:
            segments += [near[i], near[(i + 1) % 4]]
    return np.asarray(segments, dtype=float)


def _entity(stamp: dict, entity_id: str, **primitives) -> dict:
    entity = {"timestamp": stamp, "frame_id": FRAME_ID, "id": entity_id,
              "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": []}
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts",
                 "models"):
        entity[kind] = primitives.get(kind, [])
    return entity


def _label(at, text: str) -> dict:
    return {"pose": _pose(at), "billboard": True, "font_size": 14.0, "scale_invariant": True,
            "color": _rgba((0.1, 0.1, 0.1, 1.0)), "text": text}


def _time(ns: int) -> dict:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _xyz(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _pose(position) -> dict:
    return {"position": _xyz(position), "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _rgba(c) -> dict:
    return dict(zip("rgba", map(float, c), strict=True))


# --- the export ---------------------------------------------------------------------------------
class _Out:
    """The output MCAP file: channels registered on first use, JSON messages."""

    def __init__(self, f, run: str, source: Path):
        self._writer = Writer(f, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="minority")
        self._writer.add_metadata("minority", {"run": run, "source": str(source)})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def write(self, topic: str, schema: str, data: bytes, log_ns: int, publish_ns: int) -> None:
        if topic not in self._channels:
            if schema not in self._schemas:
                text = json.dumps({**JSON_SCHEMAS, **FOXGLOVE_SCHEMAS}[schema]).encode()
                self._schemas[schema] = self._writer.register_schema(schema, "jsonschema", text)
            self._channels[topic] = self._writer.register_channel(topic, "json",
                                                                  self._schemas[schema])
        self._writer.add_message(self._channels[topic], log_ns, data, publish_ns)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def finish(self) -> None:
        self._writer.finish()


def _json(obj) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


def export_foxglove(log: str | Path, out: str | Path, run: str | None = None) -> ExportResult:
    """Write the Foxglove view of one run of `log` to `out` (see the module's doc). `run` may
    be left out when the log holds one run; ProtocolError names the runs otherwise, or an
    undecodable record. The output appears whole or not at all."""
    log, out = Path(log), Path(out)
    with open(log, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise ProtocolError(f"{log} is not an MCAP file (no MCAP magic at its start)")
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            result = _export(log, f, run)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return result


def _export(log: Path, f, run: str | None) -> ExportResult:
    result, sink, steps = None, None, _StepAssembler()

    def emit(step_chunks, partial: bool) -> None:
        chunks = [c for c, _ in step_chunks]
        columns = steps.columns(chunks)
        sent_ns = max(c.sent_ns for c in chunks)
        sink.write(PARTICLES_TOPIC, "foxglove.PointCloud", _json(point_cloud(columns, sent_ns)),
                   max(ns for _, ns in step_chunks), sent_ns)
        result.steps += 1
        result.points += len(columns[POSITIONS])
        result.partial_steps += partial

    chosen, skipped = run, 0
    for record in read_log(log):
        topic = keys.parse_log_topic(record.topic)
        if topic is None:  # minority/_rejected: payloads that never decoded
            skipped += 1
            continue
        chosen = chosen or topic.run
        if topic.run != chosen:
            if run is None:
                raise ProtocolError(f"{log} holds runs {chosen!r} and {topic.run!r}: "
                                    "name the one to export")
            continue
        if result is None:
            result, sink = ExportResult(chosen), _Out(f, chosen, log)
        if topic.kind == keys.Topic.CHUNK:
            for _, step_chunks, partial in steps.add(record.decode(), record.log_ns):
                emit(step_chunks, partial)
            continue
        if topic.kind == keys.Topic.SPEC:
            sink.write(SCENE_TOPIC, "foxglove.SceneUpdate",
                       _json(scene_update(record.decode(), record.publish_ns)),
                       record.log_ns, record.publish_ns)
            result.scenes += 1
        name = frame_topic(topic.view) if topic.kind == keys.Topic.FRAME else _COPIED[topic.kind]
        sink.write(name, record.schema, record.data, record.log_ns, record.publish_ns)
    if result is None:
        raise ProtocolError(f"{log} holds no message of "
                            f"{'any run' if run is None else f'run {run!r}'}")
    for _, step_chunks in steps.rest():
        emit(step_chunks, True)
    sink.finish()
    result.skipped = skipped
    result.copied = {k: v for k, v in sink.counts.items()
                     if k not in (PARTICLES_TOPIC, SCENE_TOPIC)}
    return result
