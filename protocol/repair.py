"""Repair an MCAP log whose writer was killed: copy its readable prefix into a complete file.

A log cut short (a killed server or rank, a full disk) has no footer or summary, so seeking
readers (`mcap.reader.make_reader` on a file, Foxglove, the `mcap` CLI) refuse it. `repair`
reads the source front to back with mcap's StreamReader, CRCs validated, as `read_log` does,
stops at the first unreadable record (a cut-short tail or a damaged chunk), and writes every
record before it to a new, indexed MCAP: the same header, schemas, channels with their
metadata, messages (log_time, publish_time, sequence and data unchanged), metadata records
and attachments, in the source's chunks and compression. A chunk is kept whole or not at
all: its CRC is checked before any of its records is copied.

`end_in_place` does the same inside the file itself, for a writer that failed on a full disk
(protocol.log.LogWriter): the records before the cut stay as they are, and the data end,
summary and footer the copy would have are written after them.
"""

from __future__ import annotations

import enum
import io
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.reader import make_reader
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from minority.protocol.errors import ProtocolError
from minority.protocol.logread import MCAP_MAGIC

_COMPRESSION = {"": CompressionType.NONE, "lz4": CompressionType.LZ4,
                "zstd": CompressionType.ZSTD}
DEFAULT_COMPRESSION = CompressionType.NONE  # LogWriter's default, when the source shows none
_MIRROR_CHUNKS = 1 << 62  # bytes: the writer never closes a chunk itself; repair closes one
#                           where the source's ended, so the copy has the source's chunks
_LOOSE_CHUNK_BYTES = 4 << 20  # bytes: messages found outside any chunk of a chunked source
#                               are chunked by this size (LogWriter's chunk_bytes)


class LogState(enum.Enum):
    COMPLETE = "complete"    # read to its footer, every CRC valid, make_reader opens it
    TRUNCATED = "truncated"  # ends without its footer: the writer was killed mid-write
    DAMAGED = "damaged"      # an unreadable record (bad CRC, garbage) before the file's end


@dataclass(frozen=True)
class RepairResult:
    """What was read from a source log (and, for `repair`, written to its copy)."""

    state: LogState
    messages: int        # messages kept: every message before `stopped_at`
    stopped_at: int      # bytes: end of the last readable record (the file size if complete)
    size: int            # bytes: size of the source
    reason: str          # why reading stopped before the footer ("" when complete)
    schemas: int = 0
    channels: int = 0
    metadata: int = 0    # metadata records
    attachments: int = 0
    chunks: int = 0      # chunks kept
    skipped: int = 0     # messages on a channel the file never declared (read_log skips them too)
    compression: str = "none"  # the copy's: its source's first chunk's (none, lz4, zstd)
    chunked: bool = True       # the copy's: as its source (unknown: chunked)

    @property
    def lost_bytes(self) -> int:
        """Bytes of the source after its last readable record (0 if complete)."""
        return self.size - self.stopped_at


def is_complete(path: str | Path) -> bool:
    """Whether `path` starts with the MCAP magic and ends with a footer and summary that
    `mcap.reader.make_reader` reads (what Foxglove and the `mcap` CLI need). Checks no CRC
    inside the file: `scan` does."""
    with open(path, "rb") as f:
        try:
            make_reader(f).get_summary()  # checks the leading magic too
        except Exception:  # noqa: BLE001 - mcap raises its own types, struct.error, OSError on seek
            return False
    return True


def scan(src: str | Path) -> RepairResult:
    """Read `src` as `repair` would and say what it holds, writing nothing."""
    src = Path(src)
    with open(src, "rb") as f:
        _refuse_non_mcap(f, src)
        return _result(src, f, _Copy(None, *_layout(f)))


def repair(src: str | Path, dst: str | Path) -> RepairResult:
    """Write to `dst` a complete, indexed MCAP holding every readable record of `src`.

    Refuses (ProtocolError) a source that is not MCAP and (ValueError) `dst` naming the
    source file. Writes a temporary file beside `dst` and renames it into place, so `dst` is
    never a half file; an existing `dst` is replaced, a missing directory created. The copy
    gets the source's permission bits.
    """
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve() or (dst.exists() and src.exists() and os.path.samefile(src, dst)):
        raise ValueError(f"{dst}: the repaired copy must not replace its source {src}")
    with open(src, "rb") as f:
        _refuse_non_mcap(f, src)
        chunked, compression = _layout(f)
        dst.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=dst.parent, prefix=f".{dst.name}.", suffix=".part")
        try:
            with os.fdopen(fd, "wb") as out:
                writer = Writer(out, chunk_size=_MIRROR_CHUNKS, compression=compression,
                                use_chunking=chunked)
                copy = _Copy(writer, chunked, compression)
                result = _result(src, f, copy)
                copy.finish()
                out.flush()
                os.fsync(out.fileno())
            os.chmod(tmp, stat.S_IMODE(os.fstat(f.fileno()).st_mode))
            os.replace(tmp, dst)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return result


def end_in_place(fd: int, end: int) -> RepairResult:
    """Complete a log whose writer failed, in place: its first `end` bytes (the end of its
    last complete chunk) are kept as they are, and the data end, summary and footer that
    `repair` would write for them are written from `end`; the file is then cut after them.

    :param fd: the log, open for reading and writing (its offset is not used).
    :param end: bytes: where the readable records end; what follows is overwritten.

    Nothing before `end` is written: the copy `repair` makes of those records is compared
    with them byte for byte, and a difference (or an unreadable record before `end`) raises
    ProtocolError with the file unchanged. CRCs are not checked on the way in: a record
    damaged since it was written makes the copy differ (its CRC is computed anew), which the
    comparison refuses. It reads the whole file: about 0.7 s per 100 MB on a loaded 2-core
    machine. Needs room for the summary from `end` on (the
    writer reserves it); a failed write raises OSError, the file then holds complete records
    up to `end` and part of the summary after them.
    """
    source = io.BufferedReader(_Prefix(fd, end), buffer_size=1 << 20)
    chunked, compression = _layout(source)
    out = _InPlace(fd, end)
    copy = _Copy(Writer(out, chunk_size=_MIRROR_CHUNKS, compression=compression,
                        use_chunking=chunked), chunked, compression)
    state, stopped_at, reason = _read(source, copy, end, validate=False)
    if state is not LogState.TRUNCATED or stopped_at != end:
        raise ProtocolError(f"the log's records are not whole up to byte {end}: "
                            f"{reason or 'it has a footer'} (at byte {stopped_at})")
    copy.finish()
    os.ftruncate(fd, out.pos)
    return _summary(state, stopped_at, end, reason, copy)


class _Prefix(io.RawIOBase):
    """The first `size` bytes of an open file, read with pread (the file's offset is left)."""

    def __init__(self, fd: int, size: int):
        self.fd, self.size, self.pos = fd, size, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        n = min(len(buffer), self.size - self.pos)
        data = os.pread(self.fd, n, self.pos) if n > 0 else b""
        buffer[:len(data)] = data
        self.pos += len(data)
        return len(data)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self.pos = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence] + offset
        return self.pos

    def tell(self) -> int:
        return self.pos


class _InPlace:
    """An output stream for mcap's Writer over the file it reads: the bytes it writes before
    `end` must be the file's own (checked, not written), the rest is written."""

    def __init__(self, fd: int, end: int):
        self.fd, self.end, self.pos = fd, end, 0

    def write(self, data) -> int:
        view = memoryview(data)
        same = max(0, min(len(view), self.end - self.pos))
        # compared as bytes (memcmp): a memoryview compares item by item, 4x slower in all
        ours = data if same == len(view) and isinstance(data, bytes) else bytes(view[:same])
        if same and os.pread(self.fd, same, self.pos) != ours:
            raise ProtocolError(f"the copy of the log's records differs from them in bytes "
                                f"{self.pos}-{self.pos + same}: nothing was written")
        at, rest = self.pos + same, view[same:]
        while rest:
            n = os.pwrite(self.fd, rest, at)
            at, rest = at + n, rest[n:]
        self.pos += len(view)
        return len(view)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass


def _refuse_non_mcap(f: BinaryIO, path: Path) -> None:
    """A file that does not start with the MCAP magic is refused; one that is shorter than the
    magic and agrees with it (a writer killed at once) reads as a truncated, empty log."""
    head = f.read(len(MCAP_MAGIC))
    f.seek(0)
    if not MCAP_MAGIC.startswith(head):
        raise ProtocolError(f"{path}: not an MCAP file (no MCAP magic at its start)")


def _layout(f: BinaryIO) -> tuple[bool, CompressionType]:
    """Chunked or not, and the compression of the source's first chunk (the writer is made
    before the main pass reaches it). Unknown (no chunk or message readable): chunked, with
    DEFAULT_COMPRESSION."""
    try:
        for record in StreamReader(f, emit_chunks=True).records:
            if isinstance(record, Chunk):
                return True, _COMPRESSION.get(record.compression, DEFAULT_COMPRESSION)
            if isinstance(record, Message):
                return False, CompressionType.NONE
            if isinstance(record, DataEnd):
                break
    except OSError:
        raise
    except Exception:  # noqa: BLE001 - the main pass says what is unreadable, and where
        pass
    finally:
        f.seek(0)
    return True, DEFAULT_COMPRESSION


class _Copy:
    """Carries records of the source into a Writer (or only counts them: writer None).

    Source schema and channel ids are mapped to the writer's own; a record repeated with an
    id already seen (other writers repeat schemas and channels in every chunk) is skipped.
    """

    def __init__(self, writer: Writer | None, chunked: bool, compression: CompressionType):
        self.writer = writer
        self.chunked, self.compression = chunked, compression
        self.profile = self.library = ""
        self.started = False
        self.schema_ids: dict[int, int] = {0: 0}  # source id -> written id (0: no schema)
        self.channel_ids: dict[int, int] = {}
        self.messages = self.metadata = self.attachments = self.chunks = self.skipped = 0
        self._loose_bytes = 0  # bytes of messages outside any chunk since the copy's last one

    def _start(self) -> None:
        if not self.started and self.writer is not None:
            self.writer.start(profile=self.profile, library=self.library)
        self.started = True

    def header(self, record: Header) -> None:
        self.profile, self.library = record.profile, record.library
        self._start()

    def chunk(self, records: list[McapRecord]) -> None:
        """The records of one source chunk, already checked whole."""
        self.chunks += 1
        for record in records:
            self.add(record)
        if self.writer is not None:
            self.writer.flush()  # close the copy's chunk where the source's closed
        self._loose_bytes = 0

    def loose(self, record: McapRecord) -> None:
        """A record outside any chunk."""
        self.add(record)
        if isinstance(record, Message) and self.chunked and self.writer is not None:
            self._loose_bytes += len(record.data)
            if self._loose_bytes > _LOOSE_CHUNK_BYTES:
                self.writer.flush()
                self._loose_bytes = 0

    def add(self, record: McapRecord) -> None:
        self._start()
        w = self.writer
        if isinstance(record, Schema):
            if record.id not in self.schema_ids:
                self.schema_ids[record.id] = (len(self.schema_ids) if w is None else
                                              w.register_schema(record.name, record.encoding,
                                                                record.data))
        elif isinstance(record, Channel):
            if record.id not in self.channel_ids:
                schema_id = self.schema_ids.get(record.schema_id, 0)  # never declared: none
                self.channel_ids[record.id] = (len(self.channel_ids) + 1 if w is None else
                                               w.register_channel(record.topic,
                                                                  record.message_encoding,
                                                                  schema_id, record.metadata))
        elif isinstance(record, Message):
            channel_id = self.channel_ids.get(record.channel_id)
            if channel_id is None:
                self.skipped += 1
                return
            self.messages += 1
            if w is not None:
                w.add_message(channel_id, record.log_time, record.data, record.publish_time,
                              record.sequence)
        elif isinstance(record, Metadata):
            self.metadata += 1
            if w is not None:
                w.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            self.attachments += 1
            if w is not None:
                w.add_attachment(record.create_time, record.log_time, record.name,
                                 record.media_type, record.data)
        # the rest (indexes, statistics, summary offsets) the writer makes anew

    def finish(self) -> None:
        self._start()  # a source cut inside its header: the copy has an empty one
        if self.writer is not None:
            self.writer.finish()


def _read(f: BinaryIO, copy: _Copy, size: int | None = None,
          validate: bool = True) -> tuple[LogState, int, str]:
    """Feed `copy` every record of `f` up to its footer or its first unreadable record; the
    state, the end of the last record read whole (bytes) and why reading stopped. `size`:
    of `f` in bytes (its file's size when None); `validate`: check the CRCs."""
    size = os.fstat(f.fileno()).st_size if size is None else size
    records = StreamReader(f, emit_chunks=True, validate_crcs=validate).records
    stopped_at = 0
    in_summary = False  # past DataEnd: the summary repeats schemas and channels, then indexes
    while True:
        try:
            record = next(records)
        except StopIteration:  # the footer and the closing magic were read
            return LogState.COMPLETE, f.tell(), ""
        except OSError:
            raise  # the disk failed, not the file: say so rather than call the file damaged
        except Exception as exc:  # noqa: BLE001 - mcap, struct, zstd and lz4 raise their own types
            if f.tell() < size:
                return LogState.DAMAGED, stopped_at, f"unreadable record: {_text(exc)}"
            if stopped_at == size:
                return LogState.TRUNCATED, stopped_at, "the file ends without its MCAP footer"
            return LogState.TRUNCATED, stopped_at, "the file ends inside a record"
        if isinstance(record, Chunk):
            try:  # a chunk is checked whole (CRC, decompression, its records) before any is copied
                inner = breakup_chunk(record, validate_crc=validate)
            except Exception as exc:  # noqa: BLE001 - as above
                return LogState.DAMAGED, stopped_at, f"damaged chunk: {_text(exc)}"
            copy.chunk(inner)
        elif isinstance(record, Header):
            copy.header(record)
        elif isinstance(record, DataEnd):
            in_summary = True
        elif not in_summary:
            copy.loose(record)
        stopped_at = f.tell()


def _text(exc: Exception) -> str:
    return str(exc) or type(exc).__name__


def _result(path: Path, f: BinaryIO, copy: _Copy) -> RepairResult:
    state, stopped_at, reason = _read(f, copy)
    if state is LogState.COMPLETE and not is_complete(path):
        state = LogState.DAMAGED
        reason = "its footer or summary section is unreadable (make_reader refuses it)"
    return _summary(state, stopped_at, os.fstat(f.fileno()).st_size, reason, copy)


def _summary(state: LogState, stopped_at: int, size: int, reason: str, copy: _Copy) -> RepairResult:
    return RepairResult(state=state, messages=copy.messages, stopped_at=stopped_at,
                        size=size, reason=reason,
                        schemas=len(copy.schema_ids) - 1, channels=len(copy.channel_ids),
                        metadata=copy.metadata, attachments=copy.attachments,
                        chunks=copy.chunks, skipped=copy.skipped,
                        compression=copy.compression.name.lower(), chunked=copy.chunked)
