"""Repairing MCAP logs: every cut of a killed writer's log, damaged chunks, refusals, the CLI."""

import argparse
import os
import warnings

import pytest
from conftest import make_chunk, sample_messages
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from minority import log_cli
from minority.protocol.errors import ProtocolError
from minority.protocol.log import LogWriter, read_log
from minority.protocol.repair import LogState, RepairResult, is_complete, repair, scan

CUTS = 97  # byte offsets tried per log (as test_log's truncation test)


def write_log(path, compression=CompressionType.NONE) -> tuple[bytes, bytes]:
    """A log of every message type, a rejected payload and more chunks, one MCAP chunk per
    message; returns its bytes as a killed writer leaves them (no footer) and complete."""
    log = LogWriter(path, compression=compression, metadata={"host": "node-7"})
    for i, message in enumerate(sample_messages()):
        log.write(message, log_ns=1_000 + i)
        log.flush()
    log.write_payload("minority/test-run/chunk/20/0", b"garbage", log_ns=2_000)  # rejected
    log.flush()
    for step in range(6):
        log.write(make_chunk(n=40, step=step, seed=step), log_ns=3_000 + step)
        log.flush()
    cut = path.read_bytes()  # no footer yet: as if the process had been killed
    log.close()
    return cut, path.read_bytes()


def read_expected(path) -> list[tuple]:
    """What protocol.log.read_log returns from `path` (its truncation warnings silenced)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [(r.topic, r.log_ns, r.publish_ns, r.data) for r in read_log(path)]


def read_standard(path) -> list[tuple]:
    """The messages of `path` as the standard (seeking) reader returns them."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None  # indexed: footer and summary readable
        return [(c.topic, m.log_time, m.publish_time, m.data)
                for _, c, m in reader.iter_messages(log_time_order=False)]


def layout(path) -> dict:
    """Header, schemas, channels (with metadata), metadata records, chunk compressions."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        header = reader.get_header()
        return {"header": (header.profile, header.library),
                "schemas": {(s.name, s.encoding, s.data) for s in summary.schemas.values()},
                "channels": {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name
                                       if c.schema_id else "", c.metadata)
                             for c in summary.channels.values()},
                "metadata": [(m.name, m.metadata) for m in reader.iter_metadata()],
                "chunks": [i.compression for i in summary.chunk_indexes]}


def damage_chunk(path, index: int) -> int:
    """Flip a byte inside the data of the complete log's chunk `index` (0-based; the data
    ends its record, which the CRC covers); returns the chunk's offset."""
    with open(path, "rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[index]
    data = bytearray(path.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 5] ^= 0xFF
    path.write_bytes(bytes(data))
    return chunk.chunk_start_offset


def test_every_cut_of_a_killed_log_repairs_to_what_read_log_reads(tmp_path):
    source, out = tmp_path / "run.mcap", tmp_path / "run.repaired.mcap"
    data, complete = write_log(source)
    full = layout(tmp_path / "run.mcap")
    assert len(full["channels"]) == 7 and full["metadata"][0][1]["host"] == "node-7"
    counts = []
    for cut in sorted({*range(0, len(data) + 1, max(1, len(data) // CUTS)), len(data)}):
        source.write_bytes(data[:cut])
        result = repair(source, out)
        expected = read_expected(source)
        assert result.state is LogState.TRUNCATED and result.stopped_at <= cut == result.size
        assert result.messages == len(expected) and is_complete(out)
        assert read_standard(out) == expected
        if expected:  # schemas and channel metadata of the messages kept, as in the full log
            kept = layout(out)
            assert kept["header"] == full["header"] == ("minority", "minority")
            assert kept["schemas"] <= full["schemas"]
            assert all(full["channels"][t] == c for t, c in kept["channels"].items())
            assert kept["metadata"] == full["metadata"]
        counts.append(result.messages)
    assert counts == sorted(counts) and counts[-1] == 13 and counts[0] == 0
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]
    source.write_bytes(complete)
    assert scan(source).state is LogState.COMPLETE


@pytest.mark.parametrize("compression", list(CompressionType))
def test_a_complete_log_is_copied_whole_with_its_chunks(tmp_path, compression):
    source, out = tmp_path / "run.mcap", tmp_path / "copy.mcap"
    write_log(source, compression)
    result = repair(source, out)
    assert result.state is LogState.COMPLETE and result.reason == ""
    assert result.stopped_at == result.size == source.stat().st_size and result.lost_bytes == 0
    assert result.messages == 13 and result.chunks == 13 and result.metadata == 1
    assert result.compression == compression.name.lower()
    assert read_standard(out) == read_standard(source) == read_expected(source)
    assert layout(out) == layout(source)  # same chunks, compressed alike


def test_attachments_metadata_sequences_and_schemaless_channels_survive(tmp_path):
    source, out = tmp_path / "other.mcap", tmp_path / "other.repaired.mcap"
    with open(source, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="someone-else/1.0")
        schema = w.register_schema("pkg/Point", "ros2msg", b"float64 x")
        typed = w.register_channel("/point", "cdr", schema, {"qos": "reliable"})
        raw = w.register_channel("/raw", "application/octet-stream", 0, {})
        w.add_metadata("calibration", {"k": "1.5"})
        w.add_attachment(5, 6, "notes.txt", "text/plain", b"hello")
        for i in range(4):
            w.add_message(typed if i % 2 else raw, 100 + i, bytes([i]) * 9, 50 + i, sequence=7 + i)
            w.flush()
        data = source.read_bytes()  # killed before finish()
    source.write_bytes(data)
    result = repair(source, out)
    assert (result.state, result.messages, result.attachments, result.metadata) == (
        LogState.TRUNCATED, 4, 1, 1)
    assert result.compression == "zstd" and result.chunked
    with open(out, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        assert (header.profile, header.library) == ("ros2", "someone-else/1.0")
        messages = list(reader.iter_messages())
        assert [(c.topic, s.name if s else None, m.log_time, m.publish_time, m.sequence, m.data)
                for s, c, m in messages] == [
            ("/raw", None, 100, 50, 7, b"\x00" * 9), ("/point", "pkg/Point", 101, 51, 8, b"\x01" * 9),
            ("/raw", None, 102, 52, 9, b"\x02" * 9), ("/point", "pkg/Point", 103, 53, 10, b"\x03" * 9)]
        assert messages[1][1].metadata == {"qos": "reliable"} and messages[1][0].data == b"float64 x"
        assert [(m.name, m.metadata) for m in reader.iter_metadata()] == [("calibration", {"k": "1.5"})]
        (attachment,) = reader.iter_attachments()
        assert (attachment.create_time, attachment.log_time, attachment.name,
                attachment.media_type, attachment.data) == (5, 6, "notes.txt", "text/plain", b"hello")


@pytest.mark.parametrize("compression", list(CompressionType))
def test_a_damaged_chunk_ends_the_copy_before_it(tmp_path, compression):
    source, out = tmp_path / "d.mcap", tmp_path / "d.repaired.mcap"
    write_log(source, compression)
    offset = damage_chunk(source, 4)  # the chunk of the 5th message
    result = repair(source, out)
    expected = read_expected(source)
    assert result.state is LogState.DAMAGED and result.messages == 4 and result.chunks == 4
    assert result.stopped_at == offset < result.size and "damaged chunk" in result.reason
    assert len(expected) == 4 and read_standard(out) == expected
    assert scan(source) == result


def test_a_file_that_is_not_mcap_is_refused(tmp_path):
    source = tmp_path / "notes.mcap"
    source.write_bytes(b"this is a text file, not a log\n")
    with pytest.raises(ProtocolError, match="not an MCAP file"):
        repair(source, tmp_path / "out" / "x.mcap")
    with pytest.raises(ProtocolError, match="not an MCAP file"):
        scan(source)
    assert not is_complete(source)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.mcap"]  # nothing written


def test_the_source_is_never_the_output(tmp_path):
    source = tmp_path / "run.mcap"
    data, _ = write_log(source)
    source.write_bytes(data)
    (tmp_path / "sub").mkdir()
    os.link(source, tmp_path / "hardlink.mcap")
    for dst in (source, tmp_path / "sub" / ".." / "run.mcap", tmp_path / "hardlink.mcap"):
        with pytest.raises(ValueError, match="must not replace its source"):
            repair(source, dst)
    assert source.read_bytes() == data


def test_a_failed_write_leaves_the_old_output_and_no_half_file(tmp_path, monkeypatch):
    source, out = tmp_path / "run.mcap", tmp_path / "run.repaired.mcap"
    data, _ = write_log(source)
    source.write_bytes(data)
    out.write_bytes(b"previous copy")

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Writer, "add_message", full_disk)
    with pytest.raises(OSError, match="No space left"):
        repair(source, out)
    assert out.read_bytes() == b"previous copy"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap", "run.repaired.mcap"]


def test_an_empty_file_from_a_writer_killed_at_once_repairs_to_an_empty_log(tmp_path):
    source, out = tmp_path / "empty.mcap", tmp_path / "empty.repaired.mcap"
    source.write_bytes(b"")
    result = repair(source, out)
    assert result == RepairResult(LogState.TRUNCATED, 0, 0, 0, "the file ends without its MCAP footer")
    assert is_complete(out) and read_standard(out) == []


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """`minority log ...` through a parser built as minority.cli.build_parser builds one."""
    parser = argparse.ArgumentParser(prog="minority")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    log_cli.add_parser(sub)
    args = parser.parse_args(list(argv))
    status = args.func(args)
    out, err = capsys.readouterr()
    assert "Traceback" not in err and len(err.splitlines()) <= 1
    return status, out, err


def test_cli_repair_writes_beside_the_input_and_never_overwrites(tmp_path, capsys):
    source = tmp_path / "run.mcap"
    data, _ = write_log(source)
    source.write_bytes(data)
    status, out, _ = run_cli(capsys, "log", "repair", str(source))
    default = tmp_path / "run.repaired.mcap"
    assert status == 0 and len(out.splitlines()) == 1
    assert "truncated" in out and "kept 13 messages" in out and str(default) in out
    assert read_standard(default) == read_expected(source)
    status, _, err = run_cli(capsys, "log", "repair", str(source))
    assert status == 2 and "exists" in err and "--force" in err
    assert run_cli(capsys, "log", "repair", str(source), "--force")[0] == 0
    nested = tmp_path / "new" / "dir" / "fixed.mcap"
    assert run_cli(capsys, "log", "repair", str(source), "-o", str(nested))[0] == 0
    assert is_complete(nested)
    assert log_cli.default_output(tmp_path / "run.log") == tmp_path / "run.log.repaired.mcap"


def test_cli_repair_exit_codes(tmp_path, capsys):
    source = tmp_path / "run.mcap"
    data, _ = write_log(source)
    source.write_bytes(data)
    (tmp_path / "notes.txt").write_text("not a log\n")
    (tmp_path / "a_file").write_text("")
    for argv, status, said in [
        ([str(tmp_path / "missing.mcap")], 2, "no such file"),
        ([str(tmp_path)], 2, "not a regular file"),
        ([str(tmp_path / "notes.txt")], 2, "not an MCAP file"),
        ([str(source), "-o", str(source), "--force"], 2, "must not replace its source"),
        ([str(source), "-o", str(tmp_path / "a_file" / "x.mcap")], 1, "cannot write"),
    ]:
        got, _, err = run_cli(capsys, "log", "repair", *argv)
        assert (got, said in err) == (status, True), (argv, err)
    assert source.read_bytes() == data


def test_cli_check_says_complete_truncated_or_damaged(tmp_path, capsys):
    source = tmp_path / "run.mcap"
    data, complete = write_log(source)
    status, out, _ = run_cli(capsys, "log", "check", str(source))
    assert status == 0 and "complete: 13 messages on 7 channels" in out
    source.write_bytes(data[:-100])
    status, out, _ = run_cli(capsys, "log", "check", str(source))
    assert status == 1 and "truncated" in out and "12 messages" in out and "log repair" in out
    source.write_bytes(complete)
    damage_chunk(source, 4)
    status, out, _ = run_cli(capsys, "log", "check", str(source))
    assert status == 1 and "damaged" in out and "4 messages" in out
    assert run_cli(capsys, "log", "check", str(tmp_path / "missing.mcap"))[0] == 2


@pytest.mark.parametrize("argv,words", [
    (["log"], ["check", "repair", "killed"]),
    (["log", "repair"], ["OUT.mcap", "--force", ".repaired.mcap", "Exit status"]),
    (["log", "check"], ["complete", "truncated", "damaged", "Exit status"]),
])
def test_cli_help(capsys, argv, words):
    with pytest.raises(SystemExit) as exit_:
        run_cli(capsys, *argv, "--help")
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert all(w in text for w in words), text
