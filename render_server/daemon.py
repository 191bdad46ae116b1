"""The render server daemon: serve the spec, receive chunks, assemble steps, render the
scheduled views (render_server.frames, shared with `minority replay`), write PNG frames,
publish frames and timing, log every message of each run (render_server.runs).

Threads: zenoh's callbacks only enqueue (bounded inboxes); a receive thread decodes chunks,
rank events and stats, assembles steps and decides which run of the run id a message
belongs to; a render thread takes the newest assembled step (a step replaced before it was
rendered is counted as skipped); a log thread writes each run's MCAP file. The simulation
is never blocked and memory stays bounded whatever the senders do.

Only the server publishes frames, timing and server events (rank -1) of its runs: the same
messages from anyone else are not logged.

On N MPI ranks (`options.mpi`, render_server.serve_mpi) this is rank 0: it receives only its
sim ranks' chunks, assembles from the other ranks' reports too, and renders collectively.
"""

from __future__ import annotations

import dataclasses
import queue
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from minority.protocol import keys
from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.messages import MAX_RANKS, Chunk, Event, EventKind, Frame, Stats, Timing, decode_as
from minority.protocol.session import CONTROL_QOS, FRAME_QOS, Inbox, put
from minority.protocol.spec import Spec
from minority.protocol.wire import SENT_NS_OFFSET
from minority.render_server.assemble import (
    DEFAULT_MAX_PENDING,
    DEFAULT_MAX_PENDING_BYTES,
    DEFAULT_TIMEOUT_S,
    AssembledStep,
    StepAssembler,
)
from minority.render_server.frames import render_views
from minority.render_server.particles import complete_step
from minority.render_server.render import Canvas, prepare, render
from minority.render_server.runs import (
    LogQueue,
    RunInstance,
    ServerStats,
    claim_frames_dir,
    open_writer,
    unclaimed_frames_dir,
)

RECEIVE_POLL_S = 0.05  # receive loop wakes at least this often to expire stale steps
TOKEN_GRACE_S = 1.0  # a rank whose token vanished without a done event: gone this much later
ERROR_EVENT_INTERVAL_S = 1.0  # at most one error event per interval (counts in between)
SIDE_CAPACITY = 1024  # rank events and stats queued at most (the rest dropped, counted)


@dataclass
class ServerOptions:
    spec: Spec
    out_dir: Path  # frames go to out_dir/{run}/{view}/{step:06d}.png
    record: Path | None = None  # MCAP log of the first run; later runs: {stem}.1{suffix}, ...
    timeout_s: float = DEFAULT_TIMEOUT_S
    max_pending: int = DEFAULT_MAX_PENDING
    max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES
    inbox_capacity: int = 256  # chunks
    inbox_bytes: int = 1 << 30  # and at most this many bytes of them queued
    shadows: bool = False
    write_png: bool = True
    # called with (run name, key, message) for the spec, frames, timing, events and stats of
    # each run as they are logged (chunks excepted), on the receive and render threads: it
    # must return at once (enqueue, never wait); what it raises is reported, not fatal
    observer: Callable[[str, str, object], None] | None = None
    # rank 0 of N render ranks (render_server.serve_mpi.Coordinator); None: one process
    mpi: object | None = None


class LatestStep:
    """A one-slot mailbox: the newest step wins; replaced steps are counted."""

    def __init__(self, on_drop: Callable[[object], None] | None = None):
        self._cond = threading.Condition()
        self._step: AssembledStep | None = None
        self.replaced = 0
        self._on_drop = on_drop  # called with each step dropped unrendered

    def put(self, step: AssembledStep) -> None:
        """Offer a step; an older step than the one waiting is the one dropped (steps may be
        released out of order)."""
        with self._cond:
            if self._step is not None:
                self.replaced += 1
                dropped = step if self._step.step > step.step else self._step
                if self._on_drop is not None:
                    self._on_drop(dropped)
                if dropped is step:
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
    from minority.protocol.spec import Camera, View

    view = View("warm-up", Camera((0.0, -1.0, 0.0), (0.0, 0.0, 0.0)), 8, 8)
    positions = np.random.default_rng(0).random((16, 3), dtype=np.float32)
    # 4 bricks: the k-d split kernels run too (one brick skips them; a step large enough to
    # need more compiled them on arrival: 5.8 s at the first 100k step of a fresh machine)
    scene = prepare(positions, 0.1, n_bricks=4)
    for values in (positions, positions[:, 0].copy()):  # [n, 3] and [n], as chunks carry
        render(scene, values, view, shadows=True)


class RenderServer:
    """Serves one run id: its spec, and each run of it in turn (a RunInstance: the first
    opens at start, the next with the first chunk or rank token after the last has ended)."""

    def __init__(self, session: zenoh.Session, options: ServerOptions):
        """Raises OSError when the first run's log cannot be opened."""
        self.session = session
        self.options = options
        self.spec = options.spec
        self.run = options.spec.run
        self._spec_payload = bytes(self.spec.encode())  # ranks ask ~10 times/s (insitu.publisher)
        self._stop = threading.Event()
        self._last_error_event = 0.0
        self._errors_unreported = 0
        self._mpi = options.mpi
        self._latest = LatestStep(self._mpi.dropped if self._mpi is not None else None)
        self._canvases: dict[str, Canvas] = {}  # per view, reused frame after frame
        self._tokens: queue.SimpleQueue = queue.SimpleQueue()  # (rank, alive, monotonic ns)
        # the newest run; the next opens only once it has finished, so at most one is open
        self._run: RunInstance | None = None
        self._seq = 0
        self.between_runs = 0  # rank messages that came when no run was open: not logged
        self.observer_errors = 0  # calls of options.observer that raised
        self.spec_updates = 0  # specs put by another peer and adopted (_spec_update)
        self.spec_updates_refused = 0
        culled = [v.name for v in self.spec.views if v.occlusion_cull]
        if options.shadows and culled:
            print(f"minority serve: views {', '.join(culled)} have occlusion_cull: the sim "
                  "leaves hidden particles out, so their shadows are missing", file=sys.stderr,
                  flush=True)
        warm_up()  # compile the kernels now, not on the first step
        self._log = LogQueue() if options.record else None
        try:
            self._open_instance()
        except OSError:
            if self._log is not None:
                self._log.stop()
            raise
        self._inbox = Inbox(session, self._mpi.chunk_keys() if self._mpi is not None
                            else keys.chunks(self.run), options.inbox_capacity,
                            options.inbox_bytes)
        # rank events, stats, and spec updates put by another peer (an oracle that follows
        # the run: minority oracle follow); the server's own put comes back and is ignored
        self._side = Inbox(session, [keys.event(self.run), keys.stats(self.run),
                                     keys.spec(self.run)], SIDE_CAPACITY)
        self._queryable = session.declare_queryable(keys.spec(self.run), self._on_query)
        self._token_sub = session.liveliness().declare_subscriber(
            keys.rank_tokens(self.run), self._on_token, history=True)
        self._threads = [threading.Thread(target=self._receive_loop, name="minority-receive"),
                         threading.Thread(target=self._render_loop, name="minority-render")]
        for t in self._threads:
            t.start()
        put(session, keys.spec(self.run), self.spec.encode(), CONTROL_QOS)

    @property
    def current(self) -> RunInstance:
        """The open run (or the last one, once it ended): its name, frame directory, log."""
        return self._run

    @property
    def finished(self) -> threading.Event:
        """Set once the newest run has ended (every rank done, its last step rendered)."""
        return self._run.finished

    @property
    def stats(self) -> ServerStats:
        """The counters of the open run (or of the last one, once it ended)."""
        return self._run.stats

    # --- zenoh callbacks (enqueue or small work only) ---------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        query.reply(keys.spec(self.run), self._spec_payload)

    def _on_token(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse(str(sample.key_expr))
        if parsed and parsed.rest and parsed.rest[0].isdigit() and int(parsed.rest[0]) < MAX_RANKS:
            self._tokens.put((int(parsed.rest[0]), sample.kind != zenoh.SampleKind.DELETE,
                              time.monotonic_ns()))

    # --- runs -----------------------------------------------------------------------
    def _open_instance(self, inbox_dropped: int = 0) -> RunInstance:
        """The next run, its frame folder and log claimed; `inbox_dropped`: the inbox's drop
        count so far (the run counts its own)."""
        o = self.options
        try:
            frames_dir = claim_frames_dir(o.out_dir, self.run)
        except OSError as exc:  # served all the same: frames published, write errors counted
            frames_dir = unclaimed_frames_dir(o.out_dir, self.run)
            self._error(f"cannot make the frame directory {frames_dir}: {exc}")
        name = frames_dir.name
        writer, log_error = None, ""
        if o.record is not None:
            try:
                writer = open_writer(o.record, self.run, name)
            except OSError as exc:
                if self._seq == 0:  # at start: the caller says it cannot start
                    if frames_dir.is_dir():
                        frames_dir.rmdir()
                    raise
                log_error = f"cannot open a log next to {o.record}: {exc}"
                self._error(f"{log_error}; this run is not logged")
            if writer is not None and writer.path != o.record:
                print(f"minority serve: run {self.run}: {o.record} exists, this run logs to "
                      f"{writer.path}", file=sys.stderr, flush=True)
        self._seq += 1
        inst = self._run = RunInstance(
            self._seq, name, frames_dir, writer,
            StepAssembler(o.timeout_s, o.max_pending, o.max_pending_bytes))
        inst.log_error = log_error
        inst.inbox_dropped_before = inbox_dropped
        if self._mpi is not None:  # the other ranks log their chunks next to this log
            self._mpi.open_instance(writer.path if writer is not None else None)
        if self._log is not None:
            self._log.put(writer, keys.spec(self.run), self._spec_payload, time.time_ns(),
                          self.spec)
        self._observe(inst, keys.spec(self.run), self.spec)
        self._publish_event(inst, EventKind.RUN_START,
                            f"render server up, {len(self.spec.views)} views", {"name": name})
        return inst

    def _active(self) -> RunInstance | None:
        """The run a rank's chunk or new token belongs to: the open one, or a new one once
        the last has ended (waiting, bounded by the stop, for its last step's render)."""
        inst = self._run
        if not inst.drained:
            return inst
        while not inst.finished.wait(RECEIVE_POLL_S):
            if self._stop.is_set():
                return None
        return self._open_instance(self._inbox.dropped)

    def _current(self) -> RunInstance | None:
        """The open run for a rank's other messages (events, stats); None between runs."""
        return None if self._run.drained else self._run

    def _finish_instance(self, inst: RunInstance) -> None:
        """The run's last step is rendered: say so, close its log."""
        failures = self._failures(inst)
        self._publish_event(inst, EventKind.RUN_END,
                            "run ended" + (f" with failures: {'; '.join(failures)}" if failures
                                           else ""), self._summary(inst))
        if self._log is not None:
            self._log.close_writer(inst.writer)
        if self._mpi is not None:
            self._mpi.close_instance()
        inst.finished.set()

    # --- threads --------------------------------------------------------------------
    def _receive_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._take_tokens()
                self._take_side()
                if self._mpi is not None:
                    self._take_reports()
            except Exception as exc:  # noqa: BLE001 - the loop must outlive any message
                self._error(f"handling a rank event failed: {exc!r}")
            item = self._inbox.get(timeout=RECEIVE_POLL_S)
            try:
                self._receive(item)
            except Exception as exc:  # noqa: BLE001 - the loop must outlive any chunk
                self._error(f"receiving {item.key if item else 'nothing'} failed: {exc!r}")

    def _take_tokens(self) -> None:
        while True:
            try:
                rank, alive, t_ns = self._tokens.get_nowait()
            except queue.Empty:
                return
            if alive:
                inst = self._active()
                if inst is not None:
                    inst.ranks_expected = max(inst.ranks_expected, rank + 1)
            elif (inst := self._current()) is not None:  # died, or ended (its done event says)
                inst.token_gone_ns.setdefault(rank, t_ns)

    def _take_side(self) -> None:
        """Rank events and stats: log them in the open run; a done event settles its rank."""
        while (item := self._side.get(timeout=0)) is not None:
            kind = keys.parse(item.key)
            if kind is not None and kind.topic == keys.Topic.SPEC:
                self._spec_update(item)
                continue
            cls = Event if kind is not None and kind.topic == keys.Topic.EVENT else Stats
            inst = self._current()
            try:
                message = decode_as(item.payload, cls)
            except ProtocolError as exc:
                self._error(f"malformed {cls.__name__.lower()} on {item.key}: {exc}")
                message = None
            if message is not None and cls is Event and message.rank < 0:
                continue  # the server's own events are logged as published
            if inst is None:
                self.between_runs += 1
                continue
            if self._log is not None:  # a malformed one goes to the log's rejected topic
                self._log.put(inst.writer, item.key, item.payload, item.recv_ns, message)
            if message is not None:
                self._observe(inst, item.key, message)
            if message is not None and cls is Event and message.kind == EventKind.RANK_DONE:
                sent = message.detail.get("sent")
                if type(sent) is int and sent >= 0:
                    inst.chunks_sent[message.rank] = sent
                    if inst.chunks_received.get(message.rank, 0) < sent:
                        continue  # gone once its last chunk is in (_settle_gone_ranks)
                self._release(self._gone(inst, message.rank))

    def _spec_update(self, item) -> None:
        """A spec put on the run's spec key by another peer: adopt it (the queryable serves
        it, steps rendered from now on follow it; ranks follow the same put), log it, count
        it; a malformed spec or another run's is refused (an error event; the spec stays)."""
        payload = bytes(item.payload)
        inst = self._current()
        try:
            spec = decode_as(payload, Spec)
            if spec.run != self.run:
                raise SpecError(f"its run is {spec.run!r}, not {self.run!r}")
            if spec == self.spec:
                return  # the server's own put, or the same spec again
        except (ProtocolError, SpecError) as exc:
            self.spec_updates_refused += 1
            self._error(f"refused a spec update on {item.key}: {exc}")
            if self._log is not None and inst is not None:  # to the log's rejected topic
                self._log.put(inst.writer, item.key, item.payload, item.recv_ns, None)
            return
        self.spec, self._spec_payload = spec, payload
        self.spec_updates += 1
        print(f"minority serve: run {self.run}: spec updated ({len(spec.views)} views"
              + (f"; {spec.provenance['reason']}" if "reason" in spec.provenance else "")
              + ")", file=sys.stderr, flush=True)
        if inst is not None:
            if self._log is not None:
                self._log.put(inst.writer, item.key, item.payload, item.recv_ns, spec)
            self._observe(inst, item.key, spec)

    def _receive(self, item) -> None:
        """Take one received chunk (or none, on a timeout): assemble, expire, settle ranks."""
        now = time.time_ns()
        if item is not None:
            inst = self._active()
            if inst is None:
                return
            try:
                chunk = decode_as(item.payload, Chunk)
            except ProtocolError as exc:
                inst.stats.rejected += 1
                self._error(f"rejected chunk on {item.key}: {exc}")
                chunk = None
            if self._log is not None:
                self._log.put(inst.writer, item.key, item.payload, item.recv_ns, chunk)
            if chunk is not None and self._mpi is not None:  # kept here, a stub assembled
                report = self._mpi.local(chunk, item.recv_ns, len(item.payload))
                chunk = self._mpi.admit(inst.assembler, report)
            if chunk is not None:
                self._add(inst, chunk, item.recv_ns, len(item.payload))
        inst = self._run
        if not inst.drained:
            self._release(inst.assembler.expire(now))
            self._settle_gone_ranks(inst)
            if item is None and inst.all_gone():
                self._release(inst.assembler.drain(now))  # the run is over
                inst.drained = True

    def _add(self, inst: RunInstance, chunk: Chunk, recv_ns: int, nbytes: int) -> None:
        inst.stats.chunks += 1
        inst.ranks_expected = max(inst.ranks_expected, chunk.ranks)
        r = chunk.rank
        inst.chunks_received[r] = inst.chunks_received.get(r, 0) + 1
        self._release(inst.assembler.add(chunk, recv_ns, nbytes))

    def _take_reports(self) -> None:
        """The other render ranks' chunks (serve_mpi.ChunkReport) and errors."""
        while True:
            try:
                report = self._mpi.reports.get_nowait()
            except queue.Empty:
                return
            if isinstance(report, str):
                self._run.stats.rejected += "rejected chunk" in report
                self._error(report)
                continue
            inst = self._active()
            if inst is None:
                return
            self._add(inst, self._mpi.admit(inst.assembler, report), report.recv_ns,
                      report.nbytes)
            if self._mpi.too_many_sim_ranks:
                self._error(f"the sim has {report.ranks} ranks, the render ranks receive the "
                            f"chunks of the first {self._mpi.max_sim_ranks}: raise "
                            "--max-sim-ranks")

    def _release(self, steps: list[AssembledStep]) -> None:
        """Complete each released step from the run's particle cache (every step, in
        release order: a skipped step's context still counts), then offer it to render.
        On N ranks: every rank builds and completes its share (serve_mpi.Coordinator)."""
        if self._mpi is not None:
            for step in steps:
                t0 = time.perf_counter()
                share = self._mpi.release(step)
                step.receive_s += time.perf_counter() - t0
                self._latest.put(share)
            return
        for step in steps:
            t0 = time.perf_counter()
            step = complete_step(self._run.cache, step)
            step.receive_s += time.perf_counter() - t0
            self._latest.put(step)

    def _settle_gone_ranks(self, inst: RunInstance) -> None:
        """Ranks whose done event's chunks have all arrived, or whose token vanished over
        TOKEN_GRACE_S ago without one, are gone."""
        now = time.monotonic_ns()
        for rank, sent in list(inst.chunks_sent.items()):
            if rank not in inst.ranks_gone and inst.chunks_received.get(rank, 0) >= sent:
                self._release(self._gone(inst, rank))
        for rank, t in list(inst.token_gone_ns.items()):
            waiting = rank in inst.chunks_sent and rank not in inst.ranks_gone
            if rank not in inst.ranks_gone and (now - t >= TOKEN_GRACE_S * 1e9) and (
                    not waiting or now - t >= self.options.timeout_s * 1e9):
                if rank not in inst.chunks_sent:
                    inst.ranks_lost.add(rank)
                    self._error(f"rank {rank} of run {inst.name} vanished without its done "
                                "event (killed, or its link lost): the run is cut short",
                                always=True)
                self._release(self._gone(inst, rank))

    def _gone(self, inst: RunInstance, rank: int) -> list[AssembledStep]:
        inst.ranks_gone.add(rank)
        inst.ranks_expected = max(inst.ranks_expected, rank + 1)
        return inst.assembler.rank_gone(rank, time.time_ns())

    def _render_loop(self) -> None:
        while not self._stop.is_set():
            step = self._latest.take(timeout=RECEIVE_POLL_S)
            if step is not None:
                try:
                    self.render_step(step)
                except Exception as exc:  # noqa: BLE001 - keep serving the next steps
                    self._run.stats.view_errors += 1
                    self._error(f"step {step.step} failed to render: {exc!r}")
            elif self._latest.empty() and self._run.drained and not self._run.finished.is_set():
                self._finish_instance(self._run)  # every rank is done, its last step rendered

    def render_step(self, step: AssembledStep) -> None:
        """Render every view the schedule asks for at this step; publish frames and timing.
        On N ranks `step` is rank 0's serve_mpi.Share, rendered collectively."""
        inst = self._run
        if self._mpi is not None:
            results, _, totals = self._mpi.render(step, self.spec, self._canvases)
            step = dataclasses.replace(step.meta, completed=totals.completed,
                                       cached=totals.cached, cache_age_s=totals.cache_age_s,
                                       cache_age_steps=totals.cache_age_steps)
            particles = totals.particles
        else:
            results = render_views(step, self.spec, self._canvases, self.options.shadows)
            particles = len(step.positions)
        if not results:
            return
        for r in results:
            if r.error:
                inst.stats.view_errors += 1
                self._error(r.error)
                continue
            view = r.view
            if self.options.write_png:
                path = inst.frames_dir / view.name / f"{step.step:06d}.png"
                try:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(r.png)
                except OSError as exc:  # the frame is still published
                    inst.stats.write_errors += 1
                    self._error(f"cannot write {path}: {exc}")
            frame = Frame(self.run, view.name, step.step, step.time_s, view.width, view.height,
                          r.png)
            self._publish(inst, keys.frame(self.run, view.name), frame, FRAME_QOS)
            timing = Timing(self.run, step.step, view.name, step.time_s, step.receive_s,
                            r.setup_s, r.render_s, step.nbytes, particles,
                            step.ranks_expected, step.ranks_received, step.incomplete,
                            cached=step.cached, cache_age_s=step.cache_age_s,
                            cache_age_steps=step.cache_age_steps)
            self._publish(inst, keys.timing(self.run), timing, CONTROL_QOS)
            inst.stats.frames += 1
        inst.stats.steps_rendered += 1

    # --- publishing, events and shutdown --------------------------------------------
    def _publish(self, inst: RunInstance | None, key: str, message, qos) -> None:
        """Put a message of the server's own and log it in the run it belongs to (the
        subscriber side ignores the server's own frames, timing and events)."""
        payload = message.encode()
        put(self.session, key, payload, qos)
        if inst is not None:
            message.sent_ns = struct.unpack_from("<q", payload, SENT_NS_OFFSET)[0]
            if self._log is not None:
                self._log.put(inst.writer, key, payload, time.time_ns(), message)
            self._observe(inst, key, message)

    def _observe(self, inst: RunInstance, key: str, message) -> None:
        observer = self.options.observer
        if observer is None:
            return
        try:
            observer(inst.name, key, message)
        except Exception as exc:  # noqa: BLE001 - a viewer's fault never stops the server
            self.observer_errors += 1
            if self.observer_errors == 1:
                print(f"minority serve: the observer failed: {exc!r}", file=sys.stderr,
                      flush=True)

    def _publish_event(self, inst: RunInstance | None, kind: EventKind, message: str,
                       detail: dict | None = None) -> None:
        event = Event(self.run, kind, -1, message[:4000], detail or {})
        self._publish(inst, keys.event(self.run), event, CONTROL_QOS)

    def _error(self, message: str, always: bool = False) -> None:
        """Log an error and publish it as an event, at most one per interval unless
        `always`. It is logged in the open run; between runs it is published only."""
        if self._run is not None:
            self._run.stats.last_error = message
        self._errors_unreported += 1
        now = time.monotonic()
        if always or now - self._last_error_event >= ERROR_EVENT_INTERVAL_S:
            print(f"minority serve: {message}", file=sys.stderr, flush=True)
            inst = self._run if self._run is not None and not self._run.finished.is_set() \
                else None
            self._publish_event(inst, EventKind.ERROR, message,
                                {"errors": self._errors_unreported})
            self._errors_unreported = 0
            self._last_error_event = now

    def _summary(self, inst: RunInstance) -> dict:
        """The run's counters. Every chunk a rank's done event counts is in exactly one of
        chunks (assembled), inbox_dropped, queued_at_stop and lost_in_transit."""
        a, s = inst.assembler.stats, inst.stats
        missing = inst.missing()
        inbox_dropped = self._inbox.dropped - inst.inbox_dropped_before
        lost = max(0, sum(missing.values()) - inbox_dropped - inst.queued_at_stop)
        return {"name": inst.name, "chunks": s.chunks, "rejected": s.rejected,
                "steps_rendered": s.steps_rendered, "steps_skipped": self._latest.replaced,
                "frames": s.frames, "view_errors": s.view_errors,
                "write_errors": s.write_errors, "mismatched_fields": a.mismatched_fields,
                "duplicates": a.duplicates, "late": a.late, "timed_out": a.timed_out,
                "evicted": a.evicted, "inbox_dropped": inbox_dropped,
                "queued_at_stop": inst.queued_at_stop, "lost_in_transit": lost,
                "missing_by_rank": {str(r): n for r, n in missing.items()},
                "ranks_lost": sorted(inst.ranks_lost),
                "log_dropped": (self._log.dropped_by.get(inst.writer.path, 0)
                                if self._log is not None and inst.writer is not None else 0),
                "log_unwritten": inst.writer.unwritten if inst.writer is not None else 0,
                "log_failure": inst.writer.failure if inst.writer is not None else "",
                "between_runs": self.between_runs, "spec_updates": self.spec_updates,
                "spec_updates_refused": self.spec_updates_refused}

    def summary(self) -> dict:
        """The counters of the open run (or of the last one)."""
        return self._summary(self._run)

    def _failures(self, inst: RunInstance) -> list[str]:
        out = []
        if inst.ranks_lost:
            out.append("rank(s) " + ", ".join(map(str, sorted(inst.ranks_lost)))
                       + " vanished without their done event")
        if inst.writer is not None and inst.writer.failure:
            out.append(f"its log {inst.writer.path} ends early ({inst.writer.failure})")
        if inst.log_error:
            out.append(f"it was not logged ({inst.log_error})")
        return out

    def failures(self) -> list[str]:
        """What went wrong in the open run (or the last one) that its user must hear of: a
        rank killed before it was done, a log cut short. Empty: none."""
        return self._failures(self._run)

    def abort(self, reason: str) -> None:
        """A render rank died (serve_mpi): say so, end the open run and close the log without
        waiting for the render thread, which may be stuck in a collective with it. The
        process must exit after this (os._exit: MPI cannot finalize)."""
        self._stop.set()
        self._last_error_event = 0.0  # the error event goes out, whatever came just before
        self._error(reason)
        self._threads[0].join(timeout=5.0)  # the receive thread; not the render thread
        if not self._run.finished.is_set():
            self._finish_instance(self._run)
        if self._log is not None:
            self._log.stop()

    def _keep_queued(self, inst: RunInstance) -> None:
        """At a stop: the rank messages still queued go to the run's log unrendered, and its
        chunks are counted (queued_at_stop), so none is in nobody's count."""
        try:
            self._take_side()
        except Exception as exc:  # noqa: BLE001 - the stop must go on
            self._error(f"handling a rank event failed: {exc!r}")
        while (item := self._inbox.get(timeout=0)) is not None:
            inst.queued_at_stop += 1
            if self._log is not None:
                self._log.put(inst.writer, item.key, item.payload, item.recv_ns)

    def close(self) -> None:
        """Stop, render nothing more, end the open run, close the logs (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        for t in self._threads:
            t.join()
        self._inbox.close()
        self._side.close()
        self._token_sub.undeclare()
        self._queryable.undeclare()
        if not self._run.finished.is_set():
            self._keep_queued(self._run)
            self._finish_instance(self._run)
        if self._mpi is not None:
            self._mpi.stop()
        if self._log is not None:
            self._log.stop()
