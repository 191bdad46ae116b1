"""Key expressions of docs/architecture.md and their parsing."""

import pytest
from minority.protocol import keys


def test_key_expressions():
    assert keys.spec("r1") == "minority/r1/spec"
    assert keys.chunk("r1", 120, 3) == "minority/r1/chunk/120/3"
    assert keys.rank_token("r1", 2) == "minority/r1/rank/2"
    assert keys.frame("r1", "side") == "minority/r1/frame/side"
    assert keys.timing("r1") == "minority/r1/timing"
    assert keys.event("r1") == "minority/r1/event"
    assert keys.everything() == "minority/*/**"
    assert keys.chunks("r1") == "minority/r1/chunk/**"


@pytest.mark.parametrize("key,topic,log_topic", [
    ("minority/r1/chunk/120/3", "chunk", "minority/r1/chunk"),
    ("minority/r1/frame/side", "frame", "minority/r1/frame/side"),
    ("minority/r1/timing", "timing", "minority/r1/timing"),
    ("minority/r1/spec", "spec", "minority/r1/spec"),
])
def test_parse(key, topic, log_topic):
    parsed = keys.parse(key)
    assert parsed.topic == topic and parsed.run == "r1" and parsed.log_topic == log_topic


@pytest.mark.parametrize("key", ["other/r1/spec", "minority/r1/chunk/1", "minority/r1/nope",
                                 "minority/r 1/spec", "minority/r1/frame/a/b", "minority"])
def test_parse_rejects(key):
    assert keys.parse(key) is None


def test_bad_run_name_refused():
    with pytest.raises(ValueError, match="run"):
        keys.spec("a/b")
