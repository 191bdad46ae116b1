"""The server's particle cache: complete pictures while the chunks carry only the regions.

A rank that keeps the cache (its chunks have a context count: protocol.messages.Chunk)
sends every particle outside the step's regions once, as context rows with their ids, and
again only when one moved (insitu.context). The server keeps the last state of each such
particle by id, with the rank that sent it and the step it was sent at, and draws it at
every later step until it is evicted (it entered a region, or left the rank). A step whose
chunks all keep the cache is completed: its fresh rows (inside the regions) plus every
cached row, so each view draws the whole scene, not only its regions.

Updates are applied in the order steps are released, every step (rendered or skipped); a
row is only replaced or evicted by a message of the same step or a later one, so a step
released late cannot undo newer state.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from minority.render_server.assemble import AssembledStep

Schema = tuple[tuple[str, str, tuple[int, ...]], ...]  # (name, dtype, trailing shape) per field


def _schema(fields: dict[str, np.ndarray]) -> Schema:
    return tuple(sorted((k, v.dtype.str, v.shape[1:]) for k, v in fields.items()))


class ParticleCache:
    """Cached particles of one run: ids [m] int64, positions [m, 3] float32 m, fields
    [m] or [m, k], and per row the sending rank, step and simulated time (s)."""

    def __init__(self) -> None:
        self._clear()
        self.schema_changes = 0  # times a different field set emptied the cache

    def _clear(self) -> None:
        self.ids = np.zeros(0, dtype=np.int64)
        self.positions = np.zeros((0, 3), dtype=np.float32)
        self.fields: dict[str, np.ndarray] = {}
        self.rank = np.zeros(0, dtype=np.int32)
        self.step = np.zeros(0, dtype=np.int64)
        self.time_s = np.zeros(0, dtype=np.float64)

    def __len__(self) -> int:
        return len(self.ids)

    def _keep(self, keep: np.ndarray) -> None:
        self.ids, self.positions = self.ids[keep], self.positions[keep]
        self.fields = {k: v[keep] for k, v in self.fields.items()}
        self.rank, self.step, self.time_s = self.rank[keep], self.step[keep], self.time_s[keep]

    def apply(self, step: AssembledStep) -> None:
        """Take the step's context: resets, then evictions, then new or moved rows."""
        if not step.context:
            return
        for c in step.context:
            if c.reset and len(self):
                self._keep((self.rank != c.rank) | (self.step > step.step))
        evict = [c.evict for c in step.context if len(c.evict)]
        if evict and len(self):
            self._keep(~np.isin(self.ids, np.concatenate(evict)) | (self.step > step.step))
        batch = [c for c in step.context if len(c.ids)]
        if not batch:
            return
        schema = _schema(batch[0].fields)
        if any(_schema(c.fields) != schema for c in batch[1:]):
            batch = [c for c in batch if _schema(c.fields) == schema]  # ranks disagree: one wins
        if self.fields and schema != _schema(self.fields):  # the field set changed
            self.schema_changes += bool(len(self))
            self._clear()
        ids = np.concatenate([c.ids for c in batch])
        take = None  # rows of the batch to add (None: all)
        if len(self):
            clash = np.isin(self.ids, ids)
            newer = clash & (self.step > step.step)  # a later step sent these: they stay
            if newer.any():
                take = np.flatnonzero(~np.isin(ids, self.ids[newer]))
            self._keep(~clash | newer)

        def rows(arrays: list[np.ndarray]) -> np.ndarray:
            a = np.concatenate(arrays)
            return a if take is None else a[take]

        added = ids if take is None else ids[take]
        self.ids = np.concatenate([self.ids, added])
        self.positions = np.concatenate([self.positions, rows([c.positions for c in batch])])
        self.fields = {k: np.concatenate([self.fields[k], rows([c.fields[k] for c in batch])])
                       if k in self.fields else rows([c.fields[k] for c in batch])
                       for k, _, _ in schema}
        self.rank = np.concatenate([self.rank, rows(
            [np.full(len(c.ids), c.rank, dtype=np.int32) for c in batch])])
        self.step = np.concatenate([self.step, np.full(len(added), step.step, dtype=np.int64)])
        self.time_s = np.concatenate([self.time_s, np.full(len(added), step.time_s)])

    def complete(self, step: AssembledStep) -> AssembledStep:
        """The step with every cached particle added (`completed`), when all its chunks
        keep the cache and the cache holds the step's fields; else the step as it is."""
        if not step.tracked:
            return step
        if len(self) and _schema(step.fields) != _schema(self.fields):
            return step  # the cache holds other fields (a spec change): regions only
        n = len(self)
        if n == 0:
            return dataclasses.replace(step, completed=True)
        fields = {k: np.concatenate([v, self.fields[k]]) for k, v in step.fields.items()}
        return dataclasses.replace(
            step, positions=np.concatenate([step.positions, self.positions]), fields=fields,
            completed=True, cached=n,
            cache_age_s=max(0.0, float(step.time_s - self.time_s.min())),
            cache_age_steps=max(0, int(step.step - self.step.min())))


def complete_step(cache: ParticleCache, step: AssembledStep) -> AssembledStep:
    """Apply the step's context to the cache and return the step completed from it."""
    cache.apply(step)
    return cache.complete(step)

