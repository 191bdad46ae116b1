"""Golden files: an unintended change of the wire format fails here.

Regenerate deliberately (and bump FORMAT_VERSION if old files no longer decode) with
`MINORITY_REGEN_GOLDEN=1 pytest tests/test_protocol_golden.py`.
"""

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import msgspec
import pytest
from conftest import sample_messages

from minority.protocol import Chunk, decode_message

GOLDEN = Path(__file__).parent / "golden"
SENT_NS = 1_700_000_000_123_456_789
REGEN = os.environ.get("MINORITY_REGEN_GOLDEN") == "1"


def summary(message) -> dict:
    """What a decoder must produce from the golden bytes, as JSON."""
    if isinstance(message, Chunk):
        return {"meta": msgspec.to_builtins(message.meta()), "sent_ns": message.sent_ns,
                "fields": {k: {"dtype": v.dtype.str, "shape": list(v.shape),
                               "sha256": hashlib.sha256(v.tobytes()).hexdigest()}
                           for k, v in message.fields.items()}}
    return {"json": message.to_json(), "sent_ns": message.sent_ns}


def normalized(obj) -> dict:
    return json.loads(json.dumps(obj))  # tuples -> lists, as stored


NAMES = ["chunk", "spec", "frame", "timing", "event", "stats"]


@pytest.mark.skipif(not REGEN, reason="set MINORITY_REGEN_GOLDEN=1 to rewrite the golden files")
def test_regenerate_golden():
    for message in sample_messages():
        name = type(message).__name__.lower()
        replace = (msgspec.structs.replace if isinstance(message, msgspec.Struct)
                   else dataclasses.replace)
        message = replace(message, sent_ns=SENT_NS)
        payload = bytes(message.encode())
        (GOLDEN / f"{name}.bin").write_bytes(payload)
        (GOLDEN / f"{name}.json").write_text(
            json.dumps(normalized(summary(decode_message(payload))), indent=1) + "\n")


@pytest.mark.parametrize("name", NAMES)
def test_golden_decodes_and_reencodes_identically(name):
    golden = (GOLDEN / f"{name}.bin").read_bytes()
    message = decode_message(golden)
    assert normalized(summary(message)) == json.loads((GOLDEN / f"{name}.json").read_text())
    assert bytes(message.encode()) == golden, f"encoding of {name} changed; see the docstring"


def test_version_1_spec_golden_still_decodes():
    """Spec version 1 (one window per view) reads as the same spec; it re-encodes as version 2."""
    from conftest import make_spec

    message = decode_message((GOLDEN / "spec_v1.bin").read_bytes())
    stored = json.loads((GOLDEN / "spec_v1.json").read_text())["json"]
    assert stored["version"] == 1 and message == make_spec()
