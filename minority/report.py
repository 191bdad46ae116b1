"""`minority report RUN.mcap`: timing tables, bytes against a full dump, skipped and
incomplete steps, and plots, from the MCAP log of a run.

The numbers are protocol.costs' (what they mean is said there), read by protocol.runlog;
this module prints them (times in ms, bytes in MB = 1e6 B) and plots them.
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from minority.protocol.costs import byte_summary, step_accounting, timing_table
from minority.protocol.logread import LogNote
from minority.protocol.runlog import RunLog, read_run

MAX_STEP_ROWS = 200  # per-step table rows printed (first and last half beyond that)
MAX_LISTED = 20  # step numbers listed inline
MAX_TICKS = 12  # step labels on a plot's x axis
SERVER_COUNTS = ("steps_rendered", "steps_skipped", "timed_out", "evicted", "late", "duplicates",
                 "inbox_dropped", "queued_at_stop", "lost_in_transit", "ranks_lost", "rejected",
                 "view_errors", "frames", "chunks")

Notice = Callable[[str], None]  # where one-line warnings go (the CLI: stderr)


def notice_on_stderr(command: str) -> Notice:
    """A Notice printing "{command}: warning: {line}" on stderr."""
    def say(line: str) -> None:
        print(f"{command}: warning: {line}", file=sys.stderr, flush=True)
    return say


def say_notes(notes: list[LogNote], notice: Notice) -> None:
    for note in notes:
        notice(note.line())


def load_run(path: str | Path, run: str | None = None, notice: Notice | None = None) -> RunLog:
    """Read one run of an MCAP log (the only run with timing records unless `run` names one).
    Raises RunLogError on bad input, OSError when the file cannot be read. A truncated or
    damaged log is read up to its last complete chunk, said once to `notice` (default: a
    line on stderr) and recorded in RunLog.notes."""
    notes: list[LogNote] = []
    try:
        return read_run(path, run, notes)
    finally:
        say_notes(notes, notice or notice_on_stderr("minority report"))


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
