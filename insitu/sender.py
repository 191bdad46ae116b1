"""A rank's sender thread (`Sender`, mixed into insitu.publisher.RankPublisher): it takes
the encoded messages from the outbox, puts them, records them, and counts what happened.

The sender thread puts with congestion control BLOCK at data priority, so a slow server
(or network) pushes back into the counted outbox rather than into zenoh's silent drops,
and chunks and events leave in the order they were made (a `rank_done` never overtakes
the rank's last chunk). zenoh gives a blocked put up after the transport's
`block/wait_before_close` (BLOCK_TIMEOUT_S, set explicitly here) and then drops data on
that link without telling the sender until the receiver reads again. So a put that took
that long is a *stall*: it and every chunk after it count as dropped (not put) until a
spec query to the server is answered again (a probe every PROBE_INTERVAL_S).

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

from dataclasses import dataclass

import zenoh

from minority.insitu.lend import BadStep
from minority.insitu.outbox import CHUNK, CONTROL, STATS, OutboxItem
from minority.protocol import keys
from minority.protocol.session import QoS, put

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


class Sender:
    """The sender thread's half of a RankPublisher: what it reads of the publisher (session,
    run, rank, stats and their lock, outbox, record writer, clock, log, the checkpoint and
    stall state) is set up by RankPublisher.__init__ and start."""

    def _send_loop(self) -> None:
        while not self._stop.is_set():
            self._poll_checkpoint()
            item = self._outbox.take(SENDER_POLL_S)
            if item is None:
                continue
            try:
                built = item.build is None or self._build(item)
                item.released()
                if not built:
                    continue
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

    def _build(self, item: OutboxItem) -> bool:
        """Cull and encode a chunk or Stats item from its snapshot; False (counted as
        failed, said once) when that raises: the loop goes on with the next item."""
        try:
            item.payload, item.particles = item.build()
            item.build = None
            return True
        except Exception as exc:  # noqa: BLE001 - the sender must outlive a bad snapshot
            bad = isinstance(exc, BadStep)  # the caller's, raised at its next call
            with self._lock:
                if item.kind == CHUNK:
                    self.stats.failed += 1
                    self._context_stale = True  # its context rows may be half recorded
                else:
                    self.stats.stats_dropped += 1
                first = not self.stats.build_errors
                if bad:
                    self.stats.bad_steps += item.kind == CHUNK
                else:
                    self.stats.build_errors += 1
            if bad:
                self._loans.bad(exc)
            elif first:
                print(f"rank {self.rank}: could not build a {item.kind} for {item.key}: "
                      f"{exc!r}; counted as failed", file=self.log, flush=True)
            return False

    def _record(self, item: OutboxItem) -> int:
        """Write the message to the rank's record; 1 if written. The record ends at its first
        failed write (a full disk): the writer cuts it back to its last complete chunk, so
        the messages of the chunk it was filling, that message and the later ones are
        counted in record_errors (and taken back from recorded); publishing goes on."""
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
            w = self._writer
            with self._lock:
                self.stats.recorded = w.written + w.rejected
                self.stats.record_errors = max(1, w.unwritten)
            print(f"minority: rank {self.rank}: cannot write its record: {exc}; "
                  f"{w.ending or 'the record ends here'}; publishing goes on", file=self.log,
                  flush=True)
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
