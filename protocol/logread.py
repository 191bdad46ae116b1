"""Reading MCAP logs written by protocol.log: through the summary's chunk index when the file
has one, front to back otherwise (a log whose writer was killed has no summary).

A complete log ends with a summary whose chunk indexes say which channels each MCAP chunk
holds, so a read of some topics opens only the chunks holding them (each whole, its CRC
checked, as the front-to-back read checks it). Messages come in file order either way.
mcap's own `SeekingReader.iter_messages` is not used for this: with `log_time_order=False`
it reads every matching chunk before yielding the first message (its insert-order queue
holds them all), and with `log_time_order=True` it reorders by log time, which is not the
arrival order when a clock stepped back.
"""

from __future__ import annotations

import fnmatch
import json
import os
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary

from minority.protocol.errors import ProtocolError
from minority.protocol.messages import Chunk as ChunkMessage
from minority.protocol.messages import Event, Frame, Stats, Timing, decode_as
from minority.protocol.shards import merge_by_log_time, shard_paths
from minority.protocol.spec import Spec

MCAP_MAGIC = b"\x89MCAP0\r\n"  # the first 8 bytes of every MCAP file
_BY_SCHEMA = {"minority.Chunk": ChunkMessage, "minority.Spec": Spec,
              "foxglove.CompressedImage": Frame, "minority.Timing": Timing,
              "minority.Event": Event, "minority.Stats": Stats}
_CHUNK_BODY = 1 + 8  # bytes from a chunk record's start to its body: opcode u8, length u64


@dataclass(frozen=True)
class LogRecord:
    topic: str
    log_ns: int
    publish_ns: int
    schema: str
    data: bytes  # as stored: wire payload for chunks, JSON for the rest

    def decode(self):
        """The message object (Chunk, Frame, Spec, Timing, Event, Stats)."""
        cls = _BY_SCHEMA.get(self.schema)
        if cls is None:
            raise ProtocolError(f"topic {self.topic!r} has schema {self.schema!r}, not a message")
        if cls is ChunkMessage:
            return decode_as(self.data, ChunkMessage)
        try:
            obj = json.loads(self.data)
        except (ValueError, RecursionError) as exc:  # bad UTF-8, JSON, huge integers, nesting
            raise ProtocolError(f"{self.topic}: stored JSON is invalid ({str(exc)[:200]})") from None
        return cls.from_json(obj, self.publish_ns)


class LogDamagedWarning(RuntimeWarning):
    """read_log stopped at a damaged record inside a log (not at a cut-short tail)."""


class LogTruncatedWarning(RuntimeWarning):
    """read_log reached the end of a log that has no MCAP footer: its writer was killed (or
    its disk filled) and the messages after its last complete chunk are not in the file."""


def read_log(path: str | Path, topics: Iterable[str] | None = None,
             start_ns: int | None = None, end_ns: int | None = None, *,
             use_index: bool = True) -> Iterator[LogRecord]:
    """Iterate stored messages in file order, filtered by topic (exact or glob, e.g.
    `minority/*/chunk`; see keys.log_topic) and log time (ns) in [start_ns, end_ns).

    A complete log is read through its chunk index: only the MCAP chunks that hold a wanted
    topic in the time range are read (`use_index` False: every record, front to back, as
    a log without a summary is read). A file cut short (a killed recorder) yields every
    message of its completed chunks, then stops with a LogTruncatedWarning; a damaged chunk
    (its CRC does not match) stops it too, with a LogDamagedWarning (read through the index,
    a damaged chunk holding no wanted topic is not read, so not seen). A file that is not
    MCAP raises ProtocolError. The log of a server on N render ranks is read with its shards
    (protocol.shards: `{stem}.render{k}{suffix}` next to it), merged by log time."""
    patterns = list(topics) if topics is not None else None
    shards = shard_paths(path)
    if shards:
        yield from merge_by_log_time(_read_file(p, patterns, start_ns, end_ns, use_index)
                                     for p in [Path(path), *shards])
        return
    yield from _read_file(path, patterns, start_ns, end_ns, use_index)


def _read_file(path: str | Path, patterns: list[str] | None, start_ns: int | None,
               end_ns: int | None, use_index: bool) -> Iterator[LogRecord]:
    """read_log of one file."""
    with open(path, "rb") as f:
        magic = f.read(len(MCAP_MAGIC))
        if len(magic) == len(MCAP_MAGIC) and magic != MCAP_MAGIC:
            raise ProtocolError(f"{path}: not an MCAP file (no MCAP magic at its start)")
        summary = _indexed_summary(f) if use_index else None
        f.seek(0)
        if summary is None:
            yield from _scan(f, path, patterns, start_ns, end_ns)
        else:
            yield from _indexed(f, path, summary, patterns, start_ns, end_ns)


def topic_counts(path: str | Path) -> dict[str, int] | None:
    """Messages per topic, from the summary's statistics without reading a message; None when
    the log (or one of its shards) has no summary or statistics (read it: read_log)."""
    counts: dict[str, int] = {}
    for part in [Path(path), *shard_paths(path)]:
        with open(part, "rb") as f:
            summary = _summary(f)
        if summary is None or summary.statistics is None:
            return None
        for channel_id, n in summary.statistics.channel_message_counts.items():
            channel = summary.channels.get(channel_id)
            if channel is not None:
                counts[channel.topic] = counts.get(channel.topic, 0) + n
    return counts


def _summary(f: BinaryIO) -> Summary | None:
    """The file's summary; None when it has none or it cannot be read (a cut-short file)."""
    try:
        f.seek(0)
        return SeekingReader(f).get_summary()
    except Exception:  # noqa: BLE001 - mcap raises its own types, struct.error, OSError on seek
        return None


def _indexed_summary(f: BinaryIO) -> Summary | None:
    """The summary when the chunk index covers the file's messages, else None (no summary;
    or no chunk index, as in an unchunked file: read front to back)."""
    summary = _summary(f)
    if summary is None or not summary.chunk_indexes:
        return None
    if summary.statistics is not None and summary.statistics.chunk_count != len(
            summary.chunk_indexes):
        return None  # an index that does not list every chunk: do not trust it
    return summary


def _matcher(patterns: list[str] | None):
    if patterns is None:
        return lambda topic: True
    return lambda topic: any(fnmatch.fnmatchcase(topic, p) for p in patterns)


def _indexed(f: BinaryIO, path, summary: Summary, patterns: list[str] | None,
             start_ns: int | None, end_ns: int | None) -> Iterator[LogRecord]:
    matches = _matcher(patterns)
    wanted = {cid for cid, c in summary.channels.items() if matches(c.topic)}
    if not wanted:
        return
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        if start_ns is not None and index.message_end_time < start_ns:
            continue
        if end_ns is not None and index.message_start_time >= end_ns:
            continue
        held = index.message_index_offsets
        if held and wanted.isdisjoint(held):
            continue  # the chunk's message indexes name no wanted channel
        try:
            f.seek(index.chunk_start_offset + _CHUNK_BODY)
            records = breakup_chunk(Chunk.read(ReadDataStream(f)), validate_crc=True)
        except Exception as exc:  # noqa: BLE001 - mcap, zstd and lz4 raise their own types
            warnings.warn(f"{path}: unreadable record (the MCAP chunk at byte "
                          f"{index.chunk_start_offset}: {exc}); the rest of the file is not "
                          "read", LogDamagedWarning, stacklevel=3)
            return
        for record in records:
            if isinstance(record, Message) and record.channel_id in wanted:
                found = _log_record(record, summary.channels, summary.schemas, start_ns, end_ns)
                if found is not None:
                    yield found


def _scan(f: BinaryIO, path, patterns: list[str] | None, start_ns: int | None,
          end_ns: int | None) -> Iterator[LogRecord]:
    """Every record front to back (CRCs checked), as a log without a summary is read."""
    matches = _matcher(patterns)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    wanted: dict[int, bool] = {}
    records = StreamReader(f, validate_crcs=True).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            warnings.warn(f"{path}: the log ends without its MCAP footer (its writer was "
                          "stopped); every message of its complete chunks was read",
                          LogTruncatedWarning, stacklevel=3)
            return
        except Exception as exc:  # noqa: BLE001 - mcap, zstd and lz4 raise their own types
            pos, size = f.tell(), os.fstat(f.fileno()).st_size
            if pos < size:  # not a cut-short tail: a damaged record inside the file
                warnings.warn(f"{path}: unreadable record before byte {pos} of {size} "
                              f"({exc}); the rest of the file is not read",
                              LogDamagedWarning, stacklevel=3)
            else:
                warnings.warn(f"{path}: the log is cut short at byte {size} (its writer "
                              "was killed); every message of its complete chunks was read",
                              LogTruncatedWarning, stacklevel=3)
            return
        if isinstance(record, Footer):
            return
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
            wanted[record.id] = matches(record.topic)
        elif isinstance(record, Message) and wanted.get(record.channel_id):
            found = _log_record(record, channels, schemas, start_ns, end_ns)
            if found is not None:
                yield found


def _log_record(message: Message, channels: dict[int, Channel], schemas: dict[int, Schema],
                start_ns: int | None, end_ns: int | None) -> LogRecord | None:
    """The LogRecord of a stored message, or None when its log time is outside
    [start_ns, end_ns)."""
    if (start_ns is not None and message.log_time < start_ns) or (
            end_ns is not None and message.log_time >= end_ns):
        return None
    channel = channels[message.channel_id]
    schema = schemas.get(channel.schema_id)
    return LogRecord(channel.topic, message.log_time, message.publish_time,
                     schema.name if schema else "", bytes(message.data))


# --- reading with the warnings kept as notes ------------------------------------------------
@dataclass(frozen=True)
class LogNote:
    """What read_log said of a log that does not end cleanly: "truncated" (no MCAP footer:
    its writer was killed or stopped) or "damaged" (an unreadable record inside). Either way
    the messages of its complete chunks before that point were read, and only those."""

    kind: str  # "truncated" or "damaged"
    detail: str  # read_log's warning, on one line

    def line(self) -> str:
        if self.kind == "damaged":
            return (f"log damaged: {self.detail}; only the messages of the complete chunks "
                    "before it were used")
        return f"log truncated: {self.detail}"


def read_log_noting(path: str | Path, notes: list[LogNote] | None,
                    topics: Iterable[str] | None = None) -> Iterator[LogRecord]:
    """read_log, with its LogTruncatedWarning or LogDamagedWarning added to `notes` (once
    per distinct note) instead of shown; any other warning passes on as it was. `notes`
    None: read_log itself, its warnings shown."""
    records = read_log(path, topics)
    if notes is None:
        yield from records
        return
    while True:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", LogTruncatedWarning)
            warnings.simplefilter("always", LogDamagedWarning)
            record = next(records, None)
        for w in caught:
            if issubclass(w.category, (LogTruncatedWarning, LogDamagedWarning)):
                kind = "damaged" if issubclass(w.category, LogDamagedWarning) else "truncated"
                note = LogNote(kind, " ".join(str(w.message).split()))
                if note not in notes:
                    notes.append(note)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno,
                                       source=w.source)
        if record is None:
            return
        yield record
