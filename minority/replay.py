"""`minority replay`: re-render a recorded run with its own spec or a new one, export it as a
VTK series for ParaView, or re-publish it to a running render server.

The re-rendering (and what a new spec may ask that the log does not hold) is
render_server.rerender's; the re-publishing protocol.republish's. This module wires them
to the command: warnings on stderr.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import zenoh

from minority.protocol.logread import LogNote
from minority.protocol.republish import PublishSummary, republish
from minority.protocol.spec import Spec
from minority.render_server.rerender import ReplaySummary, rerender
from minority.report import Notice, notice_on_stderr, say_notes


def replay(path: Path, spec: Spec | None = None, out: Path | None = None,
           vtk: Path | None = None, run: str | None = None, shadows: bool = False,
           progress: Callable[[str], None] | None = None,
           notice: Notice | None = None) -> ReplaySummary:
    """Re-render the log at `path` into out/{view}/{step:06d}.png (out None: render nothing)
    with `spec` (None: the log's last spec), and/or export its steps to a VTK series in `vtk`.
    A truncated or damaged log replays up to its last complete chunk, said once to `notice`
    (default: a line on stderr) and in the summary."""
    notes: list[LogNote] = []
    try:
        summary = rerender(path, spec, out, vtk, run, shadows, progress, notes)
    finally:
        say_notes(notes, notice or notice_on_stderr("minority replay"))
    summary.log_notes = notes
    return summary


def publish(path: Path, session: zenoh.Session, rate: float = 1.0, run: str | None = None,
            wait_s: float = 10.0, stop: threading.Event | None = None,
            notice: Notice | None = None) -> PublishSummary:
    """Re-publish the run's recorded chunks and specs at the recorded pacing (log times
    divided by `rate`; 0: as fast as possible) with the simulation's QoS. Waits up to wait_s
    for a subscriber of the run's chunks (a render server) before the first chunk. A
    truncated or damaged log is re-published up to its last complete chunk and said once to
    `notice` (default: a line on stderr)."""
    notes: list[LogNote] = []
    try:
        return republish(path, session, rate, run, wait_s, stop, notes)
    finally:
        say_notes(notes, notice or notice_on_stderr("minority replay"))
