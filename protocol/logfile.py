"""A log's file that always ends at a complete unit and keeps room for its summary:
`ReservedFile` is the mcap Writer's output stream for protocol.log.LogWriter (used there
only; apart so the writer's module stays about the messages)."""

from __future__ import annotations

import ctypes
import errno
import functools
import io
import os
import sys
from pathlib import Path

_IOV_MAX = 1024  # buffers one pwritev takes (Linux's UIO_MAXIOV)
_FALLOC_FL_KEEP_SIZE = 0x01  # linux/falloc.h: allocate blocks, leave the file's size
_RESERVE_STEP_BYTES = 1 << 20  # bytes: blocks are reserved in steps this long (ext4, given
#   a few kB per call, scattered a 320 kB log over 27 extents); a killed writer leaves at
#   most this and the summary's room allocated past its file's end


@functools.cache
def _fallocate():
    """libc's fallocate(2) (Linux only; None elsewhere): os has posix_fallocate, which
    cannot keep the file's size."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        call = getattr(libc, "fallocate64", None) or libc.fallocate
    except (OSError, AttributeError):
        return None
    call.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
    call.restype = ctypes.c_int
    return call


class ReservedFile:
    """The log's file as the mcap Writer's output stream. What the Writer writes is held
    until it flushes (a chunk with its message indexes, the header, the summary) and then
    written at once, so the file always ends at a complete unit: `committed` bytes.

    Before each write, `fallocate(FALLOC_FL_KEEP_SIZE)` allocates the blocks for it and for
    `reserve()` bytes past it: the room the summary needs if the next write fails. KEEP_SIZE
    leaves the file's size that of its data (a reader of the live file sees no padding); the
    room is in this file, so nothing else on the disk can take it, and truncating the file
    at its end releases what the summary did not use. Where fallocate is not supported
    (`reserving` False) the summary gets whatever room the failed write leaves.
    """

    def __init__(self, path: Path, overwrite: bool, reserve):
        self.raw = io.FileIO(path, "w+" if overwrite else "x+")
        self.fd = self.raw.fileno()
        self.committed = 0      # bytes: on disk, whole units
        self.reserved_to = 0    # bytes: blocks allocated up to here
        self.reserving = _fallocate() is not None
        self._reserve = reserve  # () -> bytes to keep allocated past the data
        self._pending: list[bytes] = []
        self._pending_bytes = 0

    @property
    def closed(self) -> bool:
        return self.raw.closed

    def write(self, data) -> int:
        self._pending.append(bytes(data))
        self._pending_bytes += len(data)
        return len(data)

    def tell(self) -> int:
        return self.committed + self._pending_bytes

    def flush(self) -> None:
        self.commit()

    def commit(self, keep_reserve: bool = True) -> None:
        """Write what the Writer has written since the last commit, with the room for the
        summary past it allocated first (`keep_reserve`; the summary itself needs none).
        Raises OSError (ENOSPC when that room cannot be allocated: nothing is written)."""
        if not self._pending:
            return
        views, size = [memoryview(b) for b in self._pending], self._pending_bytes
        self._pending.clear()
        self._pending_bytes = 0
        self._allocate(self.committed + size + (self._reserve() if keep_reserve else 0))
        at = self.committed
        while views:  # pwritev: no joined copy (it cost 20 % of a 1 MB message's write)
            n = os.pwritev(self.fd, views[:_IOV_MAX], at)
            at += n
            while views and n >= len(views[0]):
                n -= len(views.pop(0))
            if n:
                views[0] = views[0][n:]
        self.committed = at

    def _allocate(self, end: int) -> None:
        """Blocks up to `end` at least: up to the next multiple of _RESERVE_STEP_BYTES, or
        exactly to `end` when there is no room for that."""
        if not self.reserving or end <= self.reserved_to:
            return
        for to in (-(-end // _RESERVE_STEP_BYTES) * _RESERVE_STEP_BYTES, end):
            if _fallocate()(self.fd, _FALLOC_FL_KEEP_SIZE, self.reserved_to,
                            to - self.reserved_to) == 0:
                self.reserved_to = to
                return
            code = ctypes.get_errno()
            if code in (errno.EOPNOTSUPP, errno.ENOSYS):
                self.reserving = False
                return
        raise OSError(code, f"{os.strerror(code)} (reserving {end - self.committed} bytes "
                      f"past byte {self.committed}: the next chunk and room for the summary)")

    def release(self) -> None:
        """Cut the file to its committed bytes: frees what is reserved past them."""
        self._pending.clear()
        self._pending_bytes = 0
        os.ftruncate(self.fd, self.committed)
        self.reserved_to = self.committed

    def close(self) -> None:
        self.raw.close()
