"""The JSON Schemas an MCAP log stores hold every message it stores: each JSON record of a
log of every message kind (and of the demo's log, tests/test_demo.py) validates against its
channel's own schema, read back from the file (Draft 2020-12, with jsonschema)."""

import json

import jsonschema
from conftest import make_spec, sample_messages
from mcap.reader import make_reader

from minority.protocol import Event, EventKind, Spec
from minority.protocol.log import LogWriter


def validate_log(path) -> dict[str, int]:
    """Validate every JSON message of the log against its channel's stored schema; returns
    how many messages each schema validated."""
    counts: dict[str, int] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding != "json":
                continue
            validator = jsonschema.Draft202012Validator(json.loads(schema.data))
            errors = sorted(validator.iter_errors(json.loads(message.data)), key=str)
            assert not errors, f"{channel.topic} ({schema.name}): {errors[0].message}"
            counts[schema.name] = counts.get(schema.name, 0) + 1
    return counts


def varied_spec() -> Spec:
    """Every shape a spec takes: a window with only every_s, an open end, regions, an inline
    colormap, occlusion_cull, the one-window shorthand, provenance."""
    d = make_spec().to_dict()
    d["views"][0]["occlusion_cull"] = True
    d["views"][0]["schedule"] = [{"t_start_s": 0.0, "t_end_s": None, "every_s": 0.01,
                                  "regions": ["toe"]}]
    d["views"][1]["colormap"] = {"Name": "gray", "ColorSpace": "RGB",
                                 "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1]}
    d["regions"] = [{"name": "toe", "lo_m": [0, 0, 0], "hi_m": [1, 1, 1]}]
    d["provenance"] = {"made_by": "test"}
    flat = {k: v for k, v in d["views"][1].items() if k != "schedule"}
    d["views"].append({**flat, "name": "flat", "t_start_s": 0.1, "every_steps": 5})
    return Spec.from_dict(d)


def test_every_json_message_validates_against_its_stored_schema(tmp_path):
    path = tmp_path / "all.mcap"
    with LogWriter(path) as log:
        for message in [*sample_messages(), varied_spec(),
                        Event("test-run", EventKind.RUN_END, -1, "end", {"chunks": 3})]:
            log.write(message)
        log.write_payload("minority/test-run/timing", b"garbage", 1)  # the rejected topic
    counts = validate_log(path)
    assert counts == {"minority.Spec": 2, "foxglove.CompressedImage": 1, "minority.Timing": 1,
                      "minority.Event": 2, "minority.Stats": 1, "minority.Rejected": 1}


def test_a_schema_refuses_what_the_decoder_refuses(tmp_path):
    """The schemas are closed: a key the code does not know fails them (so a key the code
    writes and the schema lacks is caught by the test above)."""
    path = tmp_path / "one.mcap"
    with LogWriter(path) as log:
        log.write(make_spec())
    with open(path, "rb") as f:
        schema = next(make_reader(f).iter_messages())[0]
    d = make_spec().to_dict()
    d["views"][0]["colour"] = "red"
    assert not jsonschema.Draft202012Validator(json.loads(schema.data)).is_valid(d)


def test_the_schemas_are_self_contained_and_portable():
    """Viewers read one schema per channel: no $ref to resolve; name patterns use only what
    JavaScript's regular expressions also have (no \\Z), and still refuse a trailing newline."""
    import re

    from minority.protocol.schemas import JSON_SCHEMAS

    for name, schema in JSON_SCHEMAS.items():
        text = json.dumps(schema)
        assert "$ref" not in text and "\\\\Z" not in text, name
    pattern = JSON_SCHEMAS["minority.Timing"]["properties"]["run"]["pattern"]
    assert re.search(pattern, "run-1") and not re.search(pattern, "run-1\n")
    timing = {"run": "r", "step": 1, "view": "v\n"}
    assert not jsonschema.Draft202012Validator(JSON_SCHEMAS["minority.Timing"]).is_valid(timing)
