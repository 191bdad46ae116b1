"""A log on a full disk: on a small tmpfs, a LogWriter whose write fails ends its file at its
last complete chunk with its summary and footer (mcap's reader opens it, scanning and through
the summary), says so, and never counts a message that is not in the file."""

import errno
import os
import warnings

import pytest
from conftest import PAGE_BYTES, fill, make_chunk
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType

from minority.protocol import keys, logfile
from minority.protocol.log import LogWriter, read_log
from minority.protocol.repair import LogState, scan


def chunk_payload(step: int, n: int = 200) -> bytes:
    return bytes(make_chunk(n=n, step=step).encode())


def write_group(w: LogWriter, first: int, count: int, n: int = 200) -> bool:
    """`count` chunk messages (log times first, first + 1, ...) in one MCAP chunk; whether
    all were written."""
    for ns in range(first, first + count):
        if not w.keep(w.write_payload, keys.chunk("test-run", ns, 0), chunk_payload(ns, n), ns):
            return False
    return w.keep(w.flush)


def log_times_every_way(path) -> dict:
    """The log times of the messages of `path` as mcap's readers give them (through the
    summary's index, scanning it, and minority's read_log, which warns on a cut file) and
    the summary's message count."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        indexed = [m.log_time for _, _, m in reader.iter_messages()]
    with open(path, "rb") as f:
        scanned = [m.log_time for _, _, m in NonSeekingReader(f).iter_messages()]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # neither truncated nor damaged
        ours = [r.log_ns for r in read_log(path)]
    return {"indexed": indexed, "scanned": scanned, "read_log": ours,
            "statistics": summary.statistics.message_count}


def assert_no_room_held_past_its_end(path) -> None:
    st = os.stat(path)
    assert st.st_blocks * 512 <= -(-st.st_size // PAGE_BYTES) * PAGE_BYTES


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.ZSTD,
                                         CompressionType.LZ4])
def test_a_full_disk_ends_the_log_at_its_last_complete_chunk_with_its_summary(
        disk, capsys, compression):
    path = disk / "run.mcap"
    w = LogWriter(path, compression=compression, flush_interval_s=1e9)
    kept, ns = [], 1
    for _ in range(2):  # written before the disk fills
        assert write_group(w, ns, 3)
        kept += range(ns, ns + 3)
        ns += 3
    fill(disk)
    groups = 0
    while write_group(w, ns, 3, n=2000):  # the room reserved past the file holds a few
        kept += range(ns, ns + 3)
        ns += 3
        groups += 1
        assert groups < 100, "the disk never filled"
    assert w.failure.startswith("ENOSPC: No space left on device")
    assert (w.written, w.unwritten) == (len(kept), 3)  # the failed chunk's messages
    err = capsys.readouterr().err
    assert err.count("cannot write") == 1 and "ENOSPC" in err
    assert "ends at its last complete chunk" in err and "with its summary" in err
    assert not w.keep(w.write_payload, keys.chunk("test-run", ns + 3, 0), chunk_payload(1), 1)
    with pytest.raises(OSError, match="the log has ended: ENOSPC"):  # direct callers too
        w.write_payload(keys.chunk("test-run", ns + 4, 0), chunk_payload(1), 1)
    assert w.unwritten == 5
    assert w.finish() is False and w.failure.startswith("ENOSPC")
    with pytest.raises(OSError, match="ENOSPC"):
        w.close()
    times = log_times_every_way(path)
    assert times == {"indexed": kept, "scanned": kept, "read_log": kept,
                     "statistics": len(kept)}
    result = scan(path)
    assert result.state is LogState.COMPLETE and result.messages == len(kept)
    assert result.compression == compression.name.lower()
    assert_no_room_held_past_its_end(path)


def test_a_log_cannot_start_on_a_full_disk_and_leaves_no_file(disk):
    fill(disk)
    with pytest.raises(OSError, match="cannot start the log .*run.mcap.*ENOSPC") as raised:
        LogWriter(disk / "run.mcap")
    assert raised.value.errno == errno.ENOSPC
    assert sorted(p.name for p in disk.iterdir()) == ["filler"]


def test_finish_on_a_full_disk_says_the_open_chunk_was_not_written(disk, capsys):
    path = disk / "run.mcap"
    w = LogWriter(path, flush_interval_s=1e9)
    assert write_group(w, 1, 4)
    for ns in range(5, 9):  # in the open chunk, not on disk yet; more than the disk holds
        assert w.keep(w.write_payload, keys.chunk("test-run", ns, 0), chunk_payload(ns, 20000), ns)
    assert w.written == 8
    fill(disk)
    assert w.finish() is False
    assert w.failure.startswith("ENOSPC") and (w.written, w.unwritten) == (4, 4)
    assert "cannot write" in capsys.readouterr().err
    times = log_times_every_way(path)
    assert times["indexed"] == times["scanned"] == times["read_log"] == [1, 2, 3, 4]
    assert_no_room_held_past_its_end(path)


def test_a_log_of_many_chunks_and_channels_still_gets_its_summary(disk):
    """The room reserved for the summary grows with the chunks and channels it indexes."""
    path = disk / "run.mcap"
    w = LogWriter(path, flush_interval_s=1e9)
    kept = []
    for ns in range(1, 401):  # 400 chunks over 40 channels
        run = f"run{ns % 40}"
        payload = bytes(make_chunk(n=2, step=ns, run=run).encode())
        assert w.keep(w.write_payload, keys.chunk(run, ns, 0), payload, ns) and w.keep(w.flush)
        kept.append(ns)
    fill(disk)
    assert not write_group(w, 1000, 3, n=20000)
    assert w.failure.startswith("ENOSPC")
    assert log_times_every_way(path)["indexed"] == kept
    assert scan(path).state is LogState.COMPLETE


@pytest.fixture
def no_fallocate(monkeypatch):
    """A filesystem without fallocate: nothing is reserved past the file."""
    monkeypatch.setattr(logfile, "_fallocate", lambda: None, raising=False)


def test_without_fallocate_a_cut_chunk_leaves_its_room_to_the_summary(disk, no_fallocate):
    path = disk / "run.mcap"
    w = LogWriter(path, flush_interval_s=1e9)
    assert write_group(w, 1, 3)
    fill(disk, leave=64 << 10)
    ns, kept = 4, [1, 2, 3]
    while write_group(w, ns, 3, n=2000):  # ~56 kB a chunk: one fits, the next is cut
        kept += range(ns, ns + 3)
        ns += 3
    assert w.failure.startswith("ENOSPC") and w.written == len(kept)
    assert log_times_every_way(path)["indexed"] == kept


def test_without_room_for_the_summary_the_log_ends_at_its_last_complete_chunk(
        disk, no_fallocate, capsys):
    """The summary does not fit (nothing reserved, the failed write took no room, and its
    40 channels take more than the file's last page has left): the file still ends at a
    complete chunk, which a reader that scans reads without damage."""
    from minority.protocol.log import LogTruncatedWarning

    path = disk / "run.mcap"
    w = LogWriter(path, flush_interval_s=1e9)
    for ns in range(1, 41):
        run = f"run{ns}"
        payload = bytes(make_chunk(n=2, step=ns, run=run).encode())
        assert w.keep(w.write_payload, keys.chunk(run, ns, 0), payload, ns)
    assert w.keep(w.flush)
    fill(disk)
    assert not write_group(w, 41, 3)
    assert w.failure.startswith("ENOSPC") and (w.written, w.unwritten) == (40, 3)
    assert "without its summary" in capsys.readouterr().err
    assert scan(path).state is LogState.TRUNCATED and scan(path).lost_bytes == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not damaged
        warnings.simplefilter("ignore", LogTruncatedWarning)
        assert [r.log_ns for r in read_log(path)] == list(range(1, 41))


def test_a_finished_log_on_a_normal_disk_holds_no_reserved_room(tmp_path):
    path = tmp_path / "run.mcap"
    with LogWriter(path, chunk_bytes=1 << 10) as w:
        for ns in range(1, 50):
            w.write_payload(keys.chunk("test-run", ns, 0), chunk_payload(ns), ns)
    assert log_times_every_way(path)["indexed"] == list(range(1, 50))
    assert_no_room_held_past_its_end(path)


def test_ending_in_place_never_writes_over_a_record_that_changed(tmp_path):
    """end_in_place compares its copy with the records before the cut: a chunk damaged
    after it was written is refused (ProtocolError) and the file is left as it was."""
    from minority.protocol.errors import ProtocolError
    from minority.protocol.repair import end_in_place

    path = tmp_path / "run.mcap"
    w = LogWriter(path, flush_interval_s=1e9)
    assert write_group(w, 1, 3)
    cut = os.path.getsize(path)
    data = bytearray(path.read_bytes())
    data[cut - 1000] ^= 0xFF  # a particle's bytes in the chunk's last message
    path.write_bytes(bytes(data))
    fd = os.open(path, os.O_RDWR)
    try:
        with pytest.raises(ProtocolError, match="differs from them"):
            end_in_place(fd, cut)
    finally:
        os.close(fd)
    assert path.read_bytes() == bytes(data)
    w.abandon()
