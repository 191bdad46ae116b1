"""`minority report RUN.mcap`: timing tables, bytes against a full dump, skipped and
incomplete steps, and plots, from the MCAP log of a run.

The render server publishes one Timing per (step, view) it renders: receive_s and setup_s
belong to the step (the same for each of its views), render_s to the view. So an *in situ
step* costs receive + setup + the sum of its views' render times, as in the reference
paper's table (Kumar et al. 2022, "In situ visualization time for each step"); shares are
of the mean total. Times are kept in s and printed in ms; bytes are printed in MB (1e6 B).

A *full dump* is every particle of the run, positions plus the fields the chunks carry,
at every rendered step (array bytes only: `particles * bytes per particle`). The particle
total comes from the events (sim rank 0's `run_start` detail, or the ranks' `rank_done`
details) or from the chunk counts of a step at which the logged spec culls nothing; when
none of these is in the log the report says so instead of guessing.
"""

from __future__ import annotations

import math
import sys
import warnings
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.log import (
    MCAP_MAGIC,
    REJECTED_TOPIC,
    LogDamagedWarning,
    LogRecord,
    LogTruncatedWarning,
    read_log,
)
from minority.protocol.messages import ChunkMeta, Event, EventKind, Timing
from minority.protocol.spec import Spec
from minority.protocol.wire import MessageKind, decode

MAX_STEP_ROWS = 200  # per-step table rows printed (first and last half beyond that)
MAX_LISTED = 20  # step numbers listed inline
MAX_TICKS = 12  # step labels on a plot's x axis
SERVER_COUNTS = ("steps_rendered", "steps_skipped", "timed_out", "evicted", "late", "duplicates",
                 "inbox_dropped", "rejected", "view_errors", "frames", "chunks")


class ReportError(ValueError):
    """Bad input (no such file, not MCAP, nothing to report): the CLI exits 2."""


# --- logs that did not end cleanly ------------------------------------------------------
@dataclass(frozen=True)
class LogNote:
    """What read_log said of a log that does not end cleanly: "truncated" (no MCAP footer:
    its writer was killed or stopped) or "damaged" (an unreadable record inside). Either way
    the messages of its complete chunks before that point were read, and only those."""

    kind: str  # "truncated" or "damaged"
    detail: str  # read_log's warning, on one line

    def line(self) -> str:
        if self.kind == "damaged":
            return (f"log damaged: {self.detail}; only the messages of the complete chunks "
                    "before it were used")
        return f"log truncated: {self.detail}"


Notice = Callable[[str], None]  # where one-line warnings go (the CLI: stderr)


def notice_on_stderr(command: str) -> Notice:
    """A Notice printing "{command}: warning: {line}" on stderr."""
    def say(line: str) -> None:
        print(f"{command}: warning: {line}", file=sys.stderr, flush=True)
    return say


def read_log_noting(path: str | Path, notes: list[LogNote],
                    topics: Iterable[str] | None = None) -> Iterator[LogRecord]:
    """read_log, with its LogTruncatedWarning or LogDamagedWarning added to `notes` (once
    per distinct note) instead of shown; any other warning passes on as it was."""
    records = read_log(path, topics)
    while True:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", LogTruncatedWarning)
            warnings.simplefilter("always", LogDamagedWarning)
            record = next(records, None)
        for w in caught:
            if issubclass(w.category, (LogTruncatedWarning, LogDamagedWarning)):
                kind = "damaged" if issubclass(w.category, LogDamagedWarning) else "truncated"
                note = LogNote(kind, " ".join(str(w.message).split()))
                if note not in notes:
                    notes.append(note)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno,
                                       source=w.source)
        if record is None:
            return
        yield record


def say_notes(notes: list[LogNote], notice: Notice) -> None:
    for note in notes:
        notice(note.line())


@dataclass(frozen=True)
class ChunkInfo:
    """What the report needs of one logged chunk (its arrays are not kept)."""

    step: int
    rank: int
    ranks: int  # ranks named in the header
    time_s: float  # simulated, s
    count: int  # particles
    nbytes: int  # wire bytes (header + arrays)
    particle_bytes: int  # array bytes per particle: positions + fields
    prev_time_s: float | None = None  # simulated time of the step before, s


@dataclass
class RunLog:
    path: Path
    run: str
    runs: tuple[str, ...]  # every run id in the log
    timings: list[Timing]
    events: list[Event]
    chunks: list[ChunkInfo]
    frames: dict[str, int]  # view -> Frame records in the log
    spec: Spec | None  # the last spec of the run in the log
    rejected: int = 0  # records on minority/_rejected (every run)
    undecodable: int = 0  # stored records of this run that did not decode
    notes: tuple[LogNote, ...] = ()  # the log is truncated or damaged: what was read of it


@dataclass
class _Acc:  # one run's records while reading
    timings: list = field(default_factory=list)
    events: list = field(default_factory=list)
    chunks: list = field(default_factory=list)
    frames: Counter = field(default_factory=Counter)
    spec: Spec | None = None
    undecodable: int = 0


def chunk_info(data: bytes) -> ChunkInfo:
    """A logged chunk's header numbers, read without a pass over its particle data."""
    env = decode(data, ChunkMeta, expect=MessageKind.CHUNK)  # header and sizes, no data pass
    m = env.meta
    per_particle = sum(a.dtype.itemsize * math.prod(a.shape[1:]) for a in env.arrays.values())
    return ChunkInfo(m.step, m.rank, m.ranks, m.time_s, m.count, len(data), per_particle,
                     m.prev_time_s)


def load_run(path: str | Path, run: str | None = None, notice: Notice | None = None) -> RunLog:
    """Read one run of an MCAP log (the only run with timing records unless `run` names one).
    Raises ReportError on bad input, OSError when the file cannot be read. A truncated or
    damaged log is read up to its last complete chunk, said once to `notice` (default: a
    line on stderr) and recorded in RunLog.notes."""
    path = Path(path)
    if not path.exists():
        raise ReportError(f"{path}: no such file")
    if path.is_dir():
        raise ReportError(f"{path}: is a directory, not an MCAP log")
    with open(path, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise ReportError(f"{path}: not an MCAP file (no MCAP magic at its start)")
    notes: list[LogNote] = []
    try:
        return _load_run(path, run, notes)
    finally:
        say_notes(notes, notice or notice_on_stderr("minority report"))


def _load_run(path: Path, run: str | None, notes: list[LogNote]) -> RunLog:
    accs: dict[str, _Acc] = defaultdict(_Acc)
    rejected = 0
    for rec in read_log_noting(path, notes):
        if rec.topic == REJECTED_TOPIC:
            rejected += 1
            continue
        parts = rec.topic.split("/")
        if len(parts) < 3:
            continue
        acc, kind = accs[parts[1]], parts[2]
        try:
            if kind == "chunk":
                acc.chunks.append(chunk_info(rec.data))
            elif kind == "frame":
                acc.frames[parts[3] if len(parts) > 3 else "?"] += 1
            elif kind in ("timing", "event", "spec"):
                message = rec.decode()
                {"timing": acc.timings, "event": acc.events}.get(kind, []).append(message)
                if kind == "spec":
                    acc.spec = message
        except (ProtocolError, SpecError):
            acc.undecodable += 1
    runs = tuple(sorted(accs))
    if run is None:
        timed = [r for r in runs if accs[r].timings]
        if not timed:
            raise ReportError(f"{path}: no timing records (runs in the log: "
                              f"{', '.join(runs) or 'none'}); record the run next to "
                              f"`minority serve`, which publishes them")
        if len(timed) > 1:
            raise ReportError(f"{path}: timing records of several runs ({', '.join(timed)}); "
                              f"pick one with --run")
        run = timed[0]
    elif run not in accs or not accs[run].timings:
        raise ReportError(f"{path}: no timing records of run {run!r} "
                          f"(runs in the log: {', '.join(runs) or 'none'})")
    a = accs[run]
    return RunLog(path, run, runs, a.timings, a.events, a.chunks, dict(a.frames), a.spec,
                  rejected, a.undecodable, tuple(notes))


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


# --- output -----------------------------------------------------------------------------
def _ms(s: float) -> str:
    return f"{s * 1e3:.3f}"


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _mb(b: float) -> str:
    return f"{b / 1e6:.3f}"


def _steps(steps: list[int]) -> str:
    shown = ", ".join(map(str, steps[:MAX_LISTED]))
    return shown + (f", ... ({len(steps) - MAX_LISTED} more)" if len(steps) > MAX_LISTED else "")


def markdown(log: RunLog, plot_paths: list[Path] = ()) -> str:
    t = timing_table(log)
    b = byte_summary(log, t)
    acc = step_accounting(log, t)
    p = t.per_step
    out = [f"# minority report: run `{log.run}`", "",
           f"Log `{log.path}`: {len(log.timings)} timing, {len(log.chunks)} chunk, "
           f"{sum(log.frames.values())} frame and {len(log.events)} event records"
           + (f"; {log.rejected} rejected" if log.rejected else "")
           + (f"; {log.undecodable} undecodable" if log.undecodable else "") + ".", ""]
    out += [f"**Log {n.kind}**: {n.detail}. The tables and plots below cover those messages "
            "only." for n in log.notes]
    out += [""] if log.notes else []
    out += ["## Time per in situ step", "",
            f"Mean over {p.count} rendered steps, views: {len(t.per_view)}. Receive and setup "
            "are once per step, render is the sum of the step's views.", "",
            "| | mean per in situ step (ms) | share |", "|---|---|---|"]
    out += [f"| {part} | {_ms(getattr(p, f'{part}_s'))} | {_pct(p.share(part))} |"
            for part in ("receive", "setup", "render")]
    out += [f"| total | {_ms(p.total_s)} | 100.0 % |", "", "## Per view", "",
            "| view | frames logged | timing records | receive (ms) | setup (ms) | render (ms) "
            "| total (ms) | receive % | setup % | render % |", "|---|---|---|---|---|---|---|---|---|---|"]
    for view in sorted(set(t.per_view) | set(t.frames)):
        v = t.per_view.get(view)
        if v is None:
            out.append(f"| {view} | {t.frames.get(view, 0)} | 0 | | | | | | | |")
            continue
        out.append(f"| {view} | {t.frames.get(view, 0)} | {v.count} | {_ms(v.receive_s)} | "
                   f"{_ms(v.setup_s)} | {_ms(v.render_s)} | {_ms(v.total_s)} | "
                   f"{_pct(v.share('receive'))} | {_pct(v.share('setup'))} | "
                   f"{_pct(v.share('render'))} |")
    out += ["", "## Bytes received vs a full dump", "",
            f"- particles in the run: {b.total_particles} ({b.particles_source})"
            if b.total_particles is not None else f"- particles in the run: {b.particles_source}",
            f"- received at the {len(b.received)} rendered steps: {_mb(b.received_total)} MB "
            f"(chunk wire bytes, from the timing records)"]
    if b.full_dump_total is not None:
        ratio = b.received_total / b.full_dump_total if b.full_dump_total else float("nan")
        out.append(f"- full dump at the same steps (every particle, positions + the same "
                   f"fields, array bytes only): {_mb(b.full_dump_total)} MB; received / full "
                   f"dump = {_pct(ratio)} (received bytes include the message headers)")
    if b.total_particles:
        dumped = b.total_particles * len(b.received)
        out.append(f"- particles received: {b.particles_received} of {dumped} "
                   f"({b.total_particles} x {len(b.received)} steps) = "
                   f"{_pct(b.particles_received / dumped)}")
    else:
        out.append(f"- full dump: unknown ({b.full_dump_note})")
    out += [f"- chunks in the log: {b.chunks_logged}, {_mb(b.chunk_bytes_logged)} MB (every "
            "logged step)", "", "## Skipped and incomplete steps", "",
            f"- rendered steps: {len(acc.rendered)}",
            f"- incomplete rendered steps: {len(acc.incomplete)}"
            + "".join(f"; step {s.step}: {s.ranks_received} of {s.ranks_expected} ranks"
                      for s in acc.incomplete[:MAX_LISTED]),
            f"- steps with chunks in the log but not rendered: {len(acc.unrendered)}"
            + (f" ({_steps(acc.unrendered)})" if acc.unrendered else ""),
            f"- steps with chunks missing from the log: {len(acc.short)}"
            + "".join(f"; step {s}: {got} of {named} ranks" for s, got, named in acc.short[:MAX_LISTED])]
    if acc.server is None:
        out.append("- server run_end summary: none in the log (the server did not stop cleanly, "
                   "or the log was cut short)")
    else:
        out.append("- server run_end summary: " + ", ".join(
            f"{k} {acc.server[k]}" for k in SERVER_COUNTS if k in acc.server))
    if acc.ranks_done:
        total = Counter()
        for d in acc.ranks_done.values():
            total.update({k: d[k] for k in ("scheduled", "sent", "dropped")
                          if isinstance(d.get(k), int)})
        out.append(f"- sim ranks done: {len(acc.ranks_done)}; chunks scheduled "
                   f"{total['scheduled']}, sent {total['sent']}, dropped {total['dropped']}")
    out.append(f"- error events: {len(acc.errors)}" + (f" (first: {acc.errors[0][:200]})"
                                                       if acc.errors else ""))
    out += ["", "## Every rendered step", "",
            "| step | time (s) | views | receive (ms) | setup (ms) | render (ms) | total (ms) "
            "| particles | ranks | received (MB) | full dump (MB) |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    rows = t.steps
    if len(rows) > MAX_STEP_ROWS:
        half = MAX_STEP_ROWS // 2
        rows = rows[:half] + [None] + rows[-half:]
    for s in rows:
        if s is None:
            out.append(f"| ... {len(t.steps) - MAX_STEP_ROWS} steps ... | | | | | | | | | | |")
            continue
        dump = _mb(b.full_dump[s.step]) if b.full_dump is not None else "?"
        ranks = f"{s.ranks_received}/{s.ranks_expected}" + (" incomplete" if s.incomplete else "")
        out.append(f"| {s.step} | {s.time_s:.4f} | {len(s.views)} | {_ms(s.receive_s)} | "
                   f"{_ms(s.setup_s)} | {_ms(s.render_s)} | {_ms(s.total_s)} | {s.particles} | "
                   f"{ranks} | {_mb(s.bytes)} | {dump} |")
    if plot_paths:
        out += ["", "Plots: " + ", ".join(f"`{q}`" for q in plot_paths)]
    return "\n".join(out) + "\n"


def plots(log: RunLog, out_dir: str | Path) -> list[Path]:
    """Write `{stem}.timing.png` (receive / setup / render per rendered step, stacked, ms)
    and `{stem}.bytes.png` (MB received per rendered step vs a full dump) to `out_dir`."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # Agg, no pyplot state
    from matplotlib.figure import Figure

    t = timing_table(log)
    b = byte_summary(log, t)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = log.path.stem if len(log.runs) == 1 else f"{log.path.stem}.{log.run}"
    steps = [s.step for s in t.steps]
    x = range(len(steps))  # one slot per rendered step: scheduled steps are not evenly spaced
    ticks = x[::max(1, len(steps) // MAX_TICKS)]

    def axes(fig, ylabel: str, title: str):
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        cut = "".join(f" (log {n.kind})" for n in log.notes)
        ax.set(xlabel="simulation step (rendered steps, in order)", ylabel=ylabel,
               title=f"run {log.run}: {title}{cut}", xticks=ticks, xticklabels=[steps[i] for i in ticks])
        return ax

    fig = Figure(figsize=(8, 4.5), dpi=100)
    ax = axes(fig, "time (ms)", "time per in situ step")
    bottom = [0.0] * len(x)
    for part, color in (("receive", "tab:blue"), ("setup", "tab:orange"), ("render", "tab:green")):
        ms = [getattr(s, f"{part}_s") * 1e3 for s in t.steps]
        ax.bar(x, ms, 0.8, bottom=bottom, label=part, color=color)
        bottom = [a + m for a, m in zip(bottom, ms, strict=True)]
    bad = [(i, s.total_s * 1e3) for i, s in enumerate(t.steps) if s.incomplete]
    if bad:
        ax.plot(*zip(*bad, strict=True), "rx", label="incomplete")
    ax.legend()
    timing_png = out_dir / f"{stem}.timing.png"
    fig.savefig(timing_png)

    fig = Figure(figsize=(8, 4.5), dpi=100)
    ax = axes(fig, "MB (1e6 bytes)", "bytes per rendered step")
    ax.bar(x, [b.received[s] / 1e6 for s in steps], 0.8, label="received", color="tab:blue")
    if b.full_dump is not None:
        ax.plot(x, [b.full_dump[s] / 1e6 for s in steps], "k.-", label="full dump")
    ax.legend()
    bytes_png = out_dir / f"{stem}.bytes.png"
    fig.savefig(bytes_png)
    return [timing_png, bytes_png]


def report(path: str | Path, out_dir: str | Path | None = None, make_plots: bool = True,
           run: str | None = None, notice: Notice | None = None) -> str:
    """Load a log, write the plots (beside the log unless `out_dir`), return the markdown
    (which says so when the log is truncated or damaged; so does a line to `notice`)."""
    log = load_run(path, run, notice)
    written = plots(log, out_dir if out_dir is not None else log.path.parent) if make_plots else []
    return markdown(log, written)
