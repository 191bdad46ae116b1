"""`minority replay`: re-render a recorded run with its own spec or a new one, export it as a
VTK series for ParaView, re-publish it to a running render server, or make movies of its
frames.

The re-rendering (and what a new spec may ask that the log does not hold) is
render_server.rerender's; the re-publishing protocol.republish's; the movies
minority.movie's. This module wires them to the command: warnings on stderr.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from minority.movie import DEFAULT_FPS, Movie, MovieError, write_movies
from minority.protocol import Frame, keys
from minority.protocol.logread import LogNote, read_log_noting
from minority.protocol.republish import PublishSummary, republish
from minority.protocol.runlog import log_run, log_specs
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


@dataclass
class MovieReplay:
    """What replay_movies did: the logged frames it took (view -> count) or the replay that
    re-rendered them, and the movies."""

    run: str
    out: Path
    logged: dict[str, int] | None = None  # None: the frames were re-rendered
    replayed: ReplaySummary | None = None  # the re-rendering, or the --vtk export
    movies: list[Movie] = field(default_factory=list)
    log_notes: list[LogNote] = field(default_factory=list)

    def text(self) -> str:
        lines = []
        if self.logged is not None:
            lines.append(f"run {self.run}: {sum(self.logged.values())} logged frames of "
                         f"{len(self.logged)} views written to {self.out} (not re-rendered)")
            lines += [n.line() for n in self.log_notes]
        if self.replayed is not None:
            lines.append(self.replayed.text())
        lines += [m.line() for m in self.movies]
        return "\n".join(lines)


def logged_frames(path: Path, run: str, notes: list[LogNote] | None = None
                  ) -> dict[str, list[tuple[int, bytes]]]:
    """The frames the server published for `run`, as logged: view -> [(step, PNG bytes)] in
    step order (a step logged twice: its last frame)."""
    views: dict[str, dict[int, bytes]] = {}
    for record in read_log_noting(path, notes, [keys.log_topic(run, keys.Topic.FRAME)]):
        frame = record.decode()
        if isinstance(frame, Frame):
            views.setdefault(frame.view, {})[frame.step] = frame.png
    return {view: sorted(steps.items()) for view, steps in views.items()}


def _pngs(folder: Path) -> dict[Path, int]:
    """PNG file -> modification time (ns) under folder/{view}/."""
    return {p: p.stat().st_mtime_ns for p in folder.glob("*/*.png")} if folder.is_dir() else {}


def _step_order(png: Path) -> tuple[str, int, str]:
    """By view, then by step ({step:06d}.png; a step past 999999 has more digits)."""
    return png.parent.name, int(png.stem) if png.stem.isdigit() else -1, png.name


def replay_movies(path: Path, spec: Spec | None = None, out: Path | None = None,
                  vtk: Path | None = None, run: str | None = None, shadows: bool = False,
                  fps: float = DEFAULT_FPS, animation: bool = True,
                  progress: Callable[[str], None] | None = None,
                  notice: Notice | None = None) -> MovieReplay:
    """out/{view}.mp4 (and out/{view}.webp with `animation`) of every view, beside its
    frames out/{view}/{step:06d}.png (out None: RUN-replay beside the log). Without `spec`
    the frames are the ones the server logged, written out, not re-rendered (a log holding
    no frames of the run is re-rendered with its own spec); with `spec` they are re-rendered
    and the movies take the frames this replay wrote (not older files in `out`). `vtk`: the
    steps exported as in `replay`. MovieError when no view has a frame."""
    out = out if out is not None else path.parent / f"{path.stem}-replay"
    say = notice or notice_on_stderr("minority replay")
    if spec is None:
        notes: list[LogNote] = []
        try:
            specs = log_specs(path, notes)
            run = log_run(path, specs, run, notes)
            frames = logged_frames(path, run, notes)
        finally:
            say_notes(notes, say)
        if frames:
            for s in specs:  # a view of the run's specs that never got a frame: said so
                for v in s.views if s.run == run else ():
                    frames.setdefault(v.name, [])
            result = MovieReplay(run, out, {v: len(f) for v, f in frames.items() if f},
                                 log_notes=notes)
            if vtk is not None:
                result.replayed = replay(path, None, None, vtk, run, shadows, progress, say)
            for view, steps in frames.items():
                if steps:
                    (out / view).mkdir(parents=True, exist_ok=True)
                for step, png in steps:
                    (out / view / f"{step:06d}.png").write_bytes(png)
            result.movies = write_movies({v: [png for _, png in f] for v, f in frames.items()},
                                         out, fps, animation, progress)
            return result
        if progress is not None:
            progress(f"the log holds no frames of run {run}: re-rendering with its spec")
    before = _pngs(out)
    summary = replay(path, spec, out, vtk, run, shadows, progress, say)
    written = sorted((p for p, t in _pngs(out).items() if before.get(p) != t), key=_step_order)
    views: dict[str, list[Path]] = {name: [] for name in summary.views}
    for png in written:
        if png.parent.name in views:
            views[png.parent.name].append(png)
    result = MovieReplay(summary.run, out, replayed=summary, log_notes=summary.log_notes)
    try:
        result.movies = write_movies(views, out, fps, animation, progress)
    except MovieError as exc:
        raise MovieError(f"run {summary.run}: {exc}: no view was rendered") from exc
    return result
