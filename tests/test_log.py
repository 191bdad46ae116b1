"""MCAP log: schemas, byte-identical chunks, JSON frames/timing, rejects, truncated files."""

import json
import os
import warnings

import pytest
from conftest import make_chunk, sample_messages
from mcap.reader import make_reader
from mcap.writer import CompressionType

from minority.protocol import Chunk, Frame, ProtocolError, Timing
from minority.protocol.log import (
    REJECTED_TOPIC,
    LogDamagedWarning,
    LogTruncatedWarning,
    LogWriter,
    read_log,
)


def write_samples(path, **options):
    messages = sample_messages()
    with LogWriter(path, **options) as log:
        for i, m in enumerate(messages):
            log.write(m, log_ns=1_000 + i)
    return messages


def test_every_type_round_trips(tmp_path):
    path = tmp_path / "run.mcap"
    messages = write_samples(path)
    records = list(read_log(path))
    assert [r.topic for r in records] == ["minority/test-run/chunk", "minority/test-run/spec",
                                          "minority/test-run/frame/side", "minority/test-run/timing",
                                          "minority/test-run/event", "minority/test-run/stats"]
    assert [r.log_ns for r in records] == [1000, 1001, 1002, 1003, 1004, 1005]
    for message, record in zip(messages, records, strict=True):
        back = record.decode()
        assert type(back) is type(message)
        if isinstance(message, Chunk):
            assert back.meta() == message.meta()
            assert bytes(back.encode()) == record.data  # stored as sent
        elif isinstance(message, Frame):
            assert back.png == message.png and back.meta() == message.meta()
        else:
            assert json.dumps(back.to_json()) == json.dumps(message.to_json())


def test_standard_reader_sees_schemas_and_metadata(tmp_path):
    path = tmp_path / "run.mcap"
    write_samples(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        assert schemas == {"minority.Chunk": "minority-wire-v1", "minority.Spec": "jsonschema",
                           "foxglove.CompressedImage": "jsonschema", "minority.Timing": "jsonschema",
                           "minority.Event": "jsonschema", "minority.Stats": "jsonschema"}
        channels = {c.topic: c for c in summary.channels.values()}
        assert channels["minority/test-run/timing"].message_encoding == "json"
        assert channels["minority/test-run/chunk"].metadata["run"] == "test-run"
        assert summary.statistics.message_count == 6
    frame = next(r for r in read_log(path) if r.schema == "foxglove.CompressedImage")
    obj = json.loads(frame.data)
    assert obj["format"] == "png" and obj["frame_id"] == "side" and {"sec", "nsec"} <= obj["timestamp"].keys()


def test_chunk_payload_stored_byte_for_byte(tmp_path):
    payload = bytes(make_chunk(n=500).encode())
    with LogWriter(tmp_path / "c.mcap") as log:
        log.write_payload("minority/test-run/chunk/20/0", payload)
    (record,) = read_log(tmp_path / "c.mcap")
    assert record.data == payload


@pytest.mark.parametrize("key,payload,reason", [
    ("minority/test-run/chunk/20/0", b"garbage", "shorter than the 32-byte prefix"),
    ("minority/test-run/frame/side", None, "expected a frame message, got chunk"),
    ("minority/other-run/chunk/20/0", None, "does not match key run"),
    ("elsewhere/x", None, "not a minority message key"),
])
def test_malformed_messages_are_rejected_not_lost(tmp_path, key, payload, reason):
    good = bytes(make_chunk().encode())
    path = tmp_path / "r.mcap"
    with LogWriter(path) as log:
        log.write_payload(key, good if payload is None else payload)
        log.write_payload("minority/test-run/chunk/20/0", good)
        assert log.rejected == 1 and log.written == 1
    rejected, kept = list(read_log(path, [REJECTED_TOPIC])), list(read_log(path, ["*/chunk"]))
    assert len(rejected) == 1 and len(kept) == 1 and kept[0].data == good
    body = json.loads(rejected[0].data)
    assert reason in body["reason"] and body["key"] == key


def test_topic_and_time_filters(tmp_path):
    path = tmp_path / "run.mcap"
    write_samples(path)
    assert [r.topic for r in read_log(path, ["minority/*/timing"])] == ["minority/test-run/timing"]
    assert [r.log_ns for r in read_log(path, start_ns=1001, end_ns=1003)] == [1001, 1002]
    assert isinstance(next(read_log(path, ["*/timing"])).decode(), Timing)


def test_truncated_log_yields_its_complete_chunks(tmp_path):
    path = tmp_path / "t.mcap"
    payloads = [bytes(make_chunk(n=50, step=s).encode()) for s in range(10)]
    log = LogWriter(path)
    for step, payload in enumerate(payloads):
        log.write_payload(f"minority/test-run/chunk/{step}/0", payload, log_ns=step)
        log.flush()  # one MCAP chunk per message
    size = os.path.getsize(path)  # no footer yet: as if the process had been killed
    data = path.read_bytes()
    counts = []
    for cut in range(0, size + 1, max(1, size // 97)):
        path.write_bytes(data[:cut])
        with warnings.catch_warnings():
            warnings.simplefilter("error", LogDamagedWarning)  # a cut tail is not damage
            with pytest.warns(LogTruncatedWarning):
                records = list(read_log(path))
        assert [r.data for r in records] == payloads[:len(records)]
        counts.append(len(records))
    assert counts == sorted(counts) and counts[-1] >= 9
    log.close()


@pytest.mark.parametrize("compression", list(CompressionType))
def test_a_damaged_chunk_inside_the_log_is_said(tmp_path, compression):
    path = tmp_path / "d.mcap"
    payloads = [bytes(make_chunk(n=50, step=s).encode()) for s in range(10)]
    with LogWriter(path, compression=compression) as log:
        for step, payload in enumerate(payloads):
            log.write_payload(f"minority/test-run/chunk/{step}/0", payload, log_ns=step)
            log.flush()
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0xFF  # one flipped byte in a chunk's data
    path.write_bytes(bytes(data))
    with pytest.warns(LogDamagedWarning, match="unreadable record"):
        records = list(read_log(path))
    assert 0 < len(records) < 10 and [r.data for r in records] == payloads[:len(records)]


def test_a_log_is_never_overwritten(tmp_path):
    from minority.protocol.log import free_log_path

    path = tmp_path / "run.mcap"
    with LogWriter(path) as log:
        log.write(make_chunk(n=5))
    size = path.stat().st_size
    with pytest.raises(FileExistsError):
        LogWriter(path)
    assert path.stat().st_size == size
    assert free_log_path(path) == tmp_path / "run.1.mcap"
    (tmp_path / "run.1.mcap").touch()
    assert free_log_path(path) == tmp_path / "run.2.mcap"


def test_times_outside_mcap_range_never_reach_the_writer(tmp_path):
    """A message whose decoded time cannot be stored goes to the rejected topic; a log time
    outside the range is refused before anything is written, and the file stays whole."""
    path = tmp_path / "t.mcap"
    chunk = make_chunk(n=5)
    with LogWriter(path) as log:
        with pytest.raises(ValueError, match="log time"):
            log.write(chunk, log_ns=-5)
        bad = make_chunk(n=5)
        bad.sent_ns = -7
        assert log.write_payload("minority/test-run/chunk/0/0", b"", 1, message=bad) \
            == REJECTED_TOPIC
        log.write(chunk, log_ns=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # complete, undamaged
        records = list(read_log(path))
    assert [r.topic for r in records] == [REJECTED_TOPIC, "minority/test-run/chunk"]


@pytest.mark.parametrize("data", [b"\xff", b"[" * 100_000, b'{"run": ' + b"9" * 5000 + b"}"])
def test_a_stored_json_record_that_cannot_be_parsed_is_a_protocol_error(data):
    from minority.protocol.log import LogRecord

    record = LogRecord("minority/r/timing", 0, 0, "minority.Timing", data)
    with pytest.raises(ProtocolError, match="stored JSON is invalid"):
        record.decode()


def write_mixed(path, compression=CompressionType.NONE, run="test-run"):
    """Ten steps of two chunks, a timing and (every other step) a frame, one MCAP chunk per
    step; log times step back once (a clock adjustment), so file order is not time order."""
    from conftest import make_png

    with LogWriter(path, compression=compression) as log:
        for step in range(10):
            t = 1_000 * step if step != 6 else 500  # step 6 arrives "before" step 1
            for rank in range(2):
                log.write(make_chunk(n=20, step=step, rank=rank, run=run), log_ns=t + rank)
            log.write(Timing(run, step, "side", step * 1e-4, 0.01, 0.001, 0.002, 100, 40, 2, 2,
                             False), log_ns=t + 5)
            if step % 2:
                log.write(Frame(run, "side", step, step * 1e-4, 4, 3, make_png()), log_ns=t + 6)
            log.flush()


@pytest.mark.parametrize("compression", list(CompressionType))
@pytest.mark.parametrize("topics,start_ns,end_ns", [
    (None, None, None), (["minority/*/timing"], None, None), (["*/frame/*"], None, None),
    (["minority/test-run/chunk", "minority/test-run/frame/side"], 1_000, 7_000),
    (["minority/nope/*"], None, None), (None, 4_000, 4_002)])
def test_the_index_reads_the_same_messages_as_a_scan(tmp_path, compression, topics, start_ns,
                                                     end_ns):
    path = tmp_path / "m.mcap"
    write_mixed(path, compression)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # complete: neither read warns
        indexed = list(read_log(path, topics, start_ns, end_ns))
        scanned = list(read_log(path, topics, start_ns, end_ns, use_index=False))
    assert indexed == scanned  # same records, same (file) order
    if topics == ["minority/*/timing"]:
        assert [r.decode().step for r in indexed] == list(range(10))


def test_a_read_of_some_topics_opens_only_the_chunks_holding_them(tmp_path, monkeypatch):
    from minority.protocol import logread

    path = tmp_path / "m.mcap"
    write_mixed(path)
    opened = []
    real = logread.breakup_chunk
    monkeypatch.setattr(logread, "breakup_chunk",
                        lambda chunk, **kw: opened.append(chunk) or real(chunk, **kw))
    frames = list(read_log(path, ["minority/test-run/frame/*"]))
    assert [r.decode().step for r in frames] == [1, 3, 5, 7, 9] and len(opened) == 5
    opened.clear()
    assert len(list(read_log(path))) == 35 and len(opened) == 10


def test_a_damaged_chunk_read_through_the_index_is_said(tmp_path):
    path = tmp_path / "d.mcap"
    write_mixed(path)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    third = sorted(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)[2]
    data = bytearray(path.read_bytes())
    data[third - 10] ^= 0xFF  # in the records of the third chunk (step 2)
    path.write_bytes(bytes(data))
    with pytest.warns(LogDamagedWarning, match="unreadable record"):
        steps = [r.decode().step for r in read_log(path, ["*/timing"])]
    assert steps == [0, 1]


def test_topic_counts_come_from_the_summary(tmp_path):
    from minority.protocol.log import topic_counts

    path = tmp_path / "m.mcap"
    write_mixed(path)
    assert topic_counts(path) == {"minority/test-run/chunk": 20, "minority/test-run/timing": 10,
                                  "minority/test-run/frame/side": 5}
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-100])  # no footer, no summary
    assert topic_counts(cut) is None
