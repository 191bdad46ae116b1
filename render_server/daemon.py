"""The render server daemon: serve the spec, receive chunks, assemble steps, render the
scheduled views (render_server.frames, shared with `minority replay`), write PNG frames,
publish frames and timing, record everything.

Threads: zenoh's callbacks only enqueue (bounded inbox); a receive thread decodes chunks and
assembles steps; a render thread takes the newest assembled step (a step replaced before it
was rendered is counted as skipped), so the simulation is never blocked and memory stays
bounded whatever the senders do.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from protocol import keys
from protocol.errors import ProtocolError
from protocol.log import Recorder
from protocol.messages import Chunk, Event, EventKind, Frame, Timing, decode_as
from protocol.session import CONTROL_QOS, FRAME_QOS, Inbox, put
from protocol.spec import Spec
from render_server.assemble import (
    DEFAULT_MAX_PENDING,
    DEFAULT_TIMEOUT_S,
    AssembledStep,
    StepAssembler,
)
from render_server.frames import render_views
from render_server.render import Canvas, prepare, render

RECEIVE_POLL_S = 0.05  # receive loop wakes at least this often to expire stale steps
TOKEN_GRACE_S = 1.0  # a rank whose token vanished without a done event: gone this much later
ERROR_EVENT_INTERVAL_S = 1.0  # at most one error event per interval (counts in between)


@dataclass
class ServerOptions:
    spec: Spec
    out_dir: Path  # frames go to out_dir/{run}/{view}/{step:06d}.png
    record: Path | None = None  # MCAP log of every message of the run
    timeout_s: float = DEFAULT_TIMEOUT_S
    max_pending: int = DEFAULT_MAX_PENDING
    inbox_capacity: int = 256  # chunks
    inbox_bytes: int = 1 << 30  # and at most this many bytes of them queued
    shadows: bool = False
    write_png: bool = True


@dataclass
class ServerStats:
    chunks: int = 0
    rejected: int = 0  # malformed chunks
    steps_rendered: int = 0
    steps_skipped: int = 0  # replaced by a newer step before rendering
    frames: int = 0
    view_errors: int = 0  # views that could not be rendered (e.g. a missing field)
    write_errors: int = 0  # frames rendered and published whose PNG could not be written
    last_error: str = ""
    errors_unreported: int = field(default=0, repr=False)


class LatestStep:
    """A one-slot mailbox: the newest step wins; replaced steps are counted."""

    def __init__(self):
        self._cond = threading.Condition()
        self._step: AssembledStep | None = None
        self.replaced = 0

    def put(self, step: AssembledStep) -> None:
        """Offer a step; an older step than the one waiting is the one dropped (two threads
        release steps, so they may arrive out of order)."""
        with self._cond:
            if self._step is not None:
                self.replaced += 1
                if self._step.step > step.step:
                    return
            self._step = step
            self._cond.notify()

    def empty(self) -> bool:
        with self._cond:
            return self._step is None

    def take(self, timeout: float) -> AssembledStep | None:
        with self._cond:
            if self._step is None:
                self._cond.wait(timeout)
            step, self._step = self._step, None
            return step


def warm_up() -> None:
    """Run every render kernel once on a tiny scene (numba compiles or loads its cache)."""
    from protocol.spec import Camera, View

    view = View("warm-up", Camera((0.0, -1.0, 0.0), (0.0, 0.0, 0.0)), 8, 8)
    scene = prepare(np.zeros((2, 3), np.float32), 0.1)
    for values in (np.zeros((2, 3), np.float32), np.zeros(2, np.float32)):  # as chunks carry
        render(scene, values, view, shadows=True)


class RenderServer:
    def __init__(self, session: zenoh.Session, options: ServerOptions):
        self.session = session
        self.options = options
        self.spec = options.spec
        self.run = options.spec.run
        self.stats = ServerStats()
        self._lock = threading.Lock()
        self._assembler = StepAssembler(options.timeout_s, options.max_pending)
        self._latest = LatestStep()
        self._canvases: dict[str, Canvas] = {}  # per view, reused frame after frame
        self._stop = threading.Event()
        self._last_error_event = 0.0
        # the run's end: every rank said done (event or token gone), then all drained
        self.finished = threading.Event()
        self._ranks_expected = 0  # from the chunks' rank count and the live tokens
        self._ranks_gone: set[int] = set()
        # a done event carries the rank's chunk count: the rank is gone once they all came
        # (the event travels at a higher priority than the chunks and may overtake them)
        self._rank_chunks_sent: dict[int, int] = {}
        self._rank_chunks_received: dict[int, int] = {}
        self._token_gone_ns: dict[int, int] = {}
        self._drained = threading.Event()  # nothing more to assemble; set after the last put
        culled = [v.name for v in self.spec.views if v.occlusion_cull]
        if options.shadows and culled:
            print(f"minority serve: views {', '.join(culled)} have occlusion_cull: the sim "
                  "leaves hidden particles out, so their shadows are missing", file=sys.stderr,
                  flush=True)
        warm_up()  # compile the kernels now, not on the first step
        self.recorder = Recorder(session, options.record, run=self.run) if options.record else None
        self._inbox = Inbox(session, keys.chunks(self.run), options.inbox_capacity,
                            options.inbox_bytes)
        self._queryable = session.declare_queryable(keys.spec(self.run), self._on_query)
        self._events = session.declare_subscriber(keys.event(self.run), self._on_event)
        self._tokens = session.liveliness().declare_subscriber(keys.rank_tokens(self.run),
                                                               self._on_token, history=True)
        self._threads = [threading.Thread(target=self._receive_loop, name="minority-receive"),
                         threading.Thread(target=self._render_loop, name="minority-render")]
        for t in self._threads:
            t.start()
        put(session, keys.spec(self.run), self.spec.encode(), CONTROL_QOS)
        self._event(EventKind.RUN_START, f"render server up, {len(self.spec.views)} views")

    # --- zenoh callbacks (enqueue or small work only) ---------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        query.reply(keys.spec(self.run), bytes(self.spec.encode()))

    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            event = decode_as(sample.payload.to_bytes(), Event)
        except ProtocolError as exc:
            self._error(f"malformed event: {exc}")
            return
        if event.kind == EventKind.RANK_DONE and event.rank >= 0:
            sent = event.detail.get("sent")
            if type(sent) is int and sent >= 0:
                with self._lock:
                    self._rank_chunks_sent[event.rank] = sent
                    waiting = self._rank_chunks_received.get(event.rank, 0) < sent
                if waiting:
                    return  # the receive loop marks it gone when its last chunk is in
            self._rank_gone(event.rank)

    def _on_token(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse(str(sample.key_expr))
        if not (parsed and parsed.rest and parsed.rest[0].isdigit()):
            return
        rank = int(parsed.rest[0])
        if sample.kind == zenoh.SampleKind.DELETE:  # died, or ended (its done event says)
            with self._lock:
                self._token_gone_ns.setdefault(rank, time.monotonic_ns())
        else:
            with self._lock:
                self._ranks_expected = max(self._ranks_expected, rank + 1)

    def _rank_gone(self, rank: int) -> None:
        with self._lock:
            for step in self._gone_locked(rank):
                self._latest.put(step)

    def _settle_gone_ranks(self) -> list:
        """Ranks whose done event's chunks have all arrived, or whose token vanished over
        TOKEN_GRACE_S ago without one, are gone (called with the lock held)."""
        now = time.monotonic_ns()
        out = []
        for rank, sent in list(self._rank_chunks_sent.items()):
            if rank not in self._ranks_gone and self._rank_chunks_received.get(rank, 0) >= sent:
                out += self._gone_locked(rank)
        for rank, t in list(self._token_gone_ns.items()):
            waiting = rank in self._rank_chunks_sent and rank not in self._ranks_gone
            if rank not in self._ranks_gone and (now - t >= TOKEN_GRACE_S * 1e9) and (
                    not waiting or now - t >= self.options.timeout_s * 1e9):
                out += self._gone_locked(rank)
        return out

    def _gone_locked(self, rank: int) -> list:
        self._ranks_gone.add(rank)
        self._ranks_expected = max(self._ranks_expected, rank + 1)
        return self._assembler.rank_gone(rank, time.time_ns())

    # --- threads --------------------------------------------------------------------
    def _receive_loop(self) -> None:
        while not self._stop.is_set():
            item = self._inbox.get(timeout=RECEIVE_POLL_S)
            try:
                done, drained = self._receive(item)
            except Exception as exc:  # noqa: BLE001 - the loop must outlive any chunk
                self._error(f"receiving {item.key if item else 'nothing'} failed: {exc!r}")
                continue
            for step in done:
                self._latest.put(step)
            if drained:
                self._drained.set()

    def _receive(self, item) -> tuple[list[AssembledStep], bool]:
        """Take one received chunk (or none, on a timeout): the steps now ready, and whether
        the run is over and everything is released."""
        drained = False
        with self._lock:
            done = self._assembler.expire(time.time_ns())
            if item is not None:
                try:
                    chunk = decode_as(item.payload, Chunk)
                except ProtocolError as exc:
                    self.stats.rejected += 1
                    self._error(f"rejected chunk on {item.key}: {exc}")
                else:
                    self.stats.chunks += 1
                    self._ranks_expected = max(self._ranks_expected, chunk.ranks)
                    r = chunk.rank
                    self._rank_chunks_received[r] = self._rank_chunks_received.get(r, 0) + 1
                    done += self._assembler.add(chunk, item.recv_ns, len(item.payload))
            done += self._settle_gone_ranks()
            if (item is None and self._ranks_expected and not self._drained.is_set()
                    and self._ranks_gone >= set(range(self._ranks_expected))):
                done += self._assembler.drain(time.time_ns())  # the run is over
                drained = True
        return done, drained

    def _render_loop(self) -> None:
        while not self._stop.is_set():
            step = self._latest.take(timeout=RECEIVE_POLL_S)
            if step is not None:
                try:
                    self.render_step(step)
                except Exception as exc:  # noqa: BLE001 - keep serving the next steps
                    self.stats.view_errors += 1
                    self._error(f"step {step.step} failed to render: {exc!r}")
            elif self._drained.is_set() and self._latest.empty():
                self.finished.set()  # every rank is done and its last step rendered
        self.stats.steps_skipped = self._latest.replaced

    def render_step(self, step: AssembledStep) -> None:
        """Render every view the schedule asks for at this step; publish frames and timing."""
        results = render_views(step, self.spec, self._canvases, self.options.shadows)
        if not results:
            return
        for r in results:
            if r.error:
                self.stats.view_errors += 1
                self._error(r.error)
                continue
            view = r.view
            if self.options.write_png:
                path = self.options.out_dir / self.run / view.name / f"{step.step:06d}.png"
                try:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(r.png)
                except OSError as exc:  # the frame is still published
                    self.stats.write_errors += 1
                    self._error(f"cannot write {path}: {exc}")
            frame = Frame(self.run, view.name, step.step, step.time_s, view.width, view.height,
                          r.png)
            put(self.session, keys.frame(self.run, view.name), frame.encode(), FRAME_QOS)
            timing = Timing(self.run, step.step, view.name, step.time_s, step.receive_s,
                            r.setup_s, r.render_s, step.nbytes, len(step.positions),
                            step.ranks_expected, step.ranks_received, step.incomplete)
            put(self.session, keys.timing(self.run), timing.encode(), CONTROL_QOS)
            self.stats.frames += 1
        self.stats.steps_rendered += 1

    # --- events and shutdown --------------------------------------------------------
    def _event(self, kind: EventKind, message: str, detail: dict | None = None) -> None:
        event = Event(self.run, kind, -1, message[:4000], detail or {})
        put(self.session, keys.event(self.run), event.encode(), CONTROL_QOS)

    def _error(self, message: str) -> None:
        """Log an error and publish it as an event, at most one per interval."""
        self.stats.last_error = message
        self.stats.errors_unreported += 1
        now = time.monotonic()
        if now - self._last_error_event >= ERROR_EVENT_INTERVAL_S:
            print(f"minority serve: {message}", file=sys.stderr, flush=True)
            self._event(EventKind.ERROR, message, {"errors": self.stats.errors_unreported})
            self.stats.errors_unreported = 0
            self._last_error_event = now

    def summary(self) -> dict:
        a = self._assembler.stats
        return {"chunks": self.stats.chunks, "rejected": self.stats.rejected,
                "steps_rendered": self.stats.steps_rendered,
                "steps_skipped": self._latest.replaced, "frames": self.stats.frames,
                "view_errors": self.stats.view_errors, "write_errors": self.stats.write_errors,
                "mismatched_fields": a.mismatched_fields, "duplicates": a.duplicates,
                "late": a.late, "timed_out": a.timed_out, "evicted": a.evicted,
                "inbox_dropped": self._inbox.dropped}

    def close(self) -> None:
        """Stop, render nothing more, publish run end, close the log (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        for t in self._threads:
            t.join()
        self._inbox.close()
        self._tokens.undeclare()
        self._events.undeclare()
        self._queryable.undeclare()
        self._event(EventKind.RUN_END, "render server stopping", self.summary())
        if self.recorder is not None:
            self.recorder.close()
