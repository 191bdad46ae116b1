"""A render rank k > 0 of the server on N ranks (render_server.serve_mpi): it receives its
sim ranks' chunks, logs them to its shard, reports them to rank 0, renders its share of the
steps rank 0 names, and ends the job if rank 0 falls silent.
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import time

from minority.protocol.errors import ProtocolError
from minority.protocol.log import LogWriter
from minority.protocol.messages import Chunk, decode_as
from minority.protocol.session import Inbox
from minority.protocol.shards import shard_path
from minority.protocol.spec import Spec
from minority.render_server.mpi_share import (
    DEFAULT_MAX_SIM_RANKS,
    DEFAULT_RANK_TIMEOUT_S,
    HEARTBEAT_S,
    POLL_S,
    TAG_DOWN,
    TAG_UP,
    ChunkReport,
    HeldChunks,
    RankCache,
    build_share,
    chunk_keys,
    empty_share,
    render_share,
)
from minority.render_server.render_mpi import Layers


class Worker:
    """A render rank k > 0: receives its sim ranks' chunks, logs them to its shard, reports
    them to rank 0, and renders its share of the steps rank 0 names."""

    def __init__(self, ctl, draw, session, run: str, spec: Spec,
                 max_sim_ranks: int = DEFAULT_MAX_SIM_RANKS,
                 rank_timeout_s: float = DEFAULT_RANK_TIMEOUT_S):
        self.ctl, self.draw, self.run, self.spec = ctl, draw, run, spec
        self.rank = ctl.rank
        self.rank_timeout_s = rank_timeout_s
        self.held = HeldChunks()
        self.commands: queue.SimpleQueue = queue.SimpleQueue()
        self._inbox = Inbox(session, chunk_keys(run, self.rank, ctl.size, max_sim_ranks),
                            256, 1 << 30)
        self._writer: LogWriter | None = None
        self._unlogged: list = []  # chunks that came while no shard was open
        self._send_lock = threading.Lock()
        self.received = self.rejected = 0

    def _up(self, message) -> None:
        with self._send_lock:
            self.ctl.send(message, dest=0, tag=TAG_UP)

    def _io(self) -> None:
        """Chunks from zenoh, commands and beats from rank 0, beats to rank 0, the watchdog."""
        last_seen = last_beat = time.monotonic()
        while True:
            item = self._inbox.get(timeout=POLL_S)
            if item is not None:
                self._chunk(item)
            while self.ctl.iprobe(source=0, tag=TAG_DOWN):
                message = self.ctl.recv(source=0, tag=TAG_DOWN)
                last_seen = time.monotonic()
                kind = message[0]
                if kind == "open":
                    self._open(message[1])
                elif kind == "close":
                    self._close()
                elif kind != "beat":
                    self.commands.put(message)
                if kind == "stop":
                    return
            now = time.monotonic()
            if now - last_beat >= HEARTBEAT_S:
                self._up(("beat",))
                last_beat = now
                if self._writer is not None:
                    self._writer.keep(self._writer.flush)
            if now - last_seen > self.rank_timeout_s:
                print(f"minority serve: render rank {self.rank}: nothing from rank 0 for "
                      f"{self.rank_timeout_s:g} s: it died; this rank stops", file=sys.stderr,
                      flush=True)
                self._close()
                self.ctl.Abort(1)  # ends every rank (rank 0 too, if it is stuck)

    def _chunk(self, item) -> None:
        try:
            chunk = decode_as(item.payload, Chunk)
        except ProtocolError as exc:
            chunk = None
            self.rejected += 1
            self._up(("report", f"render rank {self.rank}: rejected chunk on {item.key}: {exc}"))
        self._log(item.key, item.payload, item.recv_ns, chunk)
        if chunk is not None:
            self.received += 1
            self.held.add(chunk, len(item.payload))
            self._up(("report", ChunkReport.of(chunk, item.recv_ns, len(item.payload))))

    def _log(self, key, payload, recv_ns, chunk) -> None:
        if self._writer is None:
            if len(self._unlogged) < 256:
                self._unlogged.append((key, payload, recv_ns, chunk))
            return
        self._writer.keep(self._writer.write_payload, key, payload, recv_ns, chunk)

    def _open(self, path: str | None) -> None:
        self._close()
        self.commands.put(("open",))  # the main loop starts a new cache
        if path is None:
            self._unlogged.clear()
            return
        shard = shard_path(path, self.rank)
        try:
            self._writer = LogWriter(shard, metadata={"run": self.run, "side": "server",
                                                      "render_rank": str(self.rank)})
            self._writer.flush()  # the header on disk: a killed rank leaves a readable shard
        except OSError as exc:
            self._up(("report", f"render rank {self.rank}: cannot open its log {shard}: {exc}"))
            return
        for args in self._unlogged:
            self._log(*args)
        self._unlogged.clear()

    def _close(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._writer = None

    def serve(self) -> int:
        """Until rank 0 says stop. Returns the exit status."""
        io = threading.Thread(target=self._io, name="minority-mpi", daemon=True)
        io.start()
        cache, pending, canvases, layers = RankCache(), {}, {}, Layers()
        while True:
            message = self.commands.get()
            kind = message[0]
            if kind == "stop":
                break
            if kind == "open":
                cache, pending = RankCache(), {}
            elif kind == "release":
                release = message[1]
                chunks = self.held.take(release.step, list(release.sim_ranks))
                pending[release.seq] = build_share(release, chunks, cache)
            elif kind == "drop":
                pending.pop(message[1], None)
            elif kind == "render":
                release, spec_payload = message[1], message[2]
                if spec_payload is not None:
                    self.spec = decode_as(spec_payload, Spec)
                share = pending.pop(release.seq, None) or empty_share(release)
                for seq in [s for s in pending if s < release.seq]:
                    del pending[seq]  # replaced at rank 0 before it was rendered
                render_share(self.draw, share, self.spec, canvases, layers)
        io.join()
        self._close()
        self._inbox.close()
        return 0


def ignore_stop_signals() -> None:
    """Ranks k > 0 end when rank 0 says so (or dies), not on the launcher's SIGINT/SIGTERM:
    rank 0 receives those, finishes its collective and stops them."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
