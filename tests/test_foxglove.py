"""Foxglove shows the whole log: every stored schema is one Foxglove's JSON-schema parser
takes, every logged message carries its real publish time, and `minority log export
--foxglove` turns a run's chunks into foxglove.PointCloud and its spec into
foxglove.SceneUpdate (read back here with mcap's reader)."""

import base64
import json

import jsonschema
import numpy as np
import pytest
from conftest import make_chunk, make_png, make_spec
from mcap.reader import make_reader
from test_schemas import validate_log, varied_spec

from minority.cli import main
from minority.protocol import Frame, Spec, Stats, Timing, keys
from minority.protocol.foxglove import (
    PARTICLES_TOPIC,
    SCENE_TOPIC,
    export_foxglove,
    frustum_segments,
)
from minority.protocol.log import LogWriter, read_log
from minority.protocol.messages import decode_as
from minority.protocol.projection import camera_basis
from minority.protocol.schemas import FOXGLOVE_SCHEMAS, JSON_SCHEMAS, NUMERIC_TYPES

_ITEM_TYPES = ("boolean", "string", "number", "integer", "object")


def foxglove_refusal(schema: dict, path: tuple[str, ...] = ()) -> str | None:
    """What Foxglove's parseJsonSchema (foxglove/studio and Lichtblick,
    packages/mcap-support/src/parseJsonSchema.ts) throws for `schema`, in its words; None
    when it takes it. It reads an object's `properties` only: each needs a numeric-const
    `oneOf` or a `type` of boolean, string (no contentEncoding but base64), number, integer,
    object (recursively) or array, whose `items` has one of the first five types."""
    if schema.get("type") != "object":
        return f'Expected "type": "object" for schema, got {schema.get("type")!r}'
    if not isinstance(schema.get("properties"), dict):
        return f"object {'.'.join(path)} has no properties (Object.entries(undefined))"
    for name, prop in schema["properties"].items():
        where = ".".join((*path, name))
        if isinstance(prop.get("oneOf"), list):
            if not all(isinstance(alt.get("const"), int) for alt in prop["oneOf"]):
                return f"Unsupported type for {where}: oneOf alternatives must have number values"
            continue
        kind = prop.get("type")
        if kind == "string" and prop.get("contentEncoding") not in (None, "base64"):
            return f"Unsupported contentEncoding {prop['contentEncoding']!r} in {where}"
        if kind == "object" and (why := foxglove_refusal(prop, (*path, name))):
            return why
        if kind == "array":
            items = prop.get("items")
            item_kind = items.get("type") if isinstance(items, dict) else None
            if item_kind not in _ITEM_TYPES:
                return f"Unsupported type {item_kind!r} for array item {where}"
            if item_kind == "string" and items.get("contentEncoding") is not None:
                return f"Unsupported contentEncoding for array item {where}"
            if item_kind == "object" and (why := foxglove_refusal(items, (*path, name))):
                return why
        elif kind not in ("boolean", "string", "number", "integer", "object"):
            return f"Unsupported type {kind!r} for {where}"
    return None


def test_the_port_of_foxglove_refuses_what_foxglove_refused():
    """The spec's old camera position (a tuple: prefixItems, items false), the event's old
    kind (an enum without a type), provenance (an object without properties)."""
    tuple3 = {"type": "array", "prefixItems": [{"type": "number"}] * 3, "items": False}
    assert foxglove_refusal({"type": "object", "properties": {"position": tuple3}}) == (
        "Unsupported type None for array item position")
    assert "for event" in foxglove_refusal(
        {"type": "object", "properties": {"event": {"enum": ["run_start"]}}})
    assert "no properties" in foxglove_refusal(
        {"type": "object", "properties": {"provenance": {"type": "object"}}})


@pytest.mark.parametrize("name", [*JSON_SCHEMAS, *FOXGLOVE_SCHEMAS])
def test_foxglove_takes_every_stored_schema(name):
    schema = {**JSON_SCHEMAS, **FOXGLOVE_SCHEMAS}[name]
    assert foxglove_refusal(schema) is None
    jsonschema.Draft202012Validator.check_schema(schema)
    assert "prefixItems" not in json.dumps(schema)


def test_the_spec_schema_stays_exact():
    """Tuples keep their length and the unions their members: what the decoder refuses the
    schema refuses, what it takes the schema takes."""
    validator = jsonschema.Draft202012Validator(JSON_SCHEMAS["minority.Spec"])
    good = varied_spec().to_dict()
    assert validator.is_valid(good)
    for bad in ({"position": [0, 0]}, {"position": [0, 0, 0, 1]}):
        d = json.loads(json.dumps(good))
        d["views"][0]["camera"].update(bad)
        assert not validator.is_valid(d)
    d = json.loads(json.dumps(good))
    d["views"][0]["colormap"] = 7
    assert not validator.is_valid(d)
    d["views"][0]["colormap"] = "gray"
    d["sphere_radius_m"] = "big"
    assert not validator.is_valid(d)
    assert not jsonschema.Draft202012Validator(JSON_SCHEMAS["minority.Event"]).is_valid(
        {"run": "r", "event": "no_such_kind"})


def test_a_spec_logged_with_its_decoded_form_keeps_the_payload_publish_time(tmp_path):
    """The server logs its spec's payload (stamped at encode) with the Spec it loaded from a
    file (sent_ns 0): publish_time is the payload's stamp, not 0 (1970 in a viewer)."""
    spec = make_spec()
    assert spec.sent_ns == 0
    payload = bytes(spec.encode())
    with LogWriter(tmp_path / "s.mcap") as log:
        log.write_payload(keys.spec(spec.run), payload, 5, spec)
    (record,) = read_log(tmp_path / "s.mcap")
    assert record.publish_ns == decode_as(payload, Spec).sent_ns > 0


def _tracked(chunk, context: int, evict=(), reset=False):
    """`chunk` with its last `context` rows as context rows of ids 1000 + row."""
    chunk.context_ids = np.arange(1000, 1000 + context, dtype=np.int64) + (
        chunk.count - context)
    chunk.evict_ids = np.asarray(evict, np.int64)
    chunk.context_reset = reset
    return chunk


def _write_run(path):
    """A run of two ranks over two steps (rank 1 keeps context rows: 10 sent at step 20, one
    evicted at step 40), with a spec of one region and three views, frames and timing."""
    spec = varied_spec()
    chunks = [make_chunk(n=50, step=20, rank=0, seed=1),
              _tracked(make_chunk(n=30, step=20, rank=1, seed=2), 10, reset=True),
              make_chunk(n=40, step=40, rank=0, seed=3),
              _tracked(make_chunk(n=20, step=40, rank=1, seed=4), 0, evict=[1025])]
    with LogWriter(path) as log:
        log.write(spec)
        for c in chunks:
            log.write(c)
        log.write(Frame("test-run", "side", 40, 0.004, 4, 3, make_png()))
        log.write(Timing("test-run", 40, "side", 0.004, 0.01, 0.002, 0.03, 4096, 100, 2, 2,
                         False))
        log.write(Stats("test-run", 1, 40, 0.004, 100, 12.5, 0.75, 0.02, True,
                        [0] * 40 + [60] + [0] * 11, [0] * 30 + [40] + [0] * 21))
        log.write_payload("minority/test-run/timing", b"garbage", 1)
    return spec, chunks


def _messages(path):
    out = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            out.setdefault(channel.topic, []).append((schema, message))
    return out


def _points(cloud: dict) -> dict[str, np.ndarray]:
    """The columns of a foxglove.PointCloud (JSON form), decoded by its fields."""
    kinds = {NUMERIC_TYPES.index("FLOAT32"): "<f4", NUMERIC_TYPES.index("FLOAT64"): "<f8"}
    dtype = np.dtype({"names": [f["name"] for f in cloud["fields"]],
                      "formats": [kinds[f["type"]] for f in cloud["fields"]],
                      "offsets": [f["offset"] for f in cloud["fields"]],
                      "itemsize": cloud["point_stride"]})
    packed = np.frombuffer(base64.b64decode(cloud["data"]), dtype)
    return {name: packed[name] for name in dtype.names}


def test_export_writes_the_particles_regions_and_cameras(tmp_path):
    log, out = tmp_path / "run.mcap", tmp_path / "fox" / "run.foxglove.mcap"
    spec, chunks = _write_run(log)
    assert main(["log", "export", "--foxglove", str(log), "-o", str(out)]) == 0
    messages = _messages(out)
    assert validate_log(out) == {"foxglove.PointCloud": 2, "foxglove.SceneUpdate": 1,
                                 "minority.Spec": 1, "foxglove.CompressedImage": 1,
                                 "minority.Timing": 1, "minority.Stats": 1}
    assert sorted(messages) == ["/frame/side", "/particles", "/scene", "/spec", "/stats",
                                "/timing"]

    clouds = [json.loads(m.data) for _, m in messages[PARTICLES_TOPIC]]
    step20, step40 = (_points(c) for c in clouds)
    # step 20: both ranks' rows; step 40: rank 1's 20 fresh rows, its 10 cached context
    # rows of step 20 but the evicted id 1025, and rank 0's 40
    c0, c1 = chunks[0], chunks[1]
    expected20 = np.concatenate([c0.positions, c1.positions])
    assert np.array_equal(np.stack([step20[a] for a in "xyz"], 1), expected20)
    assert np.allclose(step20["displacement"], np.linalg.norm(
        np.concatenate([c0.fields["displacement"], c1.fields["displacement"]]), axis=1))
    assert np.array_equal(step20["velocity_magnitude"], np.concatenate(
        [c0.fields["velocity_magnitude"], c1.fields["velocity_magnitude"]]))
    kept = [i for i in range(20, 30) if 1000 + i != 1025]
    expected40 = np.concatenate([chunks[2].positions, chunks[3].positions,
                                 c1.positions[kept]])
    assert np.array_equal(np.stack([step40[a] for a in "xyz"], 1), expected40)
    assert "id" not in step40  # the fresh rows carry no id field
    assert clouds[0]["timestamp"]["sec"] > 0

    (scene_schema, scene_message), = messages[SCENE_TOPIC]
    scene = json.loads(scene_message.data)
    assert scene_message.publish_time > 0
    entities = {e["id"]: e for e in scene["entities"]}
    assert sorted(entities) == sorted([f"region/{r.name}" for r in spec.regions]
                                      + [f"camera/{v.name}" for v in spec.views])
    region = spec.regions[0]
    (cube,) = entities[f"region/{region.name}"]["cubes"]
    assert [cube["size"][a] for a in "xyz"] == [h - lo for lo, h in zip(
        region.lo_m, region.hi_m, strict=True)]
    for view in spec.views:
        (lines,) = entities[f"camera/{view.name}"]["lines"]
        points = np.array([[p[a] for a in "xyz"] for p in lines["points"]])
        assert np.allclose(points, frustum_segments(view))
        if not view.camera.parallel_projection:  # four edges from the camera itself
            assert np.allclose(points[0:16:4], view.camera.position)
            basis = camera_basis(view.camera)
            depth = (points[1:16:4] - basis.position) @ basis.forward
            assert np.allclose(depth, basis.distance)


def test_export_keeps_ids_when_every_row_has_one(tmp_path):
    chunk = make_chunk(n=12, step=20, rank=0, ranks=1)
    chunk.fields["id"] = np.arange(500, 512, dtype=np.int64)
    with LogWriter(tmp_path / "a.mcap") as log:
        log.write(chunk)
    result = export_foxglove(tmp_path / "a.mcap", tmp_path / "b.mcap")
    assert (result.steps, result.points, result.partial_steps) == (1, 12, 0)
    (_, message), = _messages(tmp_path / "b.mcap")[PARTICLES_TOPIC]
    assert np.array_equal(_points(json.loads(message.data))["id"], np.arange(500, 512))


def test_export_names_the_runs_of_a_log_of_several(tmp_path, capsys):
    with LogWriter(tmp_path / "two.mcap") as log:
        log.write(make_spec("run-a"))
        log.write(make_spec("run-b"))
    out = tmp_path / "out.mcap"
    assert main(["log", "export", "--foxglove", str(tmp_path / "two.mcap"), "-o", str(out)]) == 2
    assert "'run-a' and 'run-b'" in capsys.readouterr().err and not out.exists()
    assert main(["log", "export", "--foxglove", str(tmp_path / "two.mcap"), "-o", str(out),
                 "--run", "run-b"]) == 0
    (_, message), = _messages(out)["/spec"]
    assert json.loads(message.data)["run"] == "run-b"


def test_the_shipped_layout_shows_what_the_export_writes(tmp_path):
    """deploy/foxglove/minority.json: a 3D panel on the point cloud and the scene, an image
    panel on a frame topic, plots of timing and stats fields, all of them exported."""
    from pathlib import Path

    layout = json.loads((Path(__file__).parents[1] / "deploy/foxglove/minority.json").read_text())
    panels = layout["configById"]
    three_d = panels["3D!particles"]["topics"]
    assert three_d[PARTICLES_TOPIC]["colorField"] == "displacement" and SCENE_TOPIC in three_d
    assert panels["Image!frame"]["imageMode"]["imageTopic"] == "/frame/side"
    paths = [p["value"] for k, v in panels.items() if k.startswith("Plot!") for p in v["paths"]]
    timing, stats = JSON_SCHEMAS["minority.Timing"], JSON_SCHEMAS["minority.Stats"]
    for path in paths:
        topic, name = path.split(".")
        assert name in {"/timing": timing, "/stats": stats}[topic]["properties"], path
    placed = json.dumps(layout["layout"])
    assert all(f'"{panel}"' in placed for panel in panels)


def test_a_rank_that_stops_sending_leaves_partial_steps_in_step_order(tmp_path):
    """Rank 1 sends step 1 only: every later step waits for it, and the export writes the
    oldest partial once more than MAX_PENDING_STEPS wait (memory stays bounded)."""
    from minority.protocol.foxglove import MAX_PENDING_STEPS

    with LogWriter(tmp_path / "a.mcap") as log:
        log.write(make_chunk(n=5, step=1, rank=1, seed=99))
        for step in range(1, MAX_PENDING_STEPS + 4):
            log.write(make_chunk(n=5, step=step, rank=0, seed=step))
    result = export_foxglove(tmp_path / "a.mcap", tmp_path / "b.mcap")
    assert (result.steps, result.partial_steps) == (MAX_PENDING_STEPS + 3, MAX_PENDING_STEPS + 2)
    clouds = [json.loads(m.data) for _, m in _messages(tmp_path / "b.mcap")[PARTICLES_TOPIC]]
    assert [len(_points(c)["x"]) for c in clouds] == [10] + [5] * (MAX_PENDING_STEPS + 2)
    expected = [make_chunk(n=5, step=s, rank=0, seed=s).positions[:, 0]
                for s in range(2, MAX_PENDING_STEPS + 4)]
    assert all(np.array_equal(_points(c)["x"], x) for c, x in zip(clouds[1:], expected,
                                                                   strict=True))


def test_export_refuses_a_file_that_is_not_mcap(tmp_path, capsys):
    (tmp_path / "notes.mcap").write_text("hello\n")
    out = tmp_path / "out.mcap"
    assert main(["log", "export", "--foxglove", str(tmp_path / "notes.mcap"), "-o",
                 str(out)]) == 2
    assert "is not an MCAP file" in capsys.readouterr().err and not out.exists()
