"""The in situ API a simulation's time loop calls: `connect`, then `due` at every step and
`publish` when it says so, then `close` (or `with connect(...) as viz:`). The package
docstring (minority.insitu) and docs/insitu.md describe it for callers; the machinery is
insitu.publisher's RankPublisher, which this wraps with input checks and the caller's ids.
"""

from __future__ import annotations

import math
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from os import PathLike
from pathlib import Path
from typing import TextIO

import numpy as np

from minority.insitu.lend import BadStep, check_array, check_field, checked
from minority.insitu.payload import ID_FIELD, MAGNITUDE, Particles, particle_bytes
from minority.insitu.publisher import Bounds, PublishOptions, PublishStats, RankPublisher
from minority.protocol.check import NAME_RE
from minority.protocol.fields import FIELDS
from minority.protocol.messages import EventKind
from minority.protocol.session import DEFAULT_ENDPOINT, shm_pool_for
from minority.protocol.spec import Spec

ERROR_DRAIN_S = 1.0  # after an error in the caller's loop: wait at most this long to send
# the agreement hook of several ranks: (the spec this rank found, the error reading the spec
# file) -> the spec every rank follows; it may raise
Agree = Callable[[Spec | None, Exception | None], Spec | None]


def connect(run: str, rank: int = 0, ranks: int = 1,
            connect: Sequence[str] | None = (DEFAULT_ENDPOINT,),
            record: str | PathLike | None = None, spec: str | PathLike | None = None,
            wait_s: float = 0.0, *, id_offset: int = 0, particles: int | None = None,
            options: PublishOptions | None = None, agree: Agree | None = None,
            log: TextIO | None = None, report: bool = True) -> InSitu:
    """Open rank `rank` of `ranks` of run `run` (the spec's run id) for publishing.

    connect: zenoh endpoints of the render server (None or empty: tcp/127.0.0.1:7447);
    record: an MCAP path this rank writes what it publishes to, with or without a server
    (rank r > 0 writes `{stem}.rank{r}{suffix}`); spec: a spec file to follow when no server
    serves one; wait_s: keep trying to reach the server (and its spec) this long, s;
    id_offset: the first id of this rank's particles when `publish` is given no ids;
    particles: the most particles one chunk may carry (sizes zenoh's shared-memory pool;
    None: its default); options: the rest of PublishOptions (Stats cadence, context rows,
    outbox bounds, the network's config and credentials): its network.connect, record and
    spec_file are replaced by the arguments above; agree: ranks that must follow one spec
    (MPI) pass a collective hook; log: where notices go (stderr); report: print the outcome
    (no server, no spec) to log, and at `close` a warning again when no server was reached.

    No server is not an error: the run goes on and publishes nothing (or only records).
    A bad spec file raises (SpecError) before anything is published."""
    _check_name(run, "run")
    if not (_is_int(ranks) and ranks >= 1 and _is_int(rank) and 0 <= rank < ranks):
        raise ValueError(f"rank must be an integer in [0, ranks) and ranks >= 1, got rank "
                         f"{rank!r} of {ranks!r}")
    if not (math.isfinite(wait_s) and wait_s >= 0.0):
        raise ValueError(f"wait_s must be a finite number of seconds >= 0, got {wait_s}")
    if not (_is_int(id_offset) and id_offset >= 0):
        raise ValueError(f"id_offset must be an integer >= 0, got {id_offset!r}")
    if isinstance(connect, str):
        connect = (connect,)
    base = options if options is not None else PublishOptions()
    network = replace(base.network, connect=list(connect or ()))
    if particles is not None:
        if not (_is_int(particles) and particles >= 0):
            raise ValueError(f"particles must be an integer >= 0, got {particles!r}")
        network = replace(network, shm_pool_bytes=shm_pool_for(particles * particle_bytes(FIELDS)))
    opts = replace(base, network=network, record=Path(record) if record is not None else None,
                   spec_file=Path(spec) if spec is not None else None)
    log = log if log is not None else sys.stderr
    pub = RankPublisher(rank, ranks, opts, log)
    pub.connect(wait_s)
    try:
        try:
            found, error = pub.fetch_spec(run, wait_s), None
        except Exception as exc:  # a bad spec file (every rank reads the same one)
            found, error = None, exc
        if agree is not None:
            found = agree(found, error)
        elif error is not None:
            raise error
    except BaseException:
        pub.close()
        raise
    if report and pub.no_server_reason:
        print(f"minority: rank {rank}: WARNING: {pub.no_server_reason}: this run is NOT "
              f"observed, running without publishing"
              + (" (recording only)" if record is not None else ""), file=log, flush=True)
    if report and found is None:
        print(f"minority: rank {rank}: no spec for run {run!r} (no server serves one, no spec "
              f"file): nothing is scheduled, only Stats are published", file=log, flush=True)
    pub.start(run, found)
    return InSitu(pub, id_offset, report)


class InSitu:
    """A connected rank (from `connect`). Not thread-safe: call it from the simulation's
    thread. `stats` holds the counts so far; `spec` the spec followed now (None: none)."""

    def __init__(self, publisher: RankPublisher, id_offset: int = 0, report: bool = False):
        self._pub = publisher
        self._report = report  # at close: warn again when no server was reached
        self._id_offset = id_offset
        self._ids: np.ndarray | None = None  # arange(n) + id_offset, kept for the next call
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None  # seen so far, m
        self._bounds_lock = threading.Lock()
        self._step_checked: tuple[int, float] | None = None  # by `due`: (step, time_s)
        self._names_checked: set[str] = set()
        self._bounds_given: tuple[object, Bounds | None] = (None, None)  # last bounds_m, checked
        self._closed = False

    # --- what the caller reads ---------------------------------------------------------------
    @property
    def run(self) -> str:
        return self._pub.run

    @property
    def rank(self) -> int:
        return self._pub.rank

    @property
    def ranks(self) -> int:
        return self._pub.ranks

    @property
    def spec(self) -> Spec | None:
        return self._pub.spec

    @property
    def stats(self) -> PublishStats:
        return self._pub.stats

    @property
    def options(self) -> PublishOptions:
        return self._pub.options

    @property
    def no_server_reason(self) -> str:
        """Why no server is reachable ("" when one is)."""
        return self._pub.no_server_reason

    @property
    def wanted(self) -> tuple[str, ...]:
        """The fields the step `due` last said yes to needs (besides positions and ids): the
        spec's fields of the views due ("X_magnitude" may come as a vector field "X") and,
        when Stats are due, velocity and displacement. Build only these."""
        return self._pub.wanted()

    def summary(self) -> dict:
        """The counts as plain values (what the rank_done event carries)."""
        return self._pub.summary()

    # --- per step --------------------------------------------------------------------------
    def due(self, step: int, time_s: float) -> bool:
        """Whether step `step` (simulated time `time_s`, s, after the step) needs `publish`:
        a view of the spec is due, or the Stats cadence is (and there is a server or a record
        to send to). Call it at every step, step 0 included: `every_s` cadences need the
        previous step's time, which it remembers. Costs microseconds."""
        _check_step(step, time_s)
        self._step_checked = (step, time_s)
        return self._pub.due(step, time_s)

    def publish(self, step: int, time_s: float, positions: np.ndarray,
                fields: Mapping[str, np.ndarray | Callable[[], np.ndarray]] | None = None,
                ids: np.ndarray | None = None, *, spacing_m: float,
                bounds_m: Bounds | None = None, copy: bool = True) -> bool:
        """Hand over this rank's particles at a step `due` said yes to (asked here when the
        caller did not); returns at once: it copies what the step needs for the sender
        thread, which culls and encodes, and never waits on the network (a full outbox
        refuses the step without copying, counted in `stats.dropped_outbox`). Returns
        whether a chunk was scheduled.

        positions [n, 3] m; fields: name -> [n] or [n, k] values (SI units), or a function
        of no argument returning them (called once, only when the step needs the field):
        those the spec's views name ("X_magnitude" is computed from a given [n, k] "X"), and
        for Stats "velocity" [n, 3] m/s and "displacement" [n, 3] m (for the max
        displacement); ids [n] integers >= 0, unique across ranks (default: arange(n) +
        id_offset; give them when particles move between ranks or are reordered: decimation
        and the server's cache go by id); spacing_m: the particle spacing, m (spheres of half
        of it are drawn); bounds_m: the domain's (lo, hi) corners, m (default: the box of
        every position published so far).

        copy=True: the arrays are read before it returns, never kept; bad input (shape,
        length, dtype, a non-finite value) raises ValueError before anything is sent.
        copy=False lends them (insitu.lend): nothing is copied, the sender thread reads
        them (and calls the field functions) later, and the caller must not change them
        until `reclaim` returns; shapes and types are checked here, values there, and a bad
        lent step is not sent: the next `publish`, `reclaim` or `close` raises its
        ValueError."""
        self._pub._loans.raise_bad()  # a bad lent step: its error now
        if (step, time_s) != self._step_checked:  # (NaN is never equal: checked, raised)
            _check_step(step, time_s)
        if not (isinstance(spacing_m, (int, float, np.floating)) and math.isfinite(spacing_m)
                and spacing_m > 0.0):
            raise ValueError(f"spacing_m must be a finite length > 0 m, got {spacing_m!r}")
        positions = check_array("positions", positions)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions must be an [n, 3] array (m), got shape {positions.shape}")
        n = positions.shape[0]
        given = {}
        for name, values in (fields or {}).items():
            if name not in self._names_checked:
                _check_name(name, "field name")
                self._names_checked.add(name)
            if name in ("positions", ID_FIELD):
                raise ValueError(f"field {name!r} is reserved: pass positions and ids as "
                                 "arguments")
            given[name] = values if callable(values) else check_field(name, values, n)
        if ids is not None:
            ids = ids if isinstance(ids, np.ndarray) else np.asarray(ids)
            if ids.shape != (n,) or ids.dtype.kind not in "iu":  # signed or unsigned integers
                raise ValueError(f"ids must be [n] integers with n = {n}, got {ids.dtype} "
                                 f"{ids.shape}")
        if bounds_m is not None:
            if bounds_m is not self._bounds_given[0]:
                self._bounds_given = (bounds_m, _bounds(bounds_m))  # (as given, checked)
            bounds_m = self._bounds_given[1]
        if not self._pub.due(step, time_s):  # nothing is built or checked further
            return False
        wanted = set(self._pub.wanted())
        given = {k: v for k, v in given.items()  # the fields the step reads, no more
                 if k in wanted or k + MAGNITUDE in wanted}
        particles = Particles(positions, ids if ids is not None else self._default_ids(n), given)
        if copy:
            particles = checked(particles)
        bounds = bounds_m
        if bounds is None:  # the box seen so far: now, or by the sender for a lent step
            bounds = self._seen_bounds(particles) if copy else self._seen_bounds
        return self._pub.publish(step, time_s, particles, float(spacing_m), bounds,
                                 lend=not copy)

    def reclaim(self, timeout_s: float | None = None) -> float:
        """Wait until the sender no longer reads the arrays lent by `publish(copy=False)`
        (it has culled and encoded their messages, or dropped them); then the caller may
        change them. Returns the seconds waited (0 when nothing was lent). Raises the
        ValueError of a lent step that was bad (not sent); TimeoutError after timeout_s."""
        return self._pub.reclaim(timeout_s)

    def wait_sent(self, timeout_s: float) -> bool:
        """Wait until everything queued has left the outbox (at most timeout_s); whether it
        did. For tests and benchmarks: a simulation never needs to wait."""
        return self._pub._outbox.wait_empty(timeout_s)

    def event(self, kind: EventKind, message: str, detail: dict | None = None) -> None:
        """Publish a lifecycle event (e.g. run_start from rank 0) behind what was queued."""
        self._pub.event(kind, message, detail)

    # --- end -----------------------------------------------------------------------------------
    def close(self, detail: dict | None = None) -> PublishStats:
        """Send what is queued (waiting at most options.drain_timeout_s), then the rank_done
        event with the counts (and `detail`); release the liveliness token, the session and
        the record. Returns the counts; a second call only returns them. Raises the
        ValueError of a lent step that was bad and not raised yet (after closing; it is
        published as an error event before rank_done)."""
        if not self._closed:
            self._closed = True
            self._pub.close(detail)
            if self._report and self._pub.no_server_reason:
                print(f"minority: rank {self.rank}: WARNING: this run was NOT published/"
                      f"observed: {self._pub.no_server_reason}", file=self._pub.log, flush=True)
            if self._pub.close_error is not None:  # published as an error event too
                raise self._pub.close_error
        return self._pub.stats

    def fail(self, exc: BaseException) -> PublishStats:
        """Publish `exc` as an error event, then close (waiting at most ERROR_DRAIN_S)."""
        if self._closed:
            return self._pub.stats
        self._pub.event(EventKind.ERROR, f"rank {self.rank}: {type(exc).__name__}: {exc}",
                        {"error": type(exc).__name__})
        self._pub.options.drain_timeout_s = min(self._pub.options.drain_timeout_s, ERROR_DRAIN_S)
        try:
            return self.close({"error": str(exc)[:1000]})
        except BadStep:  # published as an event too; `exc` is the error that goes on
            return self._pub.stats

    def __enter__(self) -> InSitu:
        return self

    def __exit__(self, kind, exc, tb) -> bool:
        if exc is not None:
            self.fail(exc)
        else:
            self.close()
        return False  # an exception goes on to the caller

    # --- helpers ---------------------------------------------------------------------------
    def _default_ids(self, n: int) -> np.ndarray:
        if self._ids is None or len(self._ids) != n:
            self._ids = np.arange(self._id_offset, self._id_offset + n, dtype=np.int64)
        return self._ids

    def _seen_bounds(self, particles: Particles) -> Bounds:
        """The box of every position published so far (m); on the sender thread for a lent
        step, so under a lock."""
        positions = particles.positions
        with self._bounds_lock:
            if len(positions):
                lo, hi = positions.min(axis=0), positions.max(axis=0)
                if self._bounds is not None:
                    lo, hi = np.minimum(lo, self._bounds[0]), np.maximum(hi, self._bounds[1])
                self._bounds = (lo, hi)
            if self._bounds is None:
                return ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            return (tuple(map(float, self._bounds[0])), tuple(map(float, self._bounds[1])))


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _check_name(value, what: str) -> None:
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise ValueError(f"{what} must be 1-64 characters of A-Za-z0-9_.- starting with a "
                         f"letter, digit or underscore, got {value!r}")


def _check_step(step, time_s) -> None:
    if not (_is_int(step) and step >= 0):
        raise ValueError(f"step must be an integer >= 0, got {step!r}")
    if not (isinstance(time_s, (int, float, np.floating, np.integer)) and math.isfinite(time_s)
            and time_s >= 0.0):
        raise ValueError(f"time_s must be a finite simulated time >= 0 s, got {time_s!r}")


def _bounds(bounds_m) -> Bounds:
    b = np.asarray(bounds_m, dtype=np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or (b[0] > b[1]).any():
        raise ValueError(f"bounds_m must be ((lo x, y, z), (hi x, y, z)) in m, finite, lo <= hi, "
                         f"got {bounds_m!r}")
    return (tuple(map(float, b[0])), tuple(map(float, b[1])))
