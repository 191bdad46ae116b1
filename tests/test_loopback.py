"""Two zenoh sessions on loopback exchange chunks; the recorder logs them byte for byte;
a recorder killed with SIGKILL leaves a readable file. Waits are on message counts."""

import os
import signal
import struct
import subprocess
import sys
import threading
import time
import warnings

from conftest import fail_call, make_chunk

from minority.protocol import Chunk, decode_as, keys
from minority.protocol.log import LogDamagedWarning, LogTruncatedWarning, Recorder, read_log
from minority.protocol.session import LOSSLESS_QOS, Inbox, put

RUN = "test-run"
TIMEOUT_S = 30.0


def wait_until(predicate, timeout_s: float = TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    tick = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            return False
        tick.wait(0.01)
    return True


def handshake(sender, inboxes, timeout_s: float = TIMEOUT_S) -> int:
    """Publish step-0 probes until every subscriber has seen one (routes are established);
    returns how many probes were sent."""
    probe, sent = make_chunk(n=1, step=0, run=RUN), 0

    def probe_and_check() -> bool:
        nonlocal sent
        put(sender, keys.chunk(RUN, 0, 0), probe.encode(), LOSSLESS_QOS)
        sent += 1
        return all(i.received for i in inboxes)

    assert wait_until(probe_and_check, timeout_s)
    return sent


def test_hundred_chunks_arrive_and_are_logged_byte_identical(server, client_factory, tmp_path):
    sender, observer = client_factory(), client_factory()
    inbox = Inbox(server, keys.chunks(RUN), capacity=512)
    recorder = Recorder(observer, tmp_path / "loop.mcap", run=RUN, flush_interval_s=0.1)
    probes = handshake(sender, [inbox, recorder])

    sent = []
    for step in range(1, 101):
        payload = make_chunk(n=2000, step=step, rank=step % 2, seed=step, run=RUN).encode()
        put(sender, keys.chunk(RUN, step, step % 2), payload, LOSSLESS_QOS)
        sent.append(bytes(payload))  # after the send stamp, as it went out

    assert wait_until(lambda: inbox.received == probes + 100)
    assert wait_until(lambda: recorder.written == probes + 100)
    got = []
    while (item := inbox.get(timeout=0)) is not None:
        got.append(item)
    got = [g for g in got if decode_as(g.payload, Chunk).step > 0]
    assert [g.payload for g in got] == sent and inbox.dropped == 0
    assert got[4].key == keys.chunk(RUN, 5, 1)
    recorder.close()
    assert recorder.dropped == 0 and recorder.writer.rejected == 0

    logged = [r.data for r in read_log(tmp_path / "loop.mcap", ["minority/*/chunk"])]
    logged = [d for d in logged if decode_as(d, Chunk).step > 0]
    assert logged == sent


def test_recorder_killed_mid_run_leaves_a_readable_file(server, client_factory, endpoint, tmp_path):
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "minority", "record", "--connect", endpoint, "-o", str(path),
         "--run", RUN, "--flush-interval", "0.05", "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        sender = client_factory()
        step = 0

        def logged() -> int:  # the recorder is writing: its last chunk may be partial
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LogDamagedWarning)
                warnings.simplefilter("ignore", LogTruncatedWarning)
                return sum(1 for _ in read_log(path)) if path.exists() else 0

        def publish_and_check() -> bool:
            nonlocal step
            step += 1
            put(sender, keys.chunk(RUN, step, 0), make_chunk(n=500, step=step, run=RUN).encode(),
                LOSSLESS_QOS)
            return logged() >= 20

        assert wait_until(publish_and_check), proc.stderr.read1(4096) if proc.poll() else "no log"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=TIMEOUT_S)
        proc.stderr.close()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        records = list(read_log(path))
    # the file has no footer: its truncation is said; SIGKILL may also cut the chunk being
    # written: that, and nothing else, may be reported
    assert any(issubclass(w.category, LogTruncatedWarning) for w in caught), caught
    assert all(issubclass(w.category, (LogDamagedWarning, LogTruncatedWarning))
               for w in caught), caught
    assert len(records) >= 20
    steps = [r.decode().step for r in records]
    assert steps == sorted(steps) and all(r.topic == f"minority/{RUN}/chunk" for r in records)


def test_inbox_bounds_queued_bytes(server, client_factory):
    sender = client_factory()
    payload = make_chunk(n=1000, run=RUN).encode()  # ~28 kB
    inbox = Inbox(server, keys.chunks(RUN), capacity=100, max_bytes=3 * len(payload))
    probes = handshake(sender, [inbox])
    assert wait_until(lambda: inbox.received == probes)
    while inbox.get(timeout=0) is not None:  # drain the probes
        pass
    dropped = inbox.dropped
    for step in range(1, 11):
        put(sender, keys.chunk(RUN, step, 0), make_chunk(n=1000, step=step, run=RUN).encode(),
            LOSSLESS_QOS)
    assert wait_until(lambda: inbox.received == probes + 10)
    assert inbox.dropped - dropped == 7  # only three payloads fit
    assert [decode_as(inbox.get(timeout=0).payload, Chunk).step for _ in range(3)] == [1, 2, 3]
    put(sender, keys.chunk(RUN, 11, 0), make_chunk(n=1000, step=11, run=RUN).encode(), LOSSLESS_QOS)
    assert wait_until(lambda: inbox.received == probes + 11)
    assert inbox.get(timeout=5) is not None  # room again once drained


def test_recorder_survives_a_write_error(server, client_factory, tmp_path):
    """A write that fails (a full disk) ends the file at its last complete chunk, with its
    summary: the recorder keeps receiving, counts what it did not write, and its close
    reports the failure."""
    sender, observer = client_factory(), client_factory()
    recorder = Recorder(observer, tmp_path / "full.mcap", run=RUN, flush_interval_s=0.1)
    recorder.writer.write_payload, calls = fail_call(recorder.writer.write_payload, 2,
                                                     OSError(28, "No space left on device"))
    probes = handshake(sender, [recorder])
    for step in range(1, 11):
        put(sender, keys.chunk(RUN, step, 0), make_chunk(n=10, step=step, run=RUN).encode(),
            LOSSLESS_QOS)
    assert wait_until(lambda: recorder.received == probes + 10)
    assert recorder.close() is False
    assert len(calls) == 2 and recorder.written <= 1
    assert recorder.written + recorder.write_errors == probes + 10
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # complete: summary and footer
        assert len(list(read_log(tmp_path / "full.mcap"))) == recorder.written


def test_recorder_survives_a_negative_sent_time(server, client_factory, tmp_path):
    """A timing message stamped before the epoch is rejected with its reason; the recorder
    writes on and its file is complete."""
    from minority.protocol import Timing

    sender, observer = client_factory(), client_factory()
    recorder = Recorder(observer, tmp_path / "neg.mcap", run=RUN, flush_interval_s=0.1)
    probes = handshake(sender, [recorder])
    payload = Timing(RUN, 1, "side").encode()
    struct.pack_into("<q", payload, 24, -(2**62))
    sender.put(keys.timing(RUN), bytes(payload))  # raw: session.put would restamp it
    put(sender, keys.chunk(RUN, 2, 0), make_chunk(n=10, step=2, run=RUN).encode(), LOSSLESS_QOS)
    assert wait_until(lambda: recorder.received == probes + 2)
    recorder.close()
    assert recorder.write_errors == 0 and recorder.written == probes + 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        topics = [r.topic for r in read_log(tmp_path / "neg.mcap")]
    assert topics[-2:] == ["minority/_rejected", f"minority/{RUN}/chunk"]
