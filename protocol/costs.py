"""What an in situ run cost, from its log (protocol.runlog.RunLog): time per step, bytes
received against a full dump, skipped and incomplete steps.

The render server publishes one Timing per (step, view) it renders: receive_s and setup_s
belong to the step (the same for each of its views), render_s to the view. So an *in situ
step* costs receive + setup + the sum of its views' render times, as in the reference
paper's table (Kumar et al. 2022, "In situ visualization time for each step"); shares are
of the mean total. Times are in s, bytes in B.

A *full dump* is every particle of the run, positions plus the fields the chunks carry,
at every rendered step (array bytes only: `particles * bytes per particle`). The particle
total comes from the events (sim rank 0's `run_start` detail, or the ranks' `rank_done`
details) or from the chunk counts of a step at which the logged spec culls nothing; when
none of these is in the log it is unknown, and says why, rather than guessed.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass

from minority.protocol.messages import EventKind, Timing
from minority.protocol.runlog import ChunkInfo, RunLog


# --- timing -----------------------------------------------------------------------------
@dataclass(frozen=True)
class StepTiming:
    """One rendered in situ step; times in s."""

    step: int
    time_s: float  # simulated, s
    views: tuple[str, ...]
    receive_s: float
    setup_s: float
    render_s: float  # sum over the step's views
    bytes: int  # chunk bytes the server received for the step
    particles: int
    ranks_expected: int
    ranks_received: int
    incomplete: bool

    @property
    def total_s(self) -> float:
        return self.receive_s + self.setup_s + self.render_s


@dataclass(frozen=True)
class Breakdown:
    """Mean receive / setup / render times (s) over `count` items, and their shares."""

    count: int
    receive_s: float
    setup_s: float
    render_s: float

    @property
    def total_s(self) -> float:
        return self.receive_s + self.setup_s + self.render_s

    def share(self, part: str) -> float:
        """Fraction (0..1) of the mean total spent in `part` (receive, setup, render)."""
        return getattr(self, f"{part}_s") / self.total_s if self.total_s > 0 else 0.0


def _mean(items) -> Breakdown:
    n = len(items)
    return Breakdown(n, *(sum(getattr(i, f"{p}_s") for i in items) / n
                          for p in ("receive", "setup", "render")))


@dataclass(frozen=True)
class TimingTable:
    steps: list[StepTiming]  # rendered steps, by step
    per_step: Breakdown  # mean per in situ step
    per_view: dict[str, Breakdown]  # mean per Timing record of each view
    frames: dict[str, int]  # Frame records per view in the log
    duplicates: int  # Timing records repeating a (step, view), ignored


def timing_table(log: RunLog) -> TimingTable:
    seen: dict[tuple[int, str], Timing] = {}
    for t in log.timings:
        seen.setdefault((t.step, t.view), t)
    by_step: dict[int, list[Timing]] = defaultdict(list)
    by_view: dict[str, list[Timing]] = defaultdict(list)
    for t in seen.values():
        by_step[t.step].append(t)
        by_view[t.view].append(t)
    steps = [StepTiming(s, ts[0].time_s, tuple(t.view for t in ts),
                        max(t.receive_s for t in ts), max(t.setup_s for t in ts),
                        sum(t.render_s for t in ts), max(t.bytes for t in ts),
                        max(t.particles for t in ts), max(t.ranks_expected for t in ts),
                        min(t.ranks_received for t in ts), any(t.incomplete for t in ts))
             for s, ts in sorted(by_step.items())]
    return TimingTable(steps, _mean(steps), {v: _mean(ts) for v, ts in sorted(by_view.items())},
                       dict(sorted(log.frames.items())), len(log.timings) - len(seen))


# --- bytes ------------------------------------------------------------------------------
@dataclass(frozen=True)
class ByteSummary:
    received: dict[int, int]  # rendered step -> chunk bytes the server received (wire)
    particles_received: int  # summed over the rendered steps
    full_dump: dict[int, int] | None  # rendered step -> bytes of a full dump; None: unknown
    total_particles: int | None
    particles_source: str  # where the total came from, or why it is unknown
    full_dump_note: str  # why the full dump is unknown ("" when known)
    chunks_logged: int
    chunk_bytes_logged: int  # wire bytes of every chunk in the log (all steps)

    @property
    def received_total(self) -> int:
        return sum(self.received.values())

    @property
    def full_dump_total(self) -> int | None:
        return None if self.full_dump is None else sum(self.full_dump.values())


def total_particles(log: RunLog) -> tuple[int | None, str]:
    """The run's particle count and where it comes from (None and why when unknown)."""
    sim_events = [e for e in log.events if e.rank >= 0]
    for e in sim_events:
        n = e.detail.get("particles")
        if e.kind == EventKind.RUN_START and isinstance(n, int) and not isinstance(n, bool):
            return n, f"run_start event of sim rank {e.rank}"
    done = {e.rank: e.detail.get("particles") for e in sim_events if e.kind == EventKind.RANK_DONE}
    ranks = max([c.ranks for c in log.chunks] + [len(done)])
    if done and set(done) == set(range(ranks)) and all(
            isinstance(n, int) and not isinstance(n, bool) for n in done.values()):
        return sum(done.values()), f"sum of the rank_done events of {ranks} rank(s)"
    if log.spec is not None:
        by_step: dict[int, list[ChunkInfo]] = defaultdict(list)
        for c in log.chunks:
            by_step[c.step].append(c)
        for step, cs in sorted(by_step.items()):
            request = log.spec.request(step, cs[0].time_s, cs[0].prev_time_s)
            if (request is not None and request.regions is None and request.decimate == 1
                    and not request.visible_in
                    and {c.rank for c in cs} == set(range(cs[0].ranks))):
                return (sum(c.count for c in {c.rank: c for c in cs}.values()),
                        f"chunk counts of step {step} (all {cs[0].ranks} rank(s); the spec "
                        f"culls, decimates and hides no particle at that step)")
    return None, ("unknown: no run_start or complete set of rank_done events carries a particle "
                  "count, and no step has chunks of every rank that the logged spec leaves "
                  "unculled")


def byte_summary(log: RunLog, table: TimingTable | None = None) -> ByteSummary:
    table = table or timing_table(log)
    received = {s.step: s.bytes for s in table.steps}
    n, source = total_particles(log)
    per_step = defaultdict(int)
    for c in log.chunks:
        per_step[c.step] = max(per_step[c.step], c.particle_bytes)
    common = Counter(c.particle_bytes for c in log.chunks).most_common(1)
    full, note = None, ""
    if n is None:
        note = "the particle total is not in the log"
    elif not common:
        note = "no chunk in the log tells the bytes per particle"
    else:
        full = {s: n * per_step.get(s, common[0][0]) for s in received}
    return ByteSummary(received, sum(s.particles for s in table.steps), full, n, source, note,
                       len(log.chunks),
                       sum(c.nbytes for c in log.chunks))


# --- skipped and incomplete -------------------------------------------------------------
@dataclass(frozen=True)
class StepAccounting:
    rendered: list[int]
    incomplete: list[StepTiming]
    unrendered: list[int]  # steps with chunks in the log and no timing (skipped or failed)
    short: list[tuple[int, int, int]]  # (step, ranks logged, ranks named): chunks missing in the log
    server: dict | None  # the server's run_end summary
    ranks_done: dict[int, dict]  # sim rank -> rank_done detail
    errors: list[str]  # error event messages


def step_accounting(log: RunLog, table: TimingTable | None = None) -> StepAccounting:
    table = table or timing_table(log)
    rendered = [s.step for s in table.steps]
    by_step: dict[int, list[ChunkInfo]] = defaultdict(list)
    for c in log.chunks:
        by_step[c.step].append(c)
    short = [(s, len({c.rank for c in cs}), max(c.ranks for c in cs))
             for s, cs in sorted(by_step.items()) if len({c.rank for c in cs}) < max(c.ranks for c in cs)]
    ends = [e for e in log.events if e.kind == EventKind.RUN_END and e.rank < 0]
    return StepAccounting(
        rendered, [s for s in table.steps if s.incomplete],
        sorted(set(by_step) - set(rendered)), short, ends[-1].detail if ends else None,
        {e.rank: e.detail for e in log.events if e.kind == EventKind.RANK_DONE and e.rank >= 0},
        [e.message for e in log.events if e.kind == EventKind.ERROR])
