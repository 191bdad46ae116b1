"""What the render server keeps per run: a `RunInstance` is one run of a run id, from its
first message to its last rendered step, with its own assembler, rank bookkeeping,
counters, frame directory and MCAP log; `LogQueue` writes every instance's log on one
thread, in the order its messages were queued.

A run id may run again (a new `minority sim` with the same `--run` after the last one
ended, or after a server restart), and several servers may share one `--out`: each run
claims the first free frame directory `{run}`, `{run}.1`, ... and, apart from it, the
first free log `FILE`, `{stem}.1{suffix}`, ... (`--record FILE` is written as given while
FILE does not exist). A claim is atomic (mkdir, open O_EXCL), so two servers started at
the same instant take two names and nothing is overwritten.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from minority.protocol.log import LogWriter, numbered_log_path
from minority.render_server.assemble import StepAssembler
from minority.render_server.particles import ParticleCache

IDLE_FLUSH_S = 0.5  # an idle log queue completes its open MCAP chunks this often


@dataclass
class ServerStats:
    chunks: int = 0
    rejected: int = 0  # malformed chunks
    steps_rendered: int = 0
    frames: int = 0
    view_errors: int = 0  # views that could not be rendered (e.g. a missing field)
    write_errors: int = 0  # frames rendered and published whose PNG could not be written
    last_error: str = ""


def numbered_dir(out_dir: Path, run: str, k: int) -> Path:
    """The k-th name of a run's frame directory: `out_dir/run`, `out_dir/run.1`, ..."""
    return out_dir / (run if k == 0 else f"{run}.{k}")


def unclaimed_frames_dir(out_dir: Path, run: str) -> Path:
    """The first frame directory name of `run` that does not exist (not created)."""
    k = 0
    while (path := numbered_dir(out_dir, run, k)).exists():
        k += 1
    return path


def claim_frames_dir(out_dir: Path, run: str) -> Path:
    """Create and return the first free frame directory of `run` (mkdir: atomic, so a
    directory another server made a moment ago is never shared)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    k = 0
    while True:
        path = numbered_dir(out_dir, run, k)
        try:
            path.mkdir()
            return path
        except FileExistsError:
            k += 1


class RunInstance:
    """One run of a run id. Touched by the receive thread (assembly, ranks) and the render
    thread (frame counters); `finished` is set once its last step is rendered."""

    def __init__(self, seq: int, name: str, frames_dir: Path, writer: LogWriter | None,
                 assembler: StepAssembler):
        self.seq = seq  # 1, 2, ... per run id in this server
        self.name = name
        self.frames_dir = frames_dir
        self.writer = writer
        self.assembler = assembler
        self.cache = ParticleCache()  # particles outside the regions, by id
        self.stats = ServerStats()
        self.started_ns = time.time_ns()
        self.ranks_expected = 0  # from the chunks' rank count and the live tokens
        self.ranks_gone: set[int] = set()  # every member is below ranks_expected
        # a done event carries the rank's chunk count: the rank is gone once they all came
        # (the event travels at a higher priority than the chunks and may overtake them)
        self.chunks_sent: dict[int, int] = {}
        self.chunks_received: dict[int, int] = {}
        self.token_gone_ns: dict[int, int] = {}
        self.ranks_lost: set[int] = set()  # token vanished without a done event (killed)
        self.inbox_dropped_before = 0  # the server's inbox drops when this run opened
        self.queued_at_stop = 0  # chunks received but still queued when the server stopped
        self.log_error = ""  # why this run has no log although one was asked for
        self.drained = False  # every rank gone and every pending step released
        self.finished = threading.Event()

    def all_gone(self) -> bool:
        return self.ranks_expected > 0 and len(self.ranks_gone) >= self.ranks_expected

    def missing(self) -> dict[int, int]:
        """Chunks a rank's done event says it sent that were not assembled, per rank: dropped
        by a full inbox, still queued at a stop, or lost in transit."""
        return {r: n - self.chunks_received.get(r, 0) for r, n in sorted(self.chunks_sent.items())
                if n > self.chunks_received.get(r, 0)}


@dataclass
class _Item:
    writer: LogWriter
    key: str = ""
    payload: bytes = b""
    log_ns: int = 0
    message: object = None
    close: bool = False  # finish the writer's file (after every message queued before)


@dataclass
class LogQueue:
    """Messages for several logs, written on one thread in queue order. At most `capacity`
    messages and `max_bytes` of payload wait; past that a message is dropped and counted
    (`dropped`, per writer in `dropped_by`): logging never blocks receiving or rendering.
    A writer that fails stops at its last complete chunk (LogWriter.keep)."""

    capacity: int = 4096
    max_bytes: int = 1 << 30
    dropped: int = 0
    dropped_by: dict[Path, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._items: collections.deque[_Item] = collections.deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self._stop = False
        self._closed: set[Path] = set()  # writers whose close is queued
        self._thread = threading.Thread(target=self._loop, name="minority-log", daemon=True)
        self._thread.start()

    def put(self, writer: LogWriter | None, key: str, payload, log_ns: int,
            message=None) -> None:
        """Queue a message for `writer`; none for a writer already closed (the message came
        after its run ended: the caller publishes it only), and a full queue drops it,
        counted in `dropped`."""
        if writer is None:
            return
        with self._cond:
            if writer.path in self._closed:
                return
            if len(self._items) >= self.capacity or self._bytes + len(payload) > self.max_bytes:
                self.dropped += 1
                self.dropped_by[writer.path] = self.dropped_by.get(writer.path, 0) + 1
                return
            self._items.append(_Item(writer, key, bytes(payload), log_ns, message))
            self._bytes += len(payload)
            self._cond.notify()

    def close_writer(self, writer: LogWriter | None) -> None:
        """Finish the writer's file once the messages queued before this call are written."""
        if writer is not None:
            with self._cond:
                self._closed.add(writer.path)
                self._items.append(_Item(writer, close=True))
                self._cond.notify()

    def _loop(self) -> None:
        dirty: set[LogWriter] = set()  # written since their last flush
        while True:
            with self._cond:
                if not self._items and not self._stop:
                    self._cond.wait(IDLE_FLUSH_S)
                item = self._items.popleft() if self._items else None
                if item is not None:
                    self._bytes -= len(item.payload)
            if item is None:  # idle (or stopping): complete the open chunks on disk
                for writer in dirty:
                    writer.keep(writer.flush)
                dirty.clear()
                if self._stop:
                    return
            elif item.close:
                item.writer.finish()
                dirty.discard(item.writer)
            else:
                item.writer.keep(item.writer.write_payload, item.key, item.payload, item.log_ns,
                                 item.message)
                dirty.add(item.writer)

    def stop(self) -> None:
        """Write everything queued, then end the thread."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join()


def open_writer(record: Path, run: str, name: str) -> LogWriter:
    """A new log at the first free name of `record` (LogWriter opens O_EXCL: a file made
    by another server a moment ago is skipped, never overwritten)."""
    record.parent.mkdir(parents=True, exist_ok=True)
    k = 0
    while True:
        try:
            return LogWriter(numbered_log_path(record, k),
                             metadata={"run": run, "instance": name, "side": "server"})
        except FileExistsError:
            k += 1
