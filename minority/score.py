"""`minority report score SPEC RUN.mcap`: the oracle's predictions against the full run.

The actual run is known from the ranks' in situ Stats (speed histograms, kinetic energy,
displacement; every rank on a fixed cadence of simulated time), the frames the server
rendered and the chunk bytes it received, all in the run's MCAP log (read by
protocol.runlog.read_flow). The same event rules as the oracle's (gns.events) apply to the
actual series.

Critical windows: where the actual speed scale is at least half its peak (the main runout
phase). The equal-budget baseline renders the same number of frames on a fixed cadence over
the run and sends every particle at each of its steps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from minority.gns.events import events_from_series, fast_windows
from minority.protocol.flow import (
    MOVING_SPEED_FRACTION,
    SPEED_QUANTILE,
    histogram_quantile,
    moving_count,
)
from minority.protocol.logread import LogNote
from minority.protocol.runlog import FlowRecord, read_flow
from minority.protocol.spec import Spec
from minority.report import Notice, notice_on_stderr, say_notes

EVENT_TOLERANCE = 0.10  # targets: event times and displacement range within 10%



def load_run(path: str | Path, run: str | None = None,
             notice: Notice | None = None) -> FlowRecord:
    """The stats, frames and chunk sizes of one run of a log (`run` None: every record, for a
    log that holds one run). A truncated or damaged log is read up to its last complete
    chunk, said once to `notice` (default: a line on stderr) and kept in log_notes."""
    notes: list[LogNote] = []
    try:
        return read_flow(path, run, notes)
    finally:
        say_notes(notes, notice or notice_on_stderr("minority report score"))


def _inside(times, windows) -> int:
    t = np.asarray(times, dtype=np.float64)
    return int(sum(((t >= a) & (t <= b)).sum() for a, b in windows))


def score(spec: Spec, run: FlowRecord) -> dict:
    """Predicted vs actual, and the oracle's schedule vs a fixed cadence of equal budget."""
    scale = histogram_quantile(run.hist, SPEED_QUANTILE)
    actual = events_from_series(run.time_s, scale, run.kinetic_m2_s2)
    critical = fast_windows(run.time_s, scale)
    actual_times = {"failure_onset": actual.onset_s, "peak_motion": actual.peak_s,
                    "runout_end": actual.runout_end_s,
                    "runout_start": critical[0][0] if critical else actual.peak_s}
    interval = float(np.median(np.diff(run.time_s))) if len(run.time_s) > 1 else 0.0
    events = []
    for e in spec.events:
        if e.name not in actual_times:
            continue
        a = actual_times[e.name]
        err = e.time_s - a
        # 10 % of the actual time, but never finer than the stats cadence that measures it
        tol = max(EVENT_TOLERANCE * a, interval)
        row = {"event": e.name, "predicted_s": e.time_s, "actual_s": a, "error_s": err,
               "relative_error": err / a if a > 0 else None, "tolerance_s": tol,
               "within_tolerance": abs(err) <= tol}
        if e.interval_s is not None:  # an ensemble oracle's interval: did the run fall in it
            row.update(interval_s=list(e.interval_s),
                       within_interval=e.earliest_s - interval <= a <= e.latest_s + interval)
        events.append(row)
    predicted = spec.provenance.get("predicted", {})
    pred_disp = (predicted.get("displacement_range_m") or [0.0, float("nan")])[1]
    threshold = MOVING_SPEED_FRACTION * actual.peak_speed_m_s
    open_ = run.windows_open
    moving_in = moving_count(run.hist_in[open_], threshold).sum()
    moving_all = moving_count(run.hist[open_], threshold).sum()
    frame_times = [t for ts in run.frame_times_s.values() for t in ts]
    n_frames, duration = len(frame_times), float(run.time_s[-1])
    fixed_times = (np.arange(n_frames) + 0.5) * duration / max(n_frames, 1)
    oracle_in, fixed_in = _inside(frame_times, critical), _inside(fixed_times, critical)
    views = max(len(spec.views), 1)
    per_particle = (np.median([b for _, b in run.chunk_steps.values()])
                    if run.chunk_steps else 0.0)
    every_particle = sum(run.particles * b for _, b in run.chunk_steps.values())
    fixed_bytes = int(np.ceil(n_frames / views) * run.particles * per_particle)
    band = spec.deposit.displacement_max_m if spec.deposit is not None else None
    return {
        "events": events,
        **({"displacement_band_m": {"band": [band.low, band.high],
                                    "within": band.low <= run.max_displacement_m <= band.high}}
           if band is not None else {}),
        "displacement_max_m": {"predicted": pred_disp, "actual": run.max_displacement_m,
                               "relative_error": (pred_disp - run.max_displacement_m)
                               / run.max_displacement_m if run.max_displacement_m > 0
                               else None},
        "critical_windows_s": critical,
        "moving_speed_m_s": threshold,
        "roi_moving_fraction": float(moving_in / moving_all) if moving_all else None,
        "frames": {"oracle": n_frames, "oracle_in_critical": oracle_in,
                   "fixed_cadence_in_critical": fixed_in,
                   "ratio": oracle_in / fixed_in if fixed_in else None},
        "bytes": {"sent": run.chunk_bytes, "every_particle_at_rendered_steps": every_particle,
                  "fraction": run.chunk_bytes / every_particle if every_particle else None,
                  "fixed_cadence": fixed_bytes,
                  "ratio_to_fixed": run.chunk_bytes / fixed_bytes if fixed_bytes else None},
        "budget": {"frames": spec.budget.frames, "bytes": spec.budget.bytes},
        "stats_steps": len(run.time_s), "incomplete_stats_steps": run.incomplete_stats_steps,
        "particles": run.particles,
        # a truncated or damaged log: the score is of the messages of its complete chunks
        "log": {"complete": not run.log_notes,
                "notes": [{"kind": n.kind, "detail": n.detail} for n in run.log_notes]},
    }


def _pct(x) -> str:
    return "n/a" if x is None or x != x else f"{100 * x:+.1f}%"


def markdown(result: dict) -> str:
    lines = ["## Oracle score", ""]
    for n in result.get("log", {}).get("notes", []):
        lines += [f"**Log {n['kind']}**: {n['detail']}. The score covers those messages only.",
                  ""]
    ens = any("interval_s" in e for e in result["events"])
    lines += ["| event | predicted (s) | actual (s) | error | "
              "within 10 % (at least one stats interval) |"
              + (" inside the ensemble's interval (s) |" if ens else ""),
              "|---|---|---|---|---|" + ("---|" if ens else "")]
    for e in result["events"]:
        cell = ""
        if ens:
            cell = (f" {'yes' if e['within_interval'] else 'no'} ({e['interval_s'][0]:.3f}-"
                    f"{e['interval_s'][1]:.3f}) |" if "interval_s" in e else " n/a |")
        lines.append(f"| {e['event']} | {e['predicted_s']:.3f} | {e['actual_s']:.3f} | "
                     f"{_pct(e['relative_error'])} ({e['error_s'] * 1e3:+.0f} ms) | "
                     f"{'yes' if e['within_tolerance'] else 'no'} "
                     f"(±{e['tolerance_s'] * 1e3:.1f} ms) |" + cell)
    d, f, b = result["displacement_max_m"], result["frames"], result["bytes"]
    roi = result["roi_moving_fraction"]
    lines += ["", f"- displacement max: predicted {d['predicted']:.3f} m, actual "
                  f"{d['actual']:.3f} m ({_pct(d['relative_error'])})"
              + ("" if "displacement_band_m" not in result else
                 f"; the ensemble's band {result['displacement_band_m']['band'][0]:.3f}-"
                 f"{result['displacement_band_m']['band'][1]:.3f} m: "
                 + ("inside" if result["displacement_band_m"]["within"] else "outside")),
              f"- moving particles (faster than {result['moving_speed_m_s']:.3f} m/s) inside the "
              f"regions of interest: " + ("n/a" if roi is None else f"{100 * roi:.2f}%"),
              "- critical windows (speed >= half its peak): "
              + ", ".join(f"{a:.3f}-{b_:.3f} s" for a, b_ in result["critical_windows_s"]),
              f"- frames inside them: oracle {f['oracle_in_critical']} of {f['oracle']}, fixed "
              f"cadence with the same budget {f['fixed_cadence_in_critical']}"
              + ("" if f["ratio"] is None else f" (ratio {f['ratio']:.2f}x)"),
              f"- bytes sent: {b['sent']:,} = "
              + ("n/a" if b["fraction"] is None else f"{100 * b['fraction']:.1f}%")
              + f" of every particle at every rendered step; fixed cadence {b['fixed_cadence']:,}"
              + ("" if b["ratio_to_fixed"] is None else f" (ratio {b['ratio_to_fixed']:.2f})"),
              f"- {result['particles']:,} particles, {result['stats_steps']} stats steps"
              f" ({result['incomplete_stats_steps']} incomplete, left out)", ""]
    return "\n".join(lines)
