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


@pytest.mark.parametrize("topic,run,kind,view", [
    ("minority/r1/chunk", "r1", "chunk", None),
    ("minority/r1/frame/side", "r1", "frame", "side"),
    ("minority/r1/timing", "r1", "timing", None),
    ("minority/r1/spec", "r1", "spec", None),
    ("minority/r1/event", "r1", "event", None),
    ("minority/r1/stats", "r1", "stats", None),
])
def test_log_topics_parse_and_build(topic, run, kind, view):
    parsed = keys.parse_log_topic(topic)
    assert (parsed.run, parsed.kind, parsed.view) == (run, kind, view)
    assert str(parsed) == keys.log_topic(run, kind, view) == topic


@pytest.mark.parametrize("key", ["minority/r1/chunk/120/3", "minority/r1/frame/side",
                                 "minority/r1/timing", "minority/r1/stats"])
def test_a_key_logs_under_the_topic_the_builder_makes(key):
    parsed = keys.parse(key)
    view = parsed.rest[0] if parsed.topic == keys.Topic.FRAME else None
    assert parsed.log_topic == keys.log_topic(parsed.run, parsed.topic, view)
    assert keys.parse_log_topic(parsed.log_topic).run == parsed.run


@pytest.mark.parametrize("topic", [keys.REJECTED_LOG_TOPIC, "minority/r1/chunk/1/0",
                                   "minority/r1/frame", "minority/r1/rank", "minority/*/chunk",
                                   "minority/r1/frame/*", "other/r1/spec", "minority/r 1/spec",
                                   "minority/r1/timing/x", "minority"])
def test_parse_log_topic_rejects(topic):
    assert keys.parse_log_topic(topic) is None


def test_log_topic_patterns():
    assert keys.log_topic(keys.ALL_RUNS, keys.Topic.CHUNK) == "minority/*/chunk"
    assert keys.log_topic("r1", keys.Topic.FRAME) == "minority/r1/frame/*"
    with pytest.raises(ValueError, match="not logged"):
        keys.log_topic("r1", keys.Topic.RANK)
    with pytest.raises(ValueError, match="view"):
        keys.log_topic("r1", keys.Topic.TIMING, "side")
    with pytest.raises(ValueError, match="view"):
        keys.log_topic("r1", keys.Topic.FRAME, "a/b")
