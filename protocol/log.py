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

A full disk ends a log cleanly: each chunk goes to disk in one write, after `fallocate` has
reserved its bytes and room for the summary past them (protocol.logfile.ReservedFile). A
write that fails (ENOSPC, or any error) ends the file at its last complete chunk and writes
the summary and footer there, into the reserved room (`repair.end_in_place`), so every MCAP
reader opens it;
the messages of the chunk that failed are counted in `unwritten`, never in `written`.
"""

from __future__ import annotations

import base64
import errno
import json
import os
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
from minority.protocol.logfile import ReservedFile
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
from minority.protocol.repair import end_in_place
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
_NEVER = 1 << 62  # bytes: the mcap Writer's own chunk limit; LogWriter closes its chunks itself
_RECORD_BYTES = 64  # bytes: a bound on a message record's framing inside a chunk (31 in MCAP 0)
# A bound on the summary `repair.end_in_place` writes (data end, schemas and channels again,
# statistics, chunk and metadata indexes, summary offsets, footer, magic), in bytes: a fixed
# part, each schema and channel record twice, per chunk index 128 and 16 per channel (its
# message index offset; the statistics' count), where the records themselves take 75 + 10.
_SUMMARY_FIXED_BYTES = 4096
_CHUNK_INDEX_BYTES = 128
_PER_CHANNEL_BYTES = 16


def numbered_log_path(path: Path, k: int) -> Path:
    """The k-th name of a log: `path`, then `{stem}.{k}{suffix}` (k = 1, 2, ...)."""
    return path if k == 0 else path.with_name(f"{path.stem}.{k}{path.suffix}")


def free_log_path(path: str | Path) -> Path:
    """`path` if no file is there, else the first free numbered_log_path: a log is never
    overwritten."""
    path = Path(path)
    k = 0
    while numbered_log_path(path, k).exists():
        k += 1
    return numbered_log_path(path, k)


class LogWriter:
    """Writes messages to an MCAP file with schemas and channel metadata.

    :param path: the log; it must not exist (FileExistsError; see free_log_path) unless
        `overwrite` is set.
    :param compression: of each chunk.
    :param flush_interval_s: a chunk is closed and written at least this often, s.
    :param chunk_bytes: a chunk is closed once its messages pass this size, bytes.
    :param metadata: key-value strings stored in the log's "minority" metadata record.
    :param overwrite: replace a file at `path`.

    The header, the metadata and the room the summary needs are written at once: a log that
    cannot start (a full disk) raises OSError naming the problem and leaves no file.
    `written` and `rejected` count the messages in the file or in its open chunk; a failed
    write moves the open chunk's to `unwritten` (see keep, finish).
    """

    def __init__(self, path: str | Path, *, compression: CompressionType = CompressionType.NONE,
                 flush_interval_s: float = 0.5, chunk_bytes: int = 4 << 20,
                 metadata: dict[str, str] | None = None, overwrite: bool = False):
        self.path = Path(path)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._record_bytes = 0   # bytes of the schema and channel records registered
        self._chunks = 0         # chunks written
        self._chunk_bytes = chunk_bytes
        self._open_bytes = 0     # bytes: a bound on the open chunk's size
        self._open_written = self._open_rejected = 0  # messages in the open chunk
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._lock = threading.Lock()
        self.written = 0
        self.rejected = 0
        self.failure = ""  # why the file ended early ("ENOSPC: ..."); "" while writing
        self.unwritten = 0  # messages not in the file: the open chunk's at a failure, and after
        self.ending = ""  # after a failure: how the file ends
        self._failure_errno: int | None = None
        self._complete = False  # closed with its summary, every message in it
        self._file = ReservedFile(self.path, overwrite, self._summary_bound)
        try:
            self._writer = Writer(self._file, chunk_size=_NEVER, compression=compression)
            self._writer.start(profile=PROFILE, library="minority")
            self._writer.add_metadata("minority", {"wire_format": WIRE_ENCODING,
                                                   "created_ns": str(time.time_ns()),
                                                   **(metadata or {})})
            self._writer.flush()  # on disk now, with the summary's room
        except BaseException as exc:
            self._file.close()
            self.path.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise OSError(exc.errno, f"cannot start the log {self.path}: "
                              f"{_describe(exc)}; no file left") from exc
            raise

    def _summary_bound(self) -> int:
        """Bytes the summary would take if the chunk being written were the last one."""
        return (_SUMMARY_FIXED_BYTES + 2 * self._record_bytes
                + (self._chunks + 1) * (_CHUNK_INDEX_BYTES + _PER_CHANNEL_BYTES * len(self._channels))
                + _PER_CHANNEL_BYTES * len(self._channels))

    def _channel(self, topic: str, schema_name: str, encoding: str, meta: dict[str, str]) -> int:
        if topic not in self._channels:
            if schema_name not in self._schemas:
                if schema_name == "minority.Chunk":
                    schema = WIRE_ENCODING, WIRE_SCHEMA.encode()
                else:
                    schema = "jsonschema", json.dumps(JSON_SCHEMAS[schema_name]).encode()
                self._record_bytes += 64 + len(schema_name) + len(schema[0]) + len(schema[1])
                self._schemas[schema_name] = self._writer.register_schema(schema_name, *schema)
            self._record_bytes += 64 + len(topic) + len(encoding) + sum(
                8 + len(k) + len(v) for k, v in meta.items())
            self._channels[topic] = self._writer.register_channel(
                topic, encoding, self._schemas[schema_name], meta)
        return self._channels[topic]

    def write_payload(self, key: str, payload: bytes, log_ns: int | None = None,
                      message=None) -> str:
        """Validate and log one received payload (`message`: its decoded form, when the
        caller has decoded it already); returns the topic it went to. A failed write ends
        the log (see keep) and raises OSError; so does any write after it."""
        log_ns = time.time_ns() if log_ns is None else log_ns
        if not 0 <= log_ns <= MAX_TIME_NS:
            raise ValueError(f"log time {log_ns} ns is outside [0, {MAX_TIME_NS}]")
        try:
            topic, schema, encoding, data, sent_ns, meta = self._prepare(key, payload, message)
        except ProtocolError as exc:
            return self._reject(key, payload, str(exc), log_ns)
        with self._lock:
            self._add(lambda: self._channel(topic, schema, encoding, meta), log_ns, data, sent_ns)
        return topic

    def write(self, message, key: str | None = None, log_ns: int | None = None) -> str:
        """Log a message object (in-process use); `key` defaults to its canonical key."""
        return self.write_payload(key or default_key(message), bytes(message.encode()), log_ns)

    def _prepare(self, key: str, payload: bytes, message=None):
        parsed = keys.parse(key)
        if parsed is None or parsed.topic not in _BY_TOPIC:
            raise ProtocolError(f"key {key!r:.120} is not a minority message key")
        cls = _BY_TOPIC[parsed.topic]
        # The payload's stamp is the message's sent time: a decoded form given without it
        # (a spec loaded from a file, sent_ns 0, whose payload was stamped at publish) is
        # decoded again from the payload, so publish_time is never 0 for a stamped payload.
        if type(message) is not cls or message.sent_ns != _stamp(payload):
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
        sent_ns = max(0, _stamp(payload))
        record = Rejected(str(key)[:1024], reason, len(payload),
                          base64.b64encode(payload).decode("ascii"))
        with self._lock:
            self._add(lambda: self._channel(REJECTED_TOPIC, "minority.Rejected", JSON_ENCODING,
                                            {"kind": "rejected"}),
                      log_ns, msgspec.json.encode(record), sent_ns, rejected=True)
        return REJECTED_TOPIC

    def _add(self, channel, log_ns: int, data: bytes, sent_ns: int, rejected: bool = False) -> None:
        """Add one message to the open chunk (lock held); write the chunk when it is full or
        due. A failure ends the log and is raised."""
        if self.failure:
            self.unwritten += 1
            raise self._ended()
        added = False
        try:
            self._writer.add_message(channel(), log_ns, data, sent_ns)
            added = True
            if rejected:
                self.rejected += 1
                self._open_rejected += 1
            else:
                self.written += 1
                self._open_written += 1
            self._open_bytes += len(data) + _RECORD_BYTES
            if (self._open_bytes > self._chunk_bytes
                    or time.monotonic() - self._last_flush >= self._flush_interval_s):
                self._flush_locked()
        except Exception as exc:
            self.unwritten += not added
            self._fail_locked(exc)
            raise

    def _flush_locked(self) -> None:
        self._writer.flush()  # closes the open chunk; ReservedFile writes it
        self._chunks += (self._open_written + self._open_rejected) > 0
        self._open_written = self._open_rejected = self._open_bytes = 0
        self._last_flush = time.monotonic()

    def flush(self) -> None:
        """Close the open MCAP chunk and write it. A failure ends the log and is raised."""
        with self._lock:
            if self.failure:
                raise self._ended()
            try:
                self._flush_locked()
            except Exception as exc:
                self._fail_locked(exc)
                raise

    def _ended(self) -> OSError:
        return OSError(self._failure_errno or errno.EIO,
                       f"{self.path}: the log has ended: {self.failure}")

    def _fail_locked(self, exc: BaseException) -> None:
        """End the log after a failure: the file is cut back to its last complete chunk and
        given its summary and footer in place (in the room reserved for them); the open
        chunk's messages move to `unwritten`. Says so once on stderr."""
        if self.failure:
            return
        self.failure = _describe(exc)
        self._failure_errno = exc.errno if isinstance(exc, OSError) else None
        self.written -= self._open_written
        self.rejected -= self._open_rejected
        self.unwritten += self._open_written + self._open_rejected
        self._open_written = self._open_rejected = self._open_bytes = 0
        if self._file.closed:
            return
        cut = self._file.committed
        try:
            kept = end_in_place(self._file.fd, cut)
            self.ending = (f"it ends at its last complete chunk (byte {cut}, {kept.messages} "
                           "messages) with its summary: MCAP readers open it")
        except Exception as end_exc:  # noqa: BLE001 - whatever stops it, the file ends at the cut
            try:
                os.ftruncate(self._file.fd, cut)
                self.ending = (f"it ends at its last complete chunk (byte {cut}) without its "
                               f"summary ({_describe(end_exc)}): readers that scan it read "
                               "it, `minority log repair` completes it")
            except OSError as cut_exc:
                self.ending = (f"it could not be cut back to its last complete chunk "
                               f"(byte {cut}): {_describe(cut_exc)}")
        finally:
            self._file.close()
        print(f"minority: cannot write {self.path}: {self.failure}; {self.ending}; "
              f"{self.unwritten} messages not written (later ones are counted too)",
              file=sys.stderr, flush=True)

    def close(self) -> None:
        """Write the open chunk, the summary and the footer, and close. Raises OSError if the
        log ended early or ends now (a full disk: the file ends at its last complete chunk,
        with its summary, as keep says)."""
        with self._lock:
            if self.failure:
                raise self._ended()
            if self._file.closed:
                return
            try:
                self._flush_locked()
                self._writer.finish()  # DataEnd, summary, footer: held by _LogFile until
                self._file.commit(keep_reserve=False)  # written into the reserved room
                self._file.release()
                self._file.close()
            except Exception as exc:
                self._fail_locked(exc)
                raise
            self._complete = True

    def keep(self, write, *args) -> bool:
        """Call one write method (write_payload, write, flush) for a long-running logger: the
        first failure (a full disk; or any unexpected error, after which the writer's state
        is unknown) ends the file at its last complete chunk with its summary, says so once
        on stderr, and counts the messages lost and every later one in `unwritten`. Returns
        whether it was written (into the open chunk, for a message)."""
        if self.failure:
            self.unwritten += write != self.flush
            return False
        try:
            write(*args)
            return True
        except Exception as exc:  # noqa: BLE001 - the logger outlives any one message
            with self._lock:
                if not self.failure:  # raised before the writer was reached
                    self.unwritten += write != self.flush
                    self._fail_locked(exc)
            return False

    def finish(self) -> bool:
        """Close, with the summary. True when every message given to the log is in the file
        and the file is complete; False after a failure, now or before (`failure` says why,
        `unwritten` counts the messages not in the file, stderr said so), or after abandon.
        Never raises for a failed write."""
        if not self.failure:
            try:
                self.close()
            except Exception:  # noqa: BLE001 - _fail_locked said it and set failure
                pass
        return self._complete

    def abandon(self) -> None:
        """Close the file as it is, without the MCAP summary (a killed writer's file: its
        complete chunks and nothing after them; the open chunk's messages are counted in
        `unwritten`). Nothing to do after a failure, which ended the file already."""
        with self._lock:
            if not self._file.closed:
                self.written -= self._open_written
                self.rejected -= self._open_rejected
                self.unwritten += self._open_written + self._open_rejected
                self._open_written = self._open_rejected = self._open_bytes = 0
                try:
                    self._file.release()
                except OSError:
                    pass  # the reserved room stays allocated past the file's end
                self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:  # the exception in flight says what went wrong
            self.finish()


def _describe(exc: BaseException) -> str:
    """`ENOSPC: No space left on device ...` for an OSError with an errno, else `Type: text`."""
    if isinstance(exc, OSError) and exc.errno in errno.errorcode:
        text = exc.strerror or str(exc)
        if exc.filename is not None:
            text = f"{text}: {exc.filename}"
        return f"{errno.errorcode[exc.errno]}: {text}"
    return f"{type(exc).__name__}: {exc}"


def _stamp(payload) -> int:
    """The sent time (ns) in a payload's prefix; 0 when it is too short to hold one."""
    if len(payload) < PREFIX_SIZE:
        return 0
    return struct.unpack_from("<q", payload, SENT_NS_OFFSET)[0]


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

    def close(self) -> bool:
        """Stop receiving, write what is queued, finish the file; whether every message
        received is in it (LogWriter.finish: False after a failed write)."""
        self._inbox.close()
        self._stop.set()
        self._thread.join()
        while (item := self._inbox.get(timeout=0)) is not None:
            self.writer.keep(self.writer.write_payload, item.key, item.payload, item.recv_ns)
        return self.writer.finish()
