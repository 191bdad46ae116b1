"""The bounded queue between a rank's simulation thread and its sender thread
(insitu.publisher, insitu.sender): chunks, Stats messages and control messages (spec,
events), each kind bounded on its own so that a slow server drops the oldest data, never
blocks the simulation.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

OUTBOX_CHUNKS = 4  # chunks queued for the sender at most (the oldest is dropped)
OUTBOX_BYTES = 256 * 1024 * 1024  # and at most this many bytes of them
OUTBOX_STATS = 64  # Stats messages queued for the sender at most (the oldest is dropped)

CHUNK, STATS, CONTROL = "chunk", "stats", "control"  # kinds of outbox items


@dataclass
class OutboxItem:
    key: str
    payload: bytearray | None  # None until `build` made it (on the sender thread)
    kind: str  # CHUNK, STATS or CONTROL (spec, events)
    particles: int = 0
    publish: bool = True  # False: only recorded (the spec the rank follows)
    # culls and encodes the payload from a snapshot of the caller's arrays: (payload,
    # particles); `nbytes` counts the snapshot meanwhile
    build: Callable[[], tuple[bytearray, int]] | None = None
    nbytes: int = 0
    # a lent step's item: called once when it no longer reads the caller's arrays (built,
    # dropped or discarded; insitu.lend)
    release: Callable[[], None] | None = None

    def released(self) -> None:
        if self.release is not None:
            self.release()
            self.release = None

    @property
    def size(self) -> int:
        """Bytes the item holds: its payload, or the snapshot it is built from."""
        return len(self.payload) if self.payload is not None else self.nbytes


class Outbox:
    """A bounded FIFO between the simulation thread and the sender: at most `max_chunks`
    chunks and `max_bytes` of chunk payload (but always the newest chunk), and at most
    `max_stats` Stats messages; an item that overflows them drops the oldest of its kind.
    The publisher asks `full` first and refuses a new chunk or Stats message itself while
    the sender is behind, so a stopped server costs the caller no copy. Chunk and Stats
    items hold a snapshot and a `build` the sender runs (cull, encode) when it takes them.
    Control messages (spec, events) are few and small and always enter."""

    def __init__(self, max_chunks: int, max_bytes: int, max_stats: int = OUTBOX_STATS):
        self.max_chunks, self.max_bytes, self.max_stats = max_chunks, max_bytes, max_stats
        self._items: collections.deque[OutboxItem] = collections.deque()
        self._cond = threading.Condition()
        self._chunks = 0
        self._bytes = 0
        self._stats = 0
        self.busy = False  # the sender holds an item

    def put(self, item: OutboxItem) -> int:
        """Enqueue; returns how many items of its kind were dropped to make room."""
        dropped = 0
        with self._cond:
            if item.kind == CHUNK:
                while self._chunks and (self._chunks >= self.max_chunks
                                        or self._bytes + item.size > self.max_bytes):
                    self._drop_oldest(CHUNK)
                    dropped += 1
                self._chunks += 1
                self._bytes += item.size
            elif item.kind == STATS:
                while self._stats and self._stats >= self.max_stats:
                    self._drop_oldest(STATS)
                    dropped += 1
                self._stats += 1
            self._items.append(item)
            self._cond.notify()
        return dropped

    def full(self, kind: str) -> bool:
        """Whether an item of `kind` (CHUNK or STATS) would push an older one out: the
        sender is behind (a slow or stopped server, a slow disk)."""
        with self._cond:
            return (self._chunks >= self.max_chunks if kind == CHUNK
                    else kind == STATS and self._stats >= self.max_stats)

    def _count(self, item: OutboxItem, sign: int) -> None:
        if item.kind == CHUNK:
            self._chunks += sign
            self._bytes += sign * item.size
        elif item.kind == STATS:
            self._stats += sign

    def _drop_oldest(self, kind: str) -> None:
        for i, old in enumerate(self._items):
            if old.kind == kind:
                del self._items[i]
                self._count(old, -1)
                old.released()
                return

    def take(self, timeout: float) -> OutboxItem | None:
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            if not self._items:
                return None
            item = self._items.popleft()
            self._count(item, -1)
            self.busy = True
            return item

    def done(self) -> None:
        with self._cond:
            self.busy = False
            self._cond.notify_all()

    def wait_empty(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._items or self.busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def discard_chunks(self) -> tuple[int, int]:
        """Drop every queued chunk and Stats message; returns how many of each."""
        with self._cond:
            n = (self._chunks, self._stats)
            for item in self._items:
                item.released()
            self._items = collections.deque(i for i in self._items if i.kind == CONTROL)
            self._chunks = self._bytes = self._stats = 0
            return n
