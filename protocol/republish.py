"""Re-publish a recorded run: its chunks and specs from an MCAP log, at the recorded pacing,
with the simulation's QoS, to whatever render server subscribes (`minority replay --publish`).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from minority.protocol import keys
from minority.protocol.errors import ProtocolError
from minority.protocol.logread import LogNote, read_log_noting
from minority.protocol.messages import Chunk
from minority.protocol.runlog import RunLogError, log_run, log_specs
from minority.protocol.session import CONTROL_QOS, LOSSLESS_QOS, put

# The simulation's sender QoS (insitu.publisher.SENDER_QOS: block, data priority), not imported:
# protocol imports no other package; tests check that the two agree.
REPLAY_QOS = LOSSLESS_QOS


class NoServer(RunLogError):
    """No render server subscribed to the run's chunks in time (the CLI exits 1, not 2)."""


@dataclass
class PublishSummary:
    run: str
    chunks: int = 0
    specs: int = 0
    wall_s: float = 0.0
    log_s: float = 0.0  # span of log time re-published, s


def republish(path: str | Path, session: zenoh.Session, rate: float = 1.0,
              run: str | None = None, wait_s: float = 10.0, stop: threading.Event | None = None,
              notes: list[LogNote] | None = None) -> PublishSummary:
    """Re-publish the run's recorded chunks and specs at the recorded pacing (log times
    divided by `rate`; 0: as fast as possible). Waits up to wait_s for a subscriber of the
    run's chunks (a render server) before the first chunk, NoServer if none comes. A
    truncated or damaged log is re-published up to its last complete chunk, noted in
    `notes`."""
    run = log_run(path, log_specs(path, notes), run, notes)
    stop = stop or threading.Event()
    summary = PublishSummary(run)
    start_wall = start_log = None
    matched = False
    topics = [keys.log_topic(run, keys.Topic.SPEC), keys.log_topic(run, keys.Topic.CHUNK)]
    for record in read_log_noting(path, notes, topics):
        if start_log is None:
            start_wall, start_log = time.monotonic(), record.log_ns
        if rate > 0:
            due = start_wall + (record.log_ns - start_log) * 1e-9 / rate
            if stop.wait(max(0.0, due - time.monotonic())):
                break
        if stop.is_set():
            break
        try:
            message = record.decode()  # validated as the server will
        except ProtocolError:
            continue
        if isinstance(message, Chunk):
            key = keys.chunk(run, message.step, message.rank)
            if not matched:
                matched = _wait_for_subscriber(session, key, wait_s)
                if not matched:
                    raise NoServer(f"no render server subscribes to {key} within {wait_s:g} s "
                                   f"(start `minority serve` with a spec of run {run!r})")
            put(session, key, bytearray(record.data), REPLAY_QOS)  # sent stamp renewed
            summary.chunks += 1
        else:
            put(session, keys.spec(run), message.encode(), CONTROL_QOS)
            summary.specs += 1
        summary.log_s = (record.log_ns - start_log) * 1e-9
    summary.wall_s = 0.0 if start_wall is None else time.monotonic() - start_wall
    if summary.chunks == 0 and not stop.is_set():
        raise RunLogError(f"{path}: no chunks of run {run!r} recorded")
    return summary


def _wait_for_subscriber(session: zenoh.Session, key: str, wait_s: float) -> bool:
    """Whether a subscriber of `key` is known within wait_s seconds (a matching listener)."""
    found = threading.Event()
    pub = session.declare_publisher(key, congestion_control=REPLAY_QOS.congestion,
                                    priority=REPLAY_QOS.priority)
    listener = pub.declare_matching_listener(lambda status: status.matching and found.set())
    try:
        return pub.matching_status.matching or found.wait(wait_s)
    finally:
        listener.undeclare()
        pub.undeclare()
