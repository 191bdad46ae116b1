"""What a rank publishes: the spec's fields of the particles in its regions of interest, at
the steps its schedule asks for, and flow statistics on a fixed cadence of simulated time,
without ever blocking the simulation.

* What a chunk and a Stats message carry (`cull`, `flow_stats`) is in sim.payload; the
  bounded queue to the sender thread (`Outbox`) in sim.outbox.
* `RankPublisher.publish` runs at every sim step. It keeps the time the simulation reported
  for the previous step and passes it to `Spec.request(step, time_s, prev_time_s)` and in
  the chunk (`Chunk.prev_time_s`), so windows with an `every_s` cadence fire at exactly the
  steps the render server computes from the chunk (each instant t_start_s + k every_s falls
  to the first step whose (prev_time_s, time_s] holds it; step 0: when its time is one).
  Stats follow the same rule with their own cadence (`PublishOptions.stats_every_s`,
  instants k * stats_every_s from t = 0, step 0 included), whether or not a view is due and
  whether or not the spec is known.
* `RankPublisher` opens the rank's zenoh session (a client: no server -> it runs on and
  says why once), declares the rank's liveliness token, fetches the spec (a zenoh get with
  a timeout; a `--spec` file is the fallback), follows spec updates, and hands encoded
  messages to one sender thread through a bounded outbox. A full outbox drops its oldest
  chunk; nothing the simulation thread does waits on the network. Every drop is counted
  (`PublishStats`) and reported in the rank's `rank_done` event.
* The sender thread puts with congestion control BLOCK at data priority, so a slow server
  (or network) pushes back into the counted outbox rather than into zenoh's silent drops,
  and chunks and events leave in the order they were made (a `rank_done` never overtakes
  the rank's last chunk). zenoh gives a blocked put up after the transport's
  `block/wait_before_close` (BLOCK_TIMEOUT_S, set explicitly here) and then drops data on
  that link without telling the sender until the receiver reads again. So a put that took
  that long is a *stall*: it and every chunk after it count as dropped (not put) until a
  spec query to the server is answered again (a probe every PROBE_INTERVAL_S).
* Stats messages go through the same outbox, bounded on their own (OUTBOX_STATS, the oldest
  dropped first, counted in `stats_dropped`); spec and events always enter.
* With a record path, the sender thread also writes every message it takes from the
  outbox (spec, chunks, stats, events, as published) to that rank's MCAP record.

What `sent` means, and what is exact. `sent` is what the rank believes reached a subscriber
(the render server waits for that many chunks of the rank, and reports the difference to
what it received as lost in transit); it never exceeds what was put.

* No subscriber. zenoh puts into the void without an error when nothing subscribes, so
  `start` declares one publisher on the run's chunk key space (`minority/{run}/chunk/**`)
  and one on its stats key, never put through, only for their matching status (read by the
  sender thread before each put, about 0.5 us; the simulation thread never touches it), and
  waits one round trip so the status is known before the first chunk (measured: it is, in
  600 of 600 tries). A chunk (a Stats message) with no subscriber matching is not put:
  `dropped_no_subscriber` (`stats_dropped`). Exact as of the check; a subscriber that
  leaves during the put is the server's loss to report.
* Stalls. A chunk whose put zenoh gave up, and the chunks not put while stalled, are
  `dropped_stalled`: exact. The chunks put quickly just before a stall are the uncertain
  ones: zenoh accepted them into its queues, then may have dropped them with the link.
  *Checkpoints* bound them: after a put, at most every CHECKPOINT_INTERVAL_S and one at a
  time, the sender sends a spec query at data priority behind the chunks (same queue, so
  in order; a non-blocking get whose answer it polls). A spec answered by the server proves
  that every chunk put before that query reached the server's session (`sent_confirmed`
  counts them). When a stall is detected, every chunk put after the last answered
  checkpoint (and not already settled) moves from `sent` (and its bytes and particles) to
  `dropped_before_stall`: an upper bound of what zenoh dropped before the stall (some of
  them may have arrived: a render server may receive more chunks of a rank than its
  `sent`; measured with a subscriber that stops reading, about 600 chunks/s on loopback:
  10 to 53 moved where 3 or 4 were lost, i.e. about CHECKPOINT_INTERVAL_S of puts on top
  of the lost ones). Only a query *answer* proves delivery: a get also ends with no answer
  when the link dies (measured), so an unanswered or timed-out checkpoint settles nothing.
  With no spec queryable (no render server, e.g. a recorder alone) nothing is ever
  confirmed, and a stall moves every chunk put since the start (or since the last stall).
  Stats messages follow the same rule (`stats_sent` -> `stats_dropped`).
* Chunks put after the last checkpoint with no stall detected stay in `sent`
  (`sent - sent_confirmed` of them are unconfirmed): the rank has no evidence of their
  loss; a render server that did not get them reports them as lost in transit.
"""

from __future__ import annotations

import copy
import json
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np
import zenoh
from minority.protocol import keys
from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.messages import (
    Chunk,
    Event,
    EventKind,
    decode_as,
)
from minority.protocol.session import NetworkOptions, QoS, Role, open_session, put
from minority.protocol.spec import DataRequest, Spec, inside_mask, render_radius_m
from minority.protocol.view import Window
from minority.insitu.context import DEFAULT_TOLERANCE_M, ContextSplit, ContextTracker
from minority.insitu.outbox import (
    CHUNK,
    CONTROL,
    OUTBOX_BYTES,
    OUTBOX_CHUNKS,
    OUTBOX_STATS,
    STATS,
    Outbox,
    OutboxItem,
)
from minority.insitu.payload import SIM_FIELDS, chunk_fields, cull_rows, flow_stats, scene_visible

SPEC_TIMEOUT_S = 5.0  # zenoh get of the spec: a live server answers in milliseconds
SPEC_RETRY_S = 0.2  # s between spec queries while waiting for a starting server
DRAIN_TIMEOUT_S = 5.0  # at close: wait this long for the outbox to empty
STATS_EVERY_S = 0.005  # s of simulated time between a rank's Stats messages; 0: none
SENDER_POLL_S = 0.1
BLOCK_TIMEOUT_S = 2.0  # zenoh gives a blocked put up after this long (our client sessions)
BLOCK_TIMEOUT_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
STALL_FRACTION = 0.9  # a put that took this share of the block timeout was given up
PROBE_INTERVAL_S = 1.0  # while stalled: ask the server for the spec this often
PROBE_TIMEOUT_S = 1.0
# While chunks flow: a spec query behind them at most this often (one in flight at a time);
# its answer confirms the chunks put before it. 10 per second per rank: the render server's
# spec reply costs it about 35 us (its spec's encode), 0.35 ms/s per rank.
CHECKPOINT_INTERVAL_S = 0.1
CHECKPOINT_TIMEOUT_S = 1.0


def record_path(path: Path, rank: int) -> Path:
    """A rank's MCAP record: `path` for rank 0, `{stem}.rank{r}{suffix}` for rank r > 0."""
    path = Path(path)
    return path if rank == 0 else path.with_name(f"{path.stem}.rank{rank}{path.suffix}")


@dataclass
class PublishOptions:
    network: NetworkOptions = field(default_factory=NetworkOptions)
    spec_file: Path | None = None  # the spec to follow when no server serves one
    record: Path | None = None  # this rank's MCAP record of what it publishes
    spec_timeout_s: float = SPEC_TIMEOUT_S
    drain_timeout_s: float = DRAIN_TIMEOUT_S
    outbox_chunks: int = OUTBOX_CHUNKS
    outbox_bytes: int = OUTBOX_BYTES
    outbox_stats: int = OUTBOX_STATS
    stats_every_s: float = STATS_EVERY_S  # s of simulated time between Stats; 0: none
    # send the particles outside the regions as context rows the server caches (complete
    # pictures; sim.context), again when one moved more than the tolerance, m
    context: bool = True
    context_tolerance_m: float = DEFAULT_TOLERANCE_M

    def __post_init__(self) -> None:
        if not (math.isfinite(self.stats_every_s) and self.stats_every_s >= 0.0):
            raise ValueError(f"stats_every_s must be a finite number of seconds >= 0 (0: no "
                             f"stats), got {self.stats_every_s}")
        tol = self.context_tolerance_m
        if not (math.isfinite(tol) and tol >= 0.0):
            raise ValueError(f"the context tolerance must be a finite length >= 0 m, got {tol}")


@dataclass
class PublishStats:
    """Counts of one rank's publishing; `dropped_*` are chunks the schedule asked for that
    did not leave the rank."""

    scheduled: int = 0  # chunks the spec's schedule asked for
    sent: int = 0  # put with a subscriber matching, and not moved to dropped_before_stall
    sent_confirmed: int = 0  # of `sent`: reached the server (a later checkpoint answered)
    recorded: int = 0  # messages written to the rank's MCAP record
    record_errors: int = 0  # messages not recorded: the first failed write (a full disk) on
    bad_specs: int = 0  # spec updates that did not decode (the rank kept its spec)
    dropped_no_server: int = 0  # no zenoh session (nothing to send to)
    dropped_no_subscriber: int = 0  # a session, but nothing subscribed to the chunk: not put
    dropped_outbox: int = 0  # the outbox was full: the server (or the disk) fell behind
    dropped_at_exit: int = 0  # still in the outbox when the drain timeout ran out
    dropped_stalled: int = 0  # given up by zenoh, or not put while the link was stalled
    dropped_before_stall: int = 0  # put, unconfirmed when a stall came: an upper bound
    failed: int = 0  # zenoh refused the put (e.g. the session closed)
    stalls: int = 0  # times a put blocked for the whole block timeout
    bytes_sent: int = 0  # chunk payload bytes handed to zenoh
    particles_sent: int = 0
    particles_total: int = 0  # particles on the rank at the scheduled steps (before culling)
    prepare_s: float = 0.0  # simulation-thread time culling, encoding, queueing, s
    missing_fields: list[str] = field(default_factory=list)  # requested, not known here
    # Stats messages (not part of the chunk counts above, nor of `dropped`)
    stats_due: int = 0  # steps the stats cadence picked
    stats_sent: int = 0  # put with a subscriber matching (as `sent`)
    stats_dropped: int = 0  # due but not put (no server or subscriber, outbox full, stalled,
    #                         refused, exit) or put but unconfirmed when a stall came
    stats_s: float = 0.0  # simulation-thread time computing, encoding, queueing Stats, s
    # context rows (particles outside the regions, for the server's cache; part of
    # particles_sent when their chunk was sent), evicted ids, resets (first step, a spec
    # change, a dropped chunk)
    context_rows: int = 0
    context_evicted: int = 0
    context_resets: int = 0

    @property
    def dropped(self) -> int:
        return (self.dropped_no_server + self.dropped_no_subscriber + self.dropped_outbox
                + self.dropped_at_exit + self.dropped_stalled + self.dropped_before_stall
                + self.failed)


@dataclass(frozen=True)
class _Tally:
    """What the sender put and counted as sent, cumulative: chunks, their payload bytes and
    particles, Stats messages."""

    chunks: int = 0
    bytes: int = 0
    particles: int = 0
    stats: int = 0

    def __add__(self, other: _Tally) -> _Tally:
        return _Tally(self.chunks + other.chunks, self.bytes + other.bytes,
                      self.particles + other.particles, self.stats + other.stats)

    def __sub__(self, other: _Tally) -> _Tally:
        return _Tally(self.chunks - other.chunks, self.bytes - other.bytes,
                      self.particles - other.particles, self.stats - other.stats)


# Data priority and BLOCK: see the module docstring (the outbox is the pressure valve).
SENDER_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA)
# Checkpoints travel in the chunks' queue (data priority), in order behind them; a full queue
# drops one (never answered: it confirms nothing) rather than blocking the sender.
CHECKPOINT_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA)


class RankPublisher:
    """One rank's publishing; see the module docstring. Call `connect`, then `fetch_spec`,
    then `start`; `publish` at every step; `close` at the end."""

    def __init__(self, rank: int, ranks: int, spacing_m: float,
                 bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]],
                 options: PublishOptions, log: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic):
        """`clock` (s, monotonic) times the sender's puts (a stall), probes and checkpoints;
        tests inject one to stage a stall without waiting for it."""
        self.rank, self.ranks = rank, ranks
        self.clock = clock
        self.spacing_m, self.bounds_m = spacing_m, bounds_m
        self.options = options
        self.log = log if log is not None else sys.stderr
        self.session = None
        self.spec: Spec | None = None
        self.run: str | None = None
        self.stats = PublishStats()
        self.no_server_reason = ""
        self._outbox = Outbox(options.outbox_chunks, options.outbox_bytes, options.outbox_stats)
        self._stats_cadence = (Window(every_s=options.stats_every_s)
                               if options.stats_every_s > 0 else None)
        self._context = (ContextTracker(options.context_tolerance_m)
                         if options.context else None)
        self._context_stale = False  # set by a spec change or a dropped chunk: reset it
        self._prev: tuple[int, float] | None = None  # (step, time_s) of the last publish call
        self._token = None
        self._spec_sub = None
        self._writer = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()  # stats touched by both threads
        self._stall_s = STALL_FRACTION * BLOCK_TIMEOUT_S
        self._stalled = False
        self._last_probe = 0.0
        # matching status only (never put through), by outbox kind; the checkpoint querier
        self._readers: dict[str, zenoh.Publisher] = {}
        self._querier: zenoh.Querier | None = None
        # the sender thread's alone: what it put and counted as sent; of that, what a
        # checkpoint answer confirmed or a stall moved; the checkpoint in flight
        self._puts = _Tally()
        self._settled = _Tally()
        self._checkpoint: tuple[object, _Tally] | None = None  # (replies, puts covered)
        self._checkpoint_at = -math.inf

    # --- start ------------------------------------------------------------------------
    def connect(self, wait_s: float = 0.0) -> bool:
        """Open the rank's client session (keep trying for wait_s seconds); False, with the
        reason in no_server_reason, when no server is reachable."""
        opts = copy.copy(self.options.network)
        opts.connect_timeout_s = wait_s
        def configure(cfg: zenoh.Config) -> None:
            if opts.config is None:  # an explicit choice; a --config file keeps its own
                cfg.insert_json5(BLOCK_TIMEOUT_KEY, str(int(BLOCK_TIMEOUT_S * 1e6)))
            self._stall_s = STALL_FRACTION * json.loads(cfg.get_json(BLOCK_TIMEOUT_KEY)) * 1e-6

        try:
            self.session = open_session(opts, Role.CLIENT, configure)
        except (zenoh.ZError, OSError) as exc:  # OSError: unusable credentials (protocol.auth)
            where = ", ".join(opts.connect) or "the default endpoint"
            why = str(exc).split("  at ")[0].strip()  # drop zenoh's source location
            self.no_server_reason = f"no zenoh server reachable at {where} ({why[:160]})"
            return False
        return True

    def fetch_spec(self, run: str, wait_s: float = 0.0) -> Spec | None:
        """The spec the server serves for `run` (zenoh get with a timeout, asked again until
        wait_s seconds have passed: a server that is still starting answers once it is ready
        to receive, so nothing is published into the void), else the spec file of the
        options (its run must match), else None."""
        deadline = time.monotonic() + wait_s
        while self.session is not None:
            for reply in self.session.get(keys.spec(run), timeout=self.options.spec_timeout_s):
                if reply.ok is None:
                    continue
                try:
                    return decode_as(reply.ok.payload.to_bytes(), Spec)
                except (ProtocolError, SpecError) as exc:
                    print(f"rank {self.rank}: ignoring a malformed spec from the server: {exc}",
                          file=self.log)
            if time.monotonic() >= deadline:
                break
            time.sleep(SPEC_RETRY_S)  # polling a server that is starting up, bounded by wait_s
        if self.options.spec_file is not None:
            spec = Spec.load(self.options.spec_file)
            if spec.run != run:
                raise SpecError(f"{self.options.spec_file}: spec run {spec.run!r} is not the "
                                f"run {run!r}")
            return spec
        return None

    def start(self, run: str, spec: Spec | None) -> None:
        """Declare the liveliness token, follow spec updates, start the sender thread."""
        self.run, self.spec = run, spec
        if self.options.record is not None:
            from minority.protocol.log import LogWriter

            self._writer = LogWriter(record_path(self.options.record, self.rank), metadata={
                "run": run, "rank": str(self.rank), "ranks": str(self.ranks), "side": "sim"})
        if self.session is not None:
            self._token = self.session.liveliness().declare_token(keys.rank_token(run, self.rank))
            self._spec_sub = self.session.declare_subscriber(keys.spec(run), self._on_spec)
            self._readers = {CHUNK: self.session.declare_publisher(keys.chunks(run)),
                             STATS: self.session.declare_publisher(keys.stats(run))}
            self._querier = self.session.declare_querier(
                keys.spec(run), timeout=CHECKPOINT_TIMEOUT_S,
                congestion_control=CHECKPOINT_QOS.congestion, priority=CHECKPOINT_QOS.priority,
                allowed_destination=zenoh.Locality.REMOTE)
            # one round trip: the router sends the matching subscribers before its answer
            for _ in self.session.get(keys.spec(run), timeout=PROBE_TIMEOUT_S):
                pass
        if spec is not None:  # the server serves the spec; the record notes which one we follow
            self._outbox.put(OutboxItem(keys.spec(run), spec.encode(), CONTROL, publish=False))
        self._thread = threading.Thread(target=self._send_loop, name=f"minority-send-{self.rank}",
                                        daemon=True)
        self._thread.start()

    def _on_spec(self, sample) -> None:  # zenoh thread: decode, swap, note it in the record
        try:
            spec = decode_as(sample.payload.to_bytes(), Spec)
        except (ProtocolError, SpecError) as exc:
            with self._lock:
                self.stats.bad_specs += 1
            print(f"rank {self.rank}: ignored a malformed spec update: {exc}", file=self.log,
                  flush=True)
            return
        if spec.run == self.run and spec != self.spec:
            self.spec = spec
            self._context_stale = True
            self._outbox.put(OutboxItem(keys.spec(self.run), spec.encode(), CONTROL,
                                   publish=False))

    # --- per step -------------------------------------------------------------------------
    def request(self, step: int, time_s: float,
                prev_time_s: float | None = None) -> DataRequest | None:
        spec = self.spec
        return None if spec is None else spec.request(step, time_s, prev_time_s)

    def publish(self, step: int, time_s: float, ps: ParticleState) -> bool:
        """Call at every sim step (step 0 included), with the simulated time (s) the
        simulation reports after it. If the spec schedules this step, cull, encode and queue
        this rank's chunk (an empty one when no particle is in the regions, so the server's
        step completes); if the stats cadence picks it, queue a Stats message. Returns
        whether a chunk was scheduled.

        The previous call's time is this step's `prev_time_s` (None at step 0, or when the
        previous call was not for step - 1): `every_s` cadences need it, and the chunk
        carries it so the server decides with the very same floats."""
        prev = self._prev[1] if self._prev is not None and self._prev[0] == step - 1 else None
        self._prev = (step, time_s)
        if self._stats_cadence is not None and self._stats_cadence.wants(step, time_s, prev):
            self._publish_stats(step, time_s, ps)
        request = self.request(step, time_s, prev)
        if request is None:
            return False
        t0 = time.perf_counter()
        with self._lock:
            self.stats.scheduled += 1
            self.stats.particles_total += ps.n
            if self.session is None and self._writer is None:  # nowhere to go: not built
                self.stats.dropped_no_server += 1
                self.stats.prepare_s += time.perf_counter() - t0
                return True
        for name in request.fields:
            if name not in SIM_FIELDS and name not in self.stats.missing_fields:
                self.stats.missing_fields.append(name)
                print(f"rank {self.rank}: the spec asks for field {name!r}, which the simulation "
                      f"does not provide (known: {', '.join(SIM_FIELDS)})", file=self.log)
        inside = None if request.regions is None else inside_mask(ps.x, request.regions)
        radius = render_radius_m(self.spec, self.spacing_m)
        context = None
        if self._context is None:
            rows = cull_rows(ps, request, radius, inside)
        else:  # every view draws the whole scene: cull by it, fresh rows and context alike
            keep = np.ones(ps.n, dtype=bool) if request.decimate <= 1 else (
                ps.pid % request.decimate == 0)
            seen = scene_visible(ps, request, radius)
            if seen is not None:
                keep &= seen
            if inside is None:  # no regions: every particle is fresh, none cached
                fresh, outside = keep, np.zeros(ps.n, dtype=bool)
            else:
                fresh, outside = keep & inside, keep & ~inside
            context = self._split_context(ps, outside)
            rows = np.concatenate([np.flatnonzero(fresh), context.rows])
        chunk = Chunk(self.run, step, time_s, self.rank, self.ranks, self.spacing_m,
                      self.bounds_m, chunk_fields(ps, rows, request.fields), prev_time_s=prev)
        if context is not None:
            chunk.context_ids = ps.pid[context.rows].astype(np.int64)
            chunk.evict_ids, chunk.context_reset = context.evict, context.reset
        item = OutboxItem(keys.chunk(self.run, step, self.rank), chunk.encode(), CHUNK, chunk.count)
        dropped = self._outbox.put(item)
        with self._lock:
            self.stats.dropped_outbox += dropped
            self.stats.prepare_s += time.perf_counter() - t0
        if dropped:
            self._context_stale = True
        return True

    def _split_context(self, ps: ParticleState, outside: np.ndarray) -> ContextSplit:
        """The context rows and evictions of this chunk. outside [n] bool: the particles
        outside the regions the server must draw (within the stride, and that may show);
        the cached ones not among them are evicted."""
        if self._context_stale:
            self._context_stale = False
            self._context.reset()
        split = self._context.split(ps.pid, ps.x, outside)
        with self._lock:
            self.stats.context_rows += len(split.rows)
            self.stats.context_evicted += len(split.evict)
            self.stats.context_resets += split.reset
        return split

    def _publish_stats(self, step: int, time_s: float, ps: ParticleState) -> None:
        """Compute, encode and queue this rank's Stats (the spec's open regions at time_s;
        none while the spec is not known)."""
        t0 = time.perf_counter()
        with self._lock:
            self.stats.stats_due += 1
            if self.session is None and self._writer is None:  # nowhere to go: not built
                self.stats.stats_dropped += 1
                return
        spec = self.spec
        regions = () if spec is None else spec.active_regions(time_s)
        message = flow_stats(self.run, self.rank, step, time_s, ps, regions)
        dropped = self._outbox.put(OutboxItem(keys.stats(self.run), message.encode(), STATS))
        with self._lock:
            self.stats.stats_dropped += dropped
            self.stats.stats_s += time.perf_counter() - t0

    def event(self, kind: EventKind, message: str, detail: dict | None = None) -> None:
        if self.run is None:
            return
        ev = Event(self.run, kind, self.rank, message[:4000], detail or {})
        self._outbox.put(OutboxItem(keys.event(self.run), ev.encode(), CONTROL))

    # --- the sender thread ------------------------------------------------------------------
    def _send_loop(self) -> None:
        while not self._stop.is_set():
            self._poll_checkpoint()
            item = self._outbox.take(SENDER_POLL_S)
            if item is None:
                continue
            try:
                outcome = self._send(item) if item.publish else "local"
                recorded = self._record(item)
                with self._lock:
                    self.stats.recorded += recorded
                    if item.kind == CHUNK:
                        if outcome == "sent":
                            self._puts += _Tally(1, len(item.payload), item.particles)
                            self.stats.sent += 1
                            self.stats.bytes_sent += len(item.payload)
                            self.stats.particles_sent += item.particles
                        else:
                            name = f"dropped_{outcome}" if outcome != "failed" else "failed"
                            setattr(self.stats, name, getattr(self.stats, name) + 1)
                            if outcome != "no_server":  # the server missed cache updates
                                self._context_stale = True
                    elif item.kind == STATS:
                        if outcome == "sent":
                            self._puts += _Tally(stats=1)
                            self.stats.stats_sent += 1
                        else:
                            self.stats.stats_dropped += 1
                if outcome == "sent" and item.kind != CONTROL:
                    self._start_checkpoint()
            finally:
                self._outbox.done()

    def _record(self, item: OutboxItem) -> int:
        """Write the message to the rank's record; 1 if written. The record ends at its first
        failed write (a full disk; what follows a partial write could not be read back):
        that message and the later ones are counted in record_errors; publishing goes on."""
        if self._writer is None:
            return 0
        if self.stats.record_errors:
            with self._lock:
                self.stats.record_errors += 1
            return 0
        try:
            self._writer.write_payload(item.key, bytes(item.payload))
            return 1
        except OSError as exc:
            with self._lock:
                self.stats.record_errors += 1
            print(f"minority sim: rank {self.rank}: cannot write its record: {exc}; the record "
                  "ends here, publishing goes on", file=self.log, flush=True)
            return 0

    def _send(self, item: OutboxItem) -> str:
        """Put one message; returns "sent", "no_server", "no_subscriber" (a chunk or Stats
        message nothing subscribes to: not put), "stalled" or "failed"."""
        if self.session is None:
            return "no_server"
        readers = self._readers.get(item.kind)
        try:
            if readers is not None and not readers.matching_status.matching:
                return "no_subscriber"
        except zenoh.ZError:  # undeclared: the rank is closing
            return "failed"
        if self._stalled and not self._probe():
            return "stalled"
        t0 = self.clock()
        try:
            put(self.session, item.key, item.payload, SENDER_QOS)
        except zenoh.ZError:
            return "failed"
        blocked_s = self.clock() - t0
        if blocked_s >= self._stall_s:  # zenoh gave this put up
            self._on_stall(blocked_s)
            return "stalled"
        return "sent"

    def _on_stall(self, blocked_s: float) -> None:
        """A put was given up: count the stall, move the chunks (and Stats) put since the last
        confirmation from sent to dropped (see the module docstring), stop putting until a
        probe is answered."""
        self._poll_checkpoint()  # an answer that came while the put blocked still confirms
        self._checkpoint = None  # one still in flight confirms nothing now: it is settled
        window = self._puts - self._settled
        self._settled = self._puts
        with self._lock:
            self.stats.stalls += 1
            self.stats.sent -= window.chunks
            self.stats.bytes_sent -= window.bytes
            self.stats.particles_sent -= window.particles
            self.stats.dropped_before_stall += window.chunks
            self.stats.stats_sent -= window.stats
            self.stats.stats_dropped += window.stats
        if not self._stalled:
            print(f"rank {self.rank}: the server stopped reading (a put blocked {blocked_s:.1f} "
                  f"s); {window.chunks} chunk(s) put since the last confirmation count as "
                  f"dropped; dropping chunks until it answers again", file=self.log, flush=True)
        self._stalled = True
        self._last_probe = self.clock()

    def _start_checkpoint(self) -> None:
        """After a put: unless one is in flight or the last one is younger than
        CHECKPOINT_INTERVAL_S, send a spec query behind the puts so far (non-blocking)."""
        if self._querier is None or self._checkpoint is not None:
            return
        now = self.clock()
        if now - self._checkpoint_at < CHECKPOINT_INTERVAL_S:
            return
        self._checkpoint_at = now
        try:
            self._checkpoint = (self._querier.get(), self._puts)
        except zenoh.ZError:  # the session is closing
            self._checkpoint = None

    def _poll_checkpoint(self) -> None:
        """Settle the checkpoint in flight if answered: the puts it covers reached the server.
        One that ends with no answer (timed out, no spec queryable, the link died) or with
        errors only is forgotten."""
        if self._checkpoint is None:
            return
        replies, covered = self._checkpoint
        while True:
            try:
                reply = replies.try_recv()
            except zenoh.ZError:  # closed with no answer
                self._checkpoint = None
                return
            if reply is None:  # still in flight
                return
            if reply.ok is not None:
                self._checkpoint = None
                fresh = covered - self._settled  # >= 0: a stall forgets the one in flight
                self._settled = covered
                with self._lock:
                    self.stats.sent_confirmed += fresh.chunks
                return

    def _probe(self) -> bool:
        """While stalled: at most every PROBE_INTERVAL_S, ask the server for the spec; an
        answer means it reads again."""
        if self.clock() - self._last_probe < PROBE_INTERVAL_S:
            return False
        self._last_probe = self.clock()
        try:
            replies = self.session.get(keys.spec(self.run), timeout=PROBE_TIMEOUT_S)
            self._stalled = not any(r.ok is not None for r in replies)
        except zenoh.ZError:
            return False
        return not self._stalled

    # --- end ----------------------------------------------------------------------------------
    def close(self, detail: dict | None = None) -> PublishStats:
        """Drain the outbox (at most drain_timeout_s), publish `rank_done` with the counts
        (and `detail`), close the record and the session. Returns the final counts."""
        delivered = self._thread is None or self._outbox.wait_empty(self.options.drain_timeout_s)
        if not delivered:
            chunks, stats = self._outbox.discard_chunks()
            with self._lock:
                self.stats.dropped_at_exit += chunks
                self.stats.stats_dropped += stats
        if self._thread is not None:
            self.event(EventKind.RANK_DONE, f"rank {self.rank} done",
                       {**(detail or {}), **self.summary()})
            if not self._outbox.wait_empty(self.options.drain_timeout_s if delivered else 0.0):
                print(f"rank {self.rank}: the rank_done event could not be sent (the server "
                      f"does not read)", file=self.log)
            self._stop.set()
            self._thread.join(timeout=self.options.drain_timeout_s)
        if self.session is not None:
            for handle in (self._spec_sub, self._token, self._querier, *self._readers.values()):
                if handle is not None:
                    handle.undeclare()
            self.session.close()  # returns once a blocked put gives up (zenoh's bound)
        if self._thread is not None:
            self._thread.join(timeout=self.options.drain_timeout_s)
        if self._writer is not None and (self._thread is None or not self._thread.is_alive()):
            if self.stats.record_errors:
                self._writer.abandon()  # no summary after the failed write
            else:
                try:
                    self._writer.close()
                except OSError as exc:
                    print(f"minority sim: rank {self.rank}: cannot finish its record: {exc}",
                          file=self.log, flush=True)
                    self._writer.abandon()
        return self.stats

    def summary(self) -> dict:
        with self._lock:
            d = asdict(self.stats)
        d["dropped"] = self.stats.dropped
        d["prepare_s"] = round(d["prepare_s"], 6)
        d["stats_s"] = round(d["stats_s"], 6)
        return d
