"""MCAP logging: a writer usable in any process and the `minority record` recorder (the reader
is protocol.logread; its names are importable from here too).

Topics are per run and kind (`minority/{run}/chunk`, `.../frame/{view}`, `.../timing`, ...);
step and rank live in each chunk's payload. Chunks are stored byte-for-byte as received
(message encoding `minority-wire-v1`); spec, frame, timing and event are stored as JSON
with a JSON Schema (frames as `foxglove.CompressedImage`, so MCAP viewers show the image).
Malformed messages go to `minority/_rejected` with the reason, never to a data topic.
log_time is the arrival time and publish_time the sender's stamp, both ns since the epoch.
The writer closes an MCAP chunk at least every `flush_interval_s`, so a recorder killed
with SIGKILL leaves a file whose completed chunks the reader still returns.
"""

from __future__ import annotations

import base64
import json
import struct
import sys
import threading
import time
from pathlib import Path

import msgspec
import zenoh
from mcap.writer import CompressionType, Writer
from minority.protocol import keys
from minority.protocol.errors import ProtocolError
from minority.protocol.logread import (  # noqa: F401 - the reader's names, importable from here
    MCAP_MAGIC,
    LogDamagedWarning,
    LogNote,
    LogRecord,
    LogTruncatedWarning,
    read_log,
    read_log_noting,
    topic_counts,
)
from minority.protocol.messages import Chunk, Event, Frame, Stats, Timing, decode_as
from minority.protocol.schemas import JSON_SCHEMAS, WIRE_ENCODING, WIRE_SCHEMA, Rejected
from minority.protocol.session import Inbox
from minority.protocol.spec import Spec
from minority.protocol.wire import PREFIX_SIZE, SENT_NS_OFFSET

PROFILE = "minority"
REJECTED_TOPIC = keys.REJECTED_LOG_TOPIC
JSON_ENCODING = "json"
_BY_TOPIC = {keys.Topic.CHUNK: Chunk, keys.Topic.SPEC: Spec, keys.Topic.FRAME: Frame,
             keys.Topic.TIMING: Timing, keys.Topic.EVENT: Event, keys.Topic.STATS: Stats}


MAX_TIME_NS = (1 << 63) - 1  # log and publish times are u64 in MCAP; ours are non-negative i64


def free_log_path(path: str | Path) -> Path:
    """`path` if no file is there, else the first free `{stem}.{k}{suffix}` (k = 1, 2, ...):
    a log is never overwritten."""
    path = Path(path)
    k = 0
    while True:
        candidate = path if k == 0 else path.with_name(f"{path.stem}.{k}{path.suffix}")
        if not candidate.exists():
            return candidate
        k += 1


class LogWriter:
    """Writes messages to an MCAP file with schemas and channel metadata. The file must not
    exist (FileExistsError otherwise; see free_log_path) unless `overwrite` is set."""

    def __init__(self, path: str | Path, *, compression: CompressionType = CompressionType.NONE,
                 flush_interval_s: float = 0.5, chunk_bytes: int = 4 << 20,
                 metadata: dict[str, str] | None = None, overwrite: bool = False):
        self.path = Path(path)
        self._file = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115 (see close())
        self._writer = Writer(self._file, chunk_size=chunk_bytes, compression=compression)
        self._writer.start(profile=PROFILE, library="minority")
        self._writer.add_metadata("minority", {"wire_format": WIRE_ENCODING,
                                               "created_ns": str(time.time_ns()),
                                               **(metadata or {})})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._lock = threading.Lock()
        self.written = 0
        self.rejected = 0
        self.failure = ""  # why the file ended early (a failed write); "" while writing
        self.unwritten = 0  # messages not written: the failed one and all after it

    def _channel(self, topic: str, schema_name: str, encoding: str, meta: dict[str, str]) -> int:
        if topic not in self._channels:
            if schema_name not in self._schemas:
                if schema_name == "minority.Chunk":
                    self._schemas[schema_name] = self._writer.register_schema(
                        schema_name, WIRE_ENCODING, WIRE_SCHEMA.encode())
                else:
                    self._schemas[schema_name] = self._writer.register_schema(
                        schema_name, "jsonschema", json.dumps(JSON_SCHEMAS[schema_name]).encode())
            self._channels[topic] = self._writer.register_channel(
                topic, encoding, self._schemas[schema_name], meta)
        return self._channels[topic]

    def write_payload(self, key: str, payload: bytes, log_ns: int | None = None,
                      message=None) -> str:
        """Validate and log one received payload (`message`: its decoded form, when the
        caller has decoded it already); returns the topic it went to."""
        log_ns = time.time_ns() if log_ns is None else log_ns
        if not 0 <= log_ns <= MAX_TIME_NS:
            raise ValueError(f"log time {log_ns} ns is outside [0, {MAX_TIME_NS}]")
        try:
            topic, schema, encoding, data, sent_ns, meta = self._prepare(key, payload, message)
        except ProtocolError as exc:
            return self._reject(key, payload, str(exc), log_ns)
        with self._lock:
            self._writer.add_message(self._channel(topic, schema, encoding, meta), log_ns, data,
                                     sent_ns)
            self.written += 1
            self._maybe_flush()
        return topic

    def write(self, message, key: str | None = None, log_ns: int | None = None) -> str:
        """Log a message object (in-process use); `key` defaults to its canonical key."""
        return self.write_payload(key or default_key(message), bytes(message.encode()), log_ns)

    def _prepare(self, key: str, payload: bytes, message=None):
        parsed = keys.parse(key)
        if parsed is None or parsed.topic not in _BY_TOPIC:
            raise ProtocolError(f"key {key!r:.120} is not a minority message key")
        cls = _BY_TOPIC[parsed.topic]
        if type(message) is not cls:
            message = decode_as(payload, cls)
        if not 0 <= message.sent_ns <= MAX_TIME_NS:  # decoders refuse these; never trust it
            raise ProtocolError(f"sent time {message.sent_ns} ns is outside [0, {MAX_TIME_NS}]")
        if message.run != parsed.run:
            raise ProtocolError(f"payload run {message.run!r} does not match key run {parsed.run!r}")
        meta = {"run": parsed.run, "kind": parsed.topic, "key_expr": keys.everything(parsed.run)}
        if cls is Chunk:
            return parsed.log_topic, "minority.Chunk", WIRE_ENCODING, payload, message.sent_ns, meta
        schema = "foxglove.CompressedImage" if cls is Frame else f"minority.{cls.__name__}"
        data = json.dumps(message.to_json(), separators=(",", ":")).encode()
        return parsed.log_topic, schema, JSON_ENCODING, data, message.sent_ns, meta

    def _reject(self, key: str, payload: bytes, reason: str, log_ns: int) -> str:
        sent_ns = 0
        if len(payload) >= PREFIX_SIZE:
            sent_ns = max(0, struct.unpack_from("<q", payload, SENT_NS_OFFSET)[0])
        record = Rejected(str(key)[:1024], reason, len(payload),
                          base64.b64encode(payload).decode("ascii"))
        with self._lock:
            channel = self._channel(REJECTED_TOPIC, "minority.Rejected", JSON_ENCODING,
                                    {"kind": "rejected"})
            self._writer.add_message(channel, log_ns, msgspec.json.encode(record), sent_ns)
            self.rejected += 1
            self._maybe_flush()
        return REJECTED_TOPIC

    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self._flush_interval_s:
            self._flush_locked()

    def _flush_locked(self) -> None:
        self._writer.flush()
        self._last_flush = time.monotonic()

    def flush(self) -> None:
        """Close the open MCAP chunk and push it to the OS."""
        with self._lock:
            self._flush_locked()

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._writer.finish()
                self._file.close()

    def keep(self, write, *args) -> bool:
        """Call one write method (write_payload, write, flush) for a long-running logger: the
        first failure (a full disk; or any unexpected error, after which the writer's state
        is unknown) ends the file at its last complete chunk, says so once on stderr, and
        every later message is counted in `unwritten`. Returns whether it was written."""
        if self.failure:
            self.unwritten += write != self.flush
            return False
        try:
            write(*args)
            return True
        except Exception as exc:  # noqa: BLE001 - the logger outlives any one message
            self.failure = f"{type(exc).__name__}: {exc}"
            self.unwritten += write != self.flush
            print(f"minority: cannot write {self.path}: {self.failure}; the log ends here (its "
                  "complete chunks stay readable), later messages are counted as not written",
                  file=sys.stderr, flush=True)
            return False

    def finish(self) -> None:
        """Close: with the MCAP summary, or as it is after a failure (see abandon)."""
        if not self.failure:
            try:
                self.close()
                return
            except Exception as exc:  # noqa: BLE001
                self.failure = f"{type(exc).__name__}: {exc}"
        self.abandon()

    def abandon(self) -> None:
        """Close the file as it is, without the MCAP summary (after a failed write: the file
        reads like a cut-short one, its complete chunks and nothing after them)."""
        with self._lock:
            if not self._file.closed:
                try:
                    self._file.close()
                except OSError:
                    pass  # the buffered tail could not be written either: it is lost

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def default_key(message) -> str:
    if isinstance(message, Chunk):
        return keys.chunk(message.run, message.step, message.rank)
    if isinstance(message, Frame):
        return keys.frame(message.run, message.view)
    return {Spec: keys.spec, Timing: keys.timing, Event: keys.event,
            Stats: keys.stats}[type(message)](message.run)


class Recorder:
    """Subscribes to `minority/{run}/**` and writes every message to MCAP on its own thread.

    Usable inside other processes (pass their session). Memory is bounded by `capacity`
    queued messages; overflow is counted in `dropped`, never blocks zenoh.
    """

    def __init__(self, session: zenoh.Session, path: str | Path, run: str = keys.ALL_RUNS,
                 capacity: int = 256, **writer_options):
        self.writer = LogWriter(path, metadata={"run": run}, **writer_options)
        self._inbox = Inbox(session, keys.everything(run), capacity)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="minority-recorder", daemon=True)
        self._thread.start()

    @property
    def received(self) -> int:
        return self._inbox.received

    @property
    def dropped(self) -> int:
        return self._inbox.dropped

    @property
    def written(self) -> int:
        return self.writer.written + self.writer.rejected

    @property
    def write_errors(self) -> int:
        return self.writer.unwritten

    def _loop(self) -> None:
        while not self._stop.is_set():
            item = self._inbox.get(timeout=0.1)
            if item is None:
                self.writer.keep(self.writer.flush)
            else:
                self.writer.keep(self.writer.write_payload, item.key, item.payload, item.recv_ns)

    def close(self) -> None:
        """Stop receiving, write what is queued, finish the file."""
        self._inbox.close()
        self._stop.set()
        self._thread.join()
        while (item := self._inbox.get(timeout=0)) is not None:
            self.writer.keep(self.writer.write_payload, item.key, item.payload, item.recv_ns)
        self.writer.finish()
