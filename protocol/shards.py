"""Sharded logs: a `minority serve` on N MPI ranks writes one log as N files.

Rank 0 writes the run's log as one process does (`run.mcap`: spec, its own share of the
chunks, frames, timing, events, stats); render rank k > 0 writes the chunks it received to
its shard next to it, `run.render{k}.mcap` (the same stem and suffix, `.render{k}` added).
A reader given the main file finds its shards here and reads all of them as one log, merged
by log time (each file's own order kept), so replay, report and score need no flag.
"""

from __future__ import annotations

import heapq
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Protocol

SHARD_INFIX = "render"  # run.render1.mcap, run.render2.mcap, ...


class Timed(Protocol):
    log_ns: int


def shard_path(path: str | Path, rank: int) -> Path:
    """Render rank `rank`'s shard of the log at `path` (rank >= 1)."""
    if rank < 1:
        raise ValueError(f"render rank {rank} has no shard: rank 0 writes the log itself")
    path = Path(path)
    return path.with_name(f"{path.stem}.{SHARD_INFIX}{rank}{path.suffix}")


def shard_paths(path: str | Path) -> list[Path]:
    """The shards of the log at `path` that exist, in render rank order ([] for a log of
    one process, or for a path that is itself a shard)."""
    path = Path(path)
    pattern = re.compile(re.escape(f"{path.stem}.{SHARD_INFIX}") + r"([1-9][0-9]{0,6})"
                         + re.escape(path.suffix) + r"\Z")
    found = []
    if path.parent.is_dir():
        for candidate in path.parent.glob(f"{path.stem}.{SHARD_INFIX}*{path.suffix}"):
            m = pattern.match(candidate.name)
            if m and candidate.is_file():
                found.append((int(m.group(1)), candidate))
    return [p for _, p in sorted(found)]


def merge_by_log_time(streams: Iterable[Iterator[Timed]]) -> Iterator[Timed]:
    """One stream of records from several, by log time (ns); records of one stream keep their
    order, equal times go to the earlier stream (rank 0 first)."""
    return heapq.merge(*streams, key=lambda record: record.log_ns)
