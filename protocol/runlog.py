"""One run's records in an MCAP log, read for what a caller needs of them: the timing report's
(RunLog: timing, events, chunk headers, frame counts, the spec), the oracle score's
(FlowRecord: the ranks' Stats, frame times, chunk sizes), and which run and specs a log holds.

Reads ask read_log for the topics they use only, so a complete (indexed) log opens just the
MCAP chunks that hold them; a log without a summary (its writer was killed) is read front to
back up to its last complete chunk, and the note saying so goes to `notes`.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minority.protocol import keys
from minority.protocol.errors import ProtocolError, SpecError
from minority.protocol.logread import MCAP_MAGIC, LogNote, read_log_noting, topic_counts
from minority.protocol.messages import ChunkMeta, Event, Frame, Stats, Timing
from minority.protocol.spec import Spec
from minority.protocol.wire import MessageKind, decode

Topic = keys.Topic


class RunLogError(ValueError):
    """A log does not hold what was asked of it (no such file, not MCAP, no such run, no
    timing, no stats, no spec, no chunks): bad input, on which the CLI exits 2."""


# --- chunk headers --------------------------------------------------------------------------
@dataclass(frozen=True)
class ChunkInfo:
    """What the readers need of one logged chunk (its arrays are not kept)."""

    step: int
    rank: int
    ranks: int  # ranks named in the header
    time_s: float  # simulated, s
    count: int  # particles
    nbytes: int  # wire bytes (header + arrays)
    particle_bytes: int  # array bytes per particle: positions + fields
    prev_time_s: float | None = None  # simulated time of the step before, s


def chunk_info(data: bytes) -> ChunkInfo:
    """A logged chunk's header numbers, read without a pass over its particle data."""
    env = decode(data, ChunkMeta, expect=MessageKind.CHUNK)  # header and sizes, no data pass
    m = env.meta
    per_particle = sum(a.dtype.itemsize * math.prod(a.shape[1:]) for a in env.arrays.values())
    return ChunkInfo(m.step, m.rank, m.ranks, m.time_s, m.count, len(data), per_particle,
                     m.prev_time_s)


def check_mcap(path: str | Path) -> Path:
    """`path`, refused (RunLogError) when it is missing, a directory or not MCAP."""
    path = Path(path)
    if not path.exists():
        raise RunLogError(f"{path}: no such file")
    if path.is_dir():
        raise RunLogError(f"{path}: is a directory, not an MCAP log")
    with open(path, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise RunLogError(f"{path}: not an MCAP file (no MCAP magic at its start)")
    return path


# --- the timing report's records ------------------------------------------------------------
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


_REPORTED = (Topic.CHUNK, Topic.TIMING, Topic.EVENT, Topic.SPEC)  # read; frames are counted


def read_run(path: str | Path, run: str | None = None,
             notes: list[LogNote] | None = None) -> RunLog:
    """One run of a log for the timing report (the only run with timing records unless `run`
    names one). Frames and rejected records are counted, from the summary's statistics when
    the log has them. Raises RunLogError on bad input, OSError when the file cannot be read."""
    path = check_mcap(path)
    accs: dict[str, _Acc] = defaultdict(_Acc)
    counts = topic_counts(path)
    if counts is None:  # no summary: one pass over everything, frames counted on the way
        topics, rejected = None, 0
    else:
        read = keys.ALL_RUNS if run is None else run
        topics = [keys.log_topic(read, kind) for kind in _REPORTED]
        rejected = counts.get(keys.REJECTED_LOG_TOPIC, 0)
        for topic, n in counts.items():
            parsed = keys.parse_log_topic(topic)
            if parsed is None or not n:
                continue
            acc = accs[parsed.run]  # every run in the log, as a read of everything finds them
            if parsed.kind == Topic.FRAME:
                acc.frames[parsed.view] += n
    for rec in read_log_noting(path, notes, topics):
        if rec.topic == keys.REJECTED_LOG_TOPIC:
            rejected += 1
            continue
        topic = keys.parse_log_topic(rec.topic)
        if topic is None:
            continue
        acc = accs[topic.run]
        try:
            if topic.kind == Topic.CHUNK:
                acc.chunks.append(chunk_info(rec.data))
            elif topic.kind == Topic.FRAME:
                acc.frames[topic.view] += 1
            elif topic.kind in (Topic.TIMING, Topic.EVENT, Topic.SPEC):
                message = rec.decode()
                if topic.kind == Topic.SPEC:
                    acc.spec = message
                else:
                    (acc.timings if topic.kind == Topic.TIMING else acc.events).append(message)
        except (ProtocolError, SpecError):
            acc.undecodable += 1
    runs = tuple(sorted(accs))
    if run is None:
        timed = [r for r in runs if accs[r].timings]
        if not timed:
            raise RunLogError(f"{path}: no timing records (runs in the log: "
                              f"{', '.join(runs) or 'none'}); record the run next to "
                              f"`minority serve`, which publishes them")
        if len(timed) > 1:
            raise RunLogError(f"{path}: timing records of several runs ({', '.join(timed)}); "
                              f"pick one with --run")
        run = timed[0]
    elif run not in accs or not accs[run].timings:
        raise RunLogError(f"{path}: no timing records of run {run!r} "
                          f"(runs in the log: {', '.join(runs) or 'none'})")
    a = accs[run]
    return RunLog(path, run, runs, a.timings, a.events, a.chunks, dict(a.frames), a.spec,
                  rejected, a.undecodable, tuple(notes or ()))


# --- the oracle score's records -------------------------------------------------------------
@dataclass
class FlowRecord:
    """What the log says the run did: the ranks' Stats summed per complete step, the frames'
    simulated times, the chunk bytes."""

    time_s: np.ndarray  # [k] stats times (s), complete steps only
    hist: np.ndarray  # [k, bins] all particles' speeds
    hist_in: np.ndarray  # [k, bins] particles inside the open regions
    kinetic_m2_s2: np.ndarray  # [k] mean |v|^2
    windows_open: np.ndarray  # [k] bool
    particles: int
    max_displacement_m: float
    frame_times_s: dict[str, list[float]] = field(default_factory=dict)  # per view
    chunk_bytes: int = 0
    chunk_steps: dict[int, tuple[float, int]] = field(default_factory=dict)  # step: (t, B/p)
    incomplete_stats_steps: int = 0
    log_notes: tuple[LogNote, ...] = ()  # the log is truncated or damaged: what was read of it


def read_flow(path: str | Path, run: str | None = None,
              notes: list[LogNote] | None = None) -> FlowRecord:
    """The stats, frame times and chunk sizes of one run of a log (`run` None: those of
    every run, for a log that holds one). Raises RunLogError when it holds no stats."""
    read = keys.ALL_RUNS if run is None else run
    topics = [keys.log_topic(read, Topic.STATS), keys.log_topic(read, Topic.FRAME),
              keys.log_topic(read, Topic.CHUNK)]
    by_step: dict[int, list[Stats]] = defaultdict(list)
    frames: dict[str, list[float]] = defaultdict(list)
    chunk_bytes, chunk_steps = 0, {}
    for rec in read_log_noting(path, notes, topics):
        topic = keys.parse_log_topic(rec.topic)
        if topic is not None and topic.kind == Topic.CHUNK:  # header only: no data pass
            c = chunk_info(rec.data)
            chunk_bytes += c.nbytes
            if c.count:
                chunk_steps.setdefault(c.step, (c.time_s, c.particle_bytes))
            continue
        msg = rec.decode()
        if isinstance(msg, Stats):
            by_step[msg.step].append(msg)
        elif isinstance(msg, Frame):
            frames[msg.view].append(msg.time_s)
    if not by_step:
        raise RunLogError(f"{path}: no stats records{'' if run is None else f' of run {run!r}'}"
                          " (was the run published with stats on?)")
    ranks = max(len({s.rank for s in v}) for v in by_step.values())
    steps = sorted(k for k, v in by_step.items() if len({s.rank for s in v}) == ranks)
    rows = [by_step[k] for k in steps]
    hist_in = np.array([np.sum([s.hist_in_regions for s in r], axis=0) for r in rows])
    hist_out = np.array([np.sum([s.hist_elsewhere for s in r], axis=0) for r in rows])
    count = np.array([sum(s.count for s in r) for r in rows])
    return FlowRecord(
        time_s=np.array([r[0].time_s for r in rows]), hist=hist_in + hist_out, hist_in=hist_in,
        kinetic_m2_s2=np.array([sum(s.speed_sq_sum_m2_s2 for s in r) for r in rows])
        / np.maximum(count, 1),
        windows_open=np.array([r[0].windows_open for r in rows]),
        particles=int(count.max()),
        max_displacement_m=max(s.max_displacement_m for r in rows for s in r),
        frame_times_s=dict(frames), chunk_bytes=chunk_bytes, chunk_steps=chunk_steps,
        incomplete_stats_steps=len(by_step) - len(steps), log_notes=tuple(notes or ()))


# --- which run, which specs -----------------------------------------------------------------
def log_specs(path: str | Path, notes: list[LogNote] | None = None) -> list[Spec]:
    """Every spec recorded in the log, in file order."""
    topics = [keys.log_topic(keys.ALL_RUNS, Topic.SPEC)]
    return [r.decode() for r in read_log_noting(path, notes, topics)]


def log_run(path: str | Path, specs: list[Spec], run: str | None = None,
            notes: list[LogNote] | None = None) -> str:
    """The run to replay: `run`, else that of the log's last spec, else of its first chunk."""
    if run is not None:
        return run
    if specs:
        return specs[-1].run
    for record in read_log_noting(path, notes, [keys.log_topic(keys.ALL_RUNS, Topic.CHUNK)]):
        topic = keys.parse_log_topic(record.topic)
        if topic is not None:
            return topic.run
    raise RunLogError(f"{path}: no chunks and no spec recorded (is it a minority MCAP log?)")
