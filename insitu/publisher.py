"""What a rank publishes: the spec's fields of the particles in its regions of interest, at
the steps its schedule asks for, and flow statistics on a fixed cadence of simulated time,
without ever blocking the simulation. The public face of it is insitu.api (`connect`).

* What a chunk and a Stats message carry (`cull`, `flow_stats`) is in insitu.payload; the
  bounded queue to the sender thread (`Outbox`) in insitu.outbox; the sender thread, its
  stalls and checkpoints, and what `sent` means, in insitu.sender.
* `RankPublisher.due` runs at every simulation step, `publish` at the steps it said yes to
  (or at every step: it asks `due` itself when the caller did not). `due` keeps the time the
  simulation reported for the previous step and passes it to `Spec.request(step, time_s, prev_time_s)` and in
  the chunk (`Chunk.prev_time_s`), so windows with an `every_s` cadence fire at exactly the
  steps the render server computes from the chunk (each instant t_start_s + k every_s falls
  to the first step whose (prev_time_s, time_s] holds it; step 0: when its time is one).
  Stats follow the same rule with their own cadence (`PublishOptions.stats_every_s`,
  instants k * stats_every_s from t = 0, step 0 included), whether or not a view is due and
  whether or not the spec is known.
* `RankPublisher` opens the rank's zenoh session (a client: no server -> it runs on and
  says why once), declares the rank's liveliness token, fetches the spec (a zenoh get with
  a timeout; a spec file is the fallback), follows spec updates, and hands snapshots of
  what a due step needs (positions, ids, the wanted fields: a copy) to one sender thread
  through a bounded outbox; the sender culls, splits the context rows and encodes them, in
  step order, then puts. While the sender is behind (4 chunks queued), a new chunk is
  refused at once, before any copy; nothing the simulation thread does waits on the network
  or on culling. Every drop is counted (`PublishStats`) and reported in the rank's
  `rank_done` event.
* Stats messages go through the same outbox, bounded on their own (OUTBOX_STATS; refused
  while full, counted in `stats_dropped`), computed on the sender thread from a snapshot of
  the velocities and displacements; spec and events always enter.
* With a record path, the sender thread also writes every message it takes from the
  outbox (spec, chunks, stats, events, as published) to that rank's MCAP record.
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

from minority.insitu.context import DEFAULT_TOLERANCE_M, ContextSplit, ContextTracker
from minority.insitu.lend import LentStep, Loans
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
from minority.insitu.payload import (
    ID_FIELD,
    STATS_FIELDS,
    STATS_READS,
    BufferPool,
    Particles,
    chunk_fields,
    cull_rows,
    flow_stats,
    scene_visible,
)
from minority.insitu.sender import (  # noqa: F401 (BLOCK_TIMEOUT_S, SENDER_QOS: for callers)
    BLOCK_TIMEOUT_KEY,
    BLOCK_TIMEOUT_S,
    CHECKPOINT_QOS,
    CHECKPOINT_TIMEOUT_S,
    PROBE_TIMEOUT_S,
    SENDER_QOS,
    STALL_FRACTION,
    Sender,
    _Tally,
)
from minority.protocol import keys
from minority.protocol.auth import CredentialsError
from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.messages import (
    Chunk,
    Event,
    EventKind,
    decode_as,
)
from minority.protocol.session import NetworkOptions, Role, open_session
from minority.protocol.spec import DataRequest, Spec, inside_mask, render_radius_m
from minority.protocol.view import Window

SPEC_TIMEOUT_S = 5.0  # zenoh get of the spec: a live server answers in milliseconds
SPEC_RETRY_S = 0.2  # s between spec queries while waiting for a starting server
DRAIN_TIMEOUT_S = 5.0  # at close: wait this long for the outbox to empty
STATS_EVERY_S = 0.005  # s of simulated time between a rank's Stats messages; 0: none


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
    # pictures; insitu.context), again when one moved more than the tolerance, m
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
    prepare_s: float = 0.0  # simulation-thread time taking a chunk's snapshot, queueing, s
    missing_fields: list[str] = field(default_factory=list)  # requested, not known here
    # Stats messages (not part of the chunk counts above, nor of `dropped`)
    stats_due: int = 0  # steps the stats cadence picked
    stats_sent: int = 0  # put with a subscriber matching (as `sent`)
    stats_dropped: int = 0  # due but not put (no server or subscriber, outbox full, stalled,
    #                         refused, exit) or put but unconfirmed when a stall came
    stats_s: float = 0.0  # simulation-thread time taking a Stats snapshot, queueing, s
    build_s: float = 0.0  # sender-thread time culling and encoding chunks and Stats, s
    build_errors: int = 0  # chunks or Stats whose culling or encoding raised (a bug)
    bad_steps: int = 0  # lent steps whose arrays were bad: not sent (in `failed`), raised
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

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]  # (lo, hi) corners, m


class _Copied:
    """A copied step's snapshot, read as a LentStep is (`get`)."""

    def __init__(self, particles: Particles):
        self._particles = particles

    @property
    def nbytes(self) -> int:
        return self._particles.nbytes

    def get(self) -> Particles:
        return self._particles


class RankPublisher(Sender):
    """One rank's publishing; see the module docstring. Call `connect`, then `fetch_spec`,
    then `start`; `due` at every step and `publish` when it says so; `close` at the end."""

    def __init__(self, rank: int, ranks: int, options: PublishOptions, log: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic):
        """`clock` (s, monotonic) times the sender's puts (a stall), probes and checkpoints;
        tests inject one to stage a stall without waiting for it."""
        self.rank, self.ranks = rank, ranks
        self.clock = clock
        self.options = options
        self.log = log if log is not None else sys.stderr
        self.session = None
        self.spec: Spec | None = None
        self.run: str | None = None
        self.stats = PublishStats()
        self.no_server_reason = ""
        self.connect_attempts = 0  # sessions tried by `connect` (open_session's attempts)
        self.connect_s = 0.0  # wall time `connect` took, s
        self._outbox = Outbox(options.outbox_chunks, options.outbox_bytes, options.outbox_stats)
        self._pool = BufferPool(keep=options.outbox_chunks + 2)  # snapshots' arrays, reused
        self._loans = Loans()  # messages that read lent arrays (publish(lend=True))
        self.close_error = None  # set by close: a bad lent step not raised before
        self._stats_cadence = (Window(every_s=options.stats_every_s)
                               if options.stats_every_s > 0 else None)
        self._context = (ContextTracker(options.context_tolerance_m)
                         if options.context else None)
        self._context_stale = False  # set by a spec change or a dropped chunk: reset it
        self._prev: tuple[int, float] | None = None  # (step, time_s) of the last `due` call
        # what the last `due` decided: (step, time_s, prev_time_s, request or None, stats due)
        self._due: tuple[int, float, float | None, DataRequest | None, bool] | None = None
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
        reason in no_server_reason (with the attempts made and the time they took: also in
        connect_attempts and connect_s), when no server is reachable."""
        opts = copy.copy(self.options.network)
        opts.connect_timeout_s = wait_s
        self.connect_attempts = 0
        t0 = time.monotonic()

        def configure(cfg: zenoh.Config) -> None:  # called once per attempt
            self.connect_attempts += 1
            if opts.config is None:  # an explicit choice; a --config file keeps its own
                cfg.insert_json5(BLOCK_TIMEOUT_KEY, str(int(BLOCK_TIMEOUT_S * 1e6)))
            self._stall_s = STALL_FRACTION * json.loads(cfg.get_json(BLOCK_TIMEOUT_KEY)) * 1e-6

        try:
            self.session = open_session(opts, Role.CLIENT, configure)
        except CredentialsError as exc:  # not authenticated: nothing sent (protocol.auth)
            self.connect_s = time.monotonic() - t0
            self.no_server_reason = f"not connecting: {exc}"
            return False
        except (zenoh.ZError, OSError) as exc:
            self.connect_s = time.monotonic() - t0
            where = ", ".join(opts.connect) or "the default endpoint"
            why = str(exc).split("  at ")[0].strip()  # drop zenoh's source location
            tries = self.connect_attempts  # 0: refused before any (no credentials)
            self.no_server_reason = (
                f"no zenoh server reachable at {where} ({why[:400]}; "
                + (f"{tries} connection attempt{'s' if tries != 1 else ''}" if tries else
                   "no connection attempted") + f" in {self.connect_s:.1f} s)")
            return False
        self.connect_s = time.monotonic() - t0
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

    def due(self, step: int, time_s: float) -> bool:
        """Call at every step (step 0 included), with the simulated time (s) after it:
        whether this step needs `publish` (the spec schedules a chunk, or the Stats cadence
        picks it, there is somewhere to send or record it, and the sender is not behind).
        Counts what the schedule asked for (`scheduled`, `stats_due`) and what it refuses
        here (no server nor record; a full outbox: `dropped_outbox`, `stats_dropped`).

        The previous call's time is this step's `prev_time_s` (None at step 0, or when the
        previous call was not for step - 1): `every_s` cadences need it, and the chunk
        carries it so the server decides with the very same floats."""
        if self._due is not None and self._due[:2] == (step, time_s):
            return self._due[3] is not None or self._due[4]
        prev = self._prev[1] if self._prev is not None and self._prev[0] == step - 1 else None
        self._prev = (step, time_s)
        stats = self._stats_cadence is not None and self._stats_cadence.wants(step, time_s, prev)
        request = self.request(step, time_s, prev)
        nowhere = self.session is None and self._writer is None  # nothing is built then
        # the sender is behind (a full outbox): refused here, so the caller builds nothing
        behind = not nowhere and request is not None and self._outbox.full(CHUNK)
        stats_behind = not nowhere and stats and self._outbox.full(STATS)
        with self._lock:
            if stats:
                self.stats.stats_due += 1
                self.stats.stats_dropped += nowhere or stats_behind
            if request is not None:
                self.stats.scheduled += 1
                self.stats.dropped_no_server += nowhere
                self.stats.dropped_outbox += behind
        if nowhere:
            request, stats = None, False
        if behind:
            request = None
        if stats_behind:
            stats = False
        self._due = (step, time_s, prev, request, stats)
        return request is not None or stats

    def wanted(self) -> tuple[str, ...]:
        """The fields the step `due` last said yes to reads, `id` aside: the request's and,
        when Stats are due, STATS_FIELDS (velocity, displacement)."""
        if self._due is None:
            return ()
        request, stats = self._due[3], self._due[4]
        names = [f for f in (request.fields if request is not None else ()) if f != ID_FIELD]
        return tuple(dict.fromkeys(names + list(STATS_FIELDS if stats else ())))

    def publish(self, step: int, time_s: float, particles: Particles, spacing_m: float,
                bounds_m: Bounds | Callable[[Particles], Bounds], lend: bool = False) -> bool:
        """At a step `due` said yes to (it is asked here when the caller did not): take what
        the step reads and queue the Stats message if its cadence picked the step and this
        rank's chunk if the spec schedules it (an empty one when no particle is in the
        regions, so the server's step completes); the sender thread culls and encodes them.
        What the step reads is copied, or with `lend` read in place by the sender (checked
        there first: insitu.lend; `reclaim` waits for it). `due` refused them already when
        the outbox was full (only this thread queues chunks and Stats, so it stays so).
        spacing_m: the particle spacing (m; the render radius follows it); bounds_m: the
        domain's corners (m), or a function of the checked particles giving them (called by
        the sender). Returns whether a chunk was scheduled. A second call for the same step
        sends nothing."""
        if self._due is None or self._due[:2] != (step, time_s):
            self.due(step, time_s)
        _, _, prev, request, stats = self._due
        self._due = (step, time_s, prev, None, False)  # consumed
        if request is None and not stats:
            return False
        t0 = time.perf_counter()
        # one snapshot for both (what the chunk and the Stats read), then both into the
        # outbox: the sender wakes once the caller's copy is done, not in the middle of it
        names = (tuple(request.fields) if request is not None else ()) + (
            STATS_READS if stats else ())
        if lend:
            snap = LentStep(step, particles, names, self._pool, self._loans.lend())
        else:
            snap = _Copied(particles.snapshot(names, self._pool))
        stats_item = self._stats_item(step, time_s, particles, snap, lend) if stats else None
        if request is None:
            self._put_stats(stats_item)
            if lend:
                snap.settle()
            return False
        for name in request.fields:
            if not particles.has(name):
                self._missing(name, particles)
        spec = self.spec

        def build() -> tuple[bytearray, int]:
            p = snap.get()
            bounds = bounds_m(p) if callable(bounds_m) else bounds_m
            return self._build_chunk(step, time_s, prev, request, spec, p, spacing_m, bounds)

        item = OutboxItem(keys.chunk(self.run, step, self.rank), None, CHUNK, build=build,
                          nbytes=snap.nbytes, release=snap.use() if lend else None)
        self._put_stats(stats_item)
        dropped = self._outbox.put(item)
        with self._lock:
            self.stats.particles_total += particles.n
            self.stats.dropped_outbox += dropped
            self.stats.prepare_s += time.perf_counter() - t0
        return True

    def reclaim(self, timeout_s: float | None = None) -> float:
        """Wait until no queued message reads a lent step's arrays (insitu.lend); the
        seconds waited. Raises the BadStep of a lent step that was not sent."""
        waited = self._loans.wait(timeout_s)
        self._loans.raise_bad()
        return waited

    def _build_chunk(self, step: int, time_s: float, prev: float | None,
                     request: DataRequest, spec: Spec, p: Particles, spacing_m: float,
                     bounds_m: Bounds) -> tuple[bytearray, int]:
        """On the sender thread, in step order: cull a snapshot, split its context rows,
        encode the chunk. Returns (payload, particles)."""
        t0 = time.perf_counter()
        inside = None if request.regions is None else inside_mask(p.positions, request.regions)
        radius = render_radius_m(spec, spacing_m)
        context = None
        if self._context is None:
            rows = cull_rows(p, request, radius, inside)
        else:  # every view draws the whole scene: cull by it, fresh rows and context alike
            keep = np.ones(p.n, dtype=bool) if request.decimate <= 1 else (
                p.ids % request.decimate == 0)
            seen = scene_visible(p, request, radius)
            if seen is not None:
                keep &= seen
            if inside is None and request.snapshot:  # every particle, in the chunk: those
                outside = keep & self._cached(p)  # the server holds go as context rows, kept
                fresh = keep & ~outside
            elif inside is None:  # no regions: every particle is fresh, none cached
                fresh, outside = keep, np.zeros(p.n, dtype=bool)
            else:
                fresh, outside = keep & inside, keep & ~inside
            context = self._split_context(p, outside, resend=request.snapshot)
            rows = np.concatenate([np.flatnonzero(fresh), context.rows])
            if len(rows) == p.n and not len(context.rows):  # every row, in order: no copy
                rows = None
        chunk = Chunk(self.run, step, time_s, self.rank, self.ranks, spacing_m, bounds_m,
                      chunk_fields(p, rows, request.fields), prev_time_s=prev)
        if context is not None:
            chunk.context_ids = p.ids[context.rows].astype(np.int64)
            chunk.evict_ids, chunk.context_reset = context.evict, context.reset
        payload = chunk.encode()
        with self._lock:
            self.stats.build_s += time.perf_counter() - t0
        return payload, chunk.count

    def _missing(self, name: str, particles: Particles) -> None:
        """Say once that the spec (or the Stats) needs a field the caller does not give."""
        if name in self.stats.missing_fields:
            return
        self.stats.missing_fields.append(name)
        print(f"rank {self.rank}: the spec asks for field {name!r}, which the simulation "
              f"does not provide (given: {', '.join(['id', *particles.fields]) })",
              file=self.log)

    def _cached(self, p: Particles) -> np.ndarray:
        """[n] bool: the particles the server holds from this rank (none after a reset)."""
        if self._context_stale:
            self._context_stale = False
            self._context.reset()
        return self._context.cached(p.ids)

    def _split_context(self, p: Particles, outside: np.ndarray,
                       resend: bool = False) -> ContextSplit:
        """The context rows and evictions of this chunk. outside [n] bool: the particles
        outside the regions the server must draw (within the stride, and that may show);
        the cached ones not among them are evicted. resend: every outside row is sent."""
        if self._context_stale:
            self._context_stale = False
            self._context.reset()
        split = self._context.split(p.ids, p.positions, outside, resend)
        with self._lock:
            self.stats.context_rows += len(split.rows)
            self.stats.context_evicted += len(split.evict)
            self.stats.context_resets += split.reset
        return split

    def _stats_item(self, step: int, time_s: float, p: Particles, snap: _Copied | LentStep,
                    lend: bool) -> OutboxItem | None:
        """This rank's Stats as an outbox item, computed and encoded on the sender thread
        from the step's snapshot or lent particles (the spec's open regions at time_s; none
        while the spec is not known). None, counted as dropped, without a velocity field."""
        t0 = time.perf_counter()
        if not ("velocity" in p.fields or "velocity_magnitude" in p.fields):
            self._missing("velocity", p)
            with self._lock:
                self.stats.stats_dropped += 1
            return None
        spec = self.spec
        regions = () if spec is None else spec.active_regions(time_s)
        run, rank = self.run, self.rank

        def build() -> tuple[bytearray, int]:
            t1 = time.perf_counter()
            payload = flow_stats(run, rank, step, time_s, snap.get(), regions).encode()
            with self._lock:
                self.stats.build_s += time.perf_counter() - t1
            return payload, 0

        with self._lock:
            self.stats.stats_s += time.perf_counter() - t0
        return OutboxItem(keys.stats(self.run), None, STATS, build=build, nbytes=snap.nbytes,
                          release=snap.use() if lend else None)

    def _put_stats(self, item: OutboxItem | None) -> None:
        if item is not None:
            dropped = self._outbox.put(item)
            if dropped:
                with self._lock:
                    self.stats.stats_dropped += dropped

    def event(self, kind: EventKind, message: str, detail: dict | None = None) -> None:
        if self.run is None:
            return
        ev = Event(self.run, kind, self.rank, message[:4000], detail or {})
        self._outbox.put(OutboxItem(keys.event(self.run), ev.encode(), CONTROL))

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
        self.close_error = self._loans.take_bad()  # a bad lent step the caller never saw
        if self.close_error is not None:
            self.event(EventKind.ERROR, f"rank {self.rank}: ValueError: {self.close_error}",
                       {"error": "ValueError"})
            detail = {**(detail or {}), "error": str(self.close_error)[:1000]}
        if self._thread is not None:
            stopped = (detail or {}).get("stopped")
            self.event(EventKind.RANK_DONE, f"rank {self.rank} "
                       + (f"stopped by {stopped}" if stopped else "done"),
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
            w = self._writer
            if not w.finish() and not self.stats.record_errors:  # the last chunk failed
                with self._lock:
                    self.stats.recorded = w.written + w.rejected
                    self.stats.record_errors = max(1, w.unwritten)
                print(f"minority: rank {self.rank}: its record is incomplete: {w.failure}; "
                      f"{w.ending}", file=self.log, flush=True)
        return self.stats

    def summary(self) -> dict:
        with self._lock:
            d = asdict(self.stats)
        d["dropped"] = self.stats.dropped
        d["prepare_s"] = round(d["prepare_s"], 6)
        d["stats_s"] = round(d["stats_s"], 6)
        d["build_s"] = round(d["build_s"], 6)
        return d
