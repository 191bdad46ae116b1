"""Zenoh key expressions of docs/architecture.md, in one place.

    minority/{run}/spec                 queryable served by the render server (updates are put)
    minority/{run}/chunk/{step}/{rank}  a particle chunk
    minority/{run}/rank/{rank}          liveliness token of a live rank
    minority/{run}/frame/{view}         a rendered frame
    minority/{run}/timing               timing records
    minority/{run}/event                lifecycle events
    minority/{run}/stats                per-rank flow statistics (for scoring the oracle)

and the MCAP log topics the recorder files them under (step, rank live in the payload):

    minority/{run}/{kind}               spec, chunk, timing, event, stats
    minority/{run}/frame/{view}         frames, one topic per view
    minority/_rejected                  malformed messages, with the reason
"""

from __future__ import annotations

from dataclasses import dataclass

from minority.protocol import check

ROOT = "minority"
ALL_RUNS = "*"


class Topic:
    """The kind segment of a key; MCAP topics drop the step/rank suffixes."""

    SPEC = "spec"
    CHUNK = "chunk"
    RANK = "rank"
    FRAME = "frame"
    TIMING = "timing"
    EVENT = "event"
    STATS = "stats"


def _run(run: str) -> str:
    return run if run == ALL_RUNS else check.name(run, "run")


def spec(run: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.SPEC}"


def chunk(run: str, step: int, rank: int) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.CHUNK}/{step}/{rank}"


def chunks(run: str) -> str:
    """Every chunk of a run."""
    return f"{ROOT}/{_run(run)}/{Topic.CHUNK}/**"


def rank_token(run: str, rank: int) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.RANK}/{rank}"


def rank_tokens(run: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.RANK}/*"


def frame(run: str, view: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.FRAME}/{check.name(view, 'view')}"


def frames(run: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.FRAME}/*"


def timing(run: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.TIMING}"


def event(run: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.EVENT}"


def stats(run: str) -> str:
    return f"{ROOT}/{_run(run)}/{Topic.STATS}"


def everything(run: str = ALL_RUNS) -> str:
    """All messages of one run, or of every run."""
    return f"{ROOT}/{_run(run)}/**"


@dataclass(frozen=True)
class ParsedKey:
    run: str
    topic: str  # one of Topic
    rest: tuple[str, ...]  # step/rank for chunks, rank for tokens, view for frames

    @property
    def log_topic(self) -> str:
        """MCAP topic: per view for frames, per kind otherwise (step/rank live in the payload)."""
        return log_topic(self.run, self.topic, self.rest[0] if self.topic == Topic.FRAME else None)


_ARITY = {Topic.SPEC: 0, Topic.CHUNK: 2, Topic.RANK: 1, Topic.FRAME: 1, Topic.TIMING: 0,
          Topic.EVENT: 0, Topic.STATS: 0}


def parse(key: str) -> ParsedKey | None:
    """Split a concrete key; None when it is not one of ours."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT or parts[2] not in _ARITY:
        return None
    if not check.NAME_RE.match(parts[1]) or len(parts) != 3 + _ARITY[parts[2]]:
        return None
    rest = tuple(parts[3:])
    if not all(check.NAME_RE.match(p) for p in rest):
        return None
    return ParsedKey(parts[1], parts[2], rest)


# --- MCAP log topics ----------------------------------------------------------------------
REJECTED_LOG_TOPIC = f"{ROOT}/_rejected"  # malformed messages of every run, with the reason
ALL_VIEWS = "*"
LOGGED = (Topic.SPEC, Topic.CHUNK, Topic.FRAME, Topic.TIMING, Topic.EVENT, Topic.STATS)


@dataclass(frozen=True)
class LogTopic:
    """A parsed MCAP log topic (REJECTED_LOG_TOPIC is not one: it belongs to no run)."""

    run: str
    kind: str  # one of LOGGED
    view: str | None = None  # frames only

    def __str__(self) -> str:
        return log_topic(self.run, self.kind, self.view)


def log_topic(run: str, kind: str, view: str | None = None) -> str:
    """The topic the recorder logs a message of `kind` under; `run` ALL_RUNS or `view`
    ALL_VIEWS make a read_log pattern (frames: `view` None is every view)."""
    if kind not in LOGGED:
        raise ValueError(f"kind {kind!r} is not logged (one of {', '.join(LOGGED)})")
    base = f"{ROOT}/{_run(run)}/{kind}"
    if kind != Topic.FRAME:
        if view is not None:
            raise ValueError(f"only frames have a view in their log topic, not {kind}")
        return base
    view = ALL_VIEWS if view is None else view
    return f"{base}/{view if view == ALL_VIEWS else check.name(view, 'view')}"


def parse_log_topic(topic: str) -> LogTopic | None:
    """Split a concrete log topic; None when it is not one of ours (REJECTED_LOG_TOPIC,
    patterns and foreign topics included)."""
    parts = str(topic).split("/")
    if len(parts) < 3 or parts[0] != ROOT or parts[2] not in LOGGED:
        return None
    if len(parts) != (4 if parts[2] == Topic.FRAME else 3):
        return None
    if not all(check.NAME_RE.match(p) for p in (parts[1], *parts[3:])):
        return None
    return LogTopic(parts[1], parts[2], parts[3] if len(parts) == 4 else None)
