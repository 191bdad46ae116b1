"""What a rank's messages carry: the culled particle fields of a chunk and the flow
statistics of a Stats message, from what the caller hands over at one step (`Particles`).

* `Particles`: positions [n, 3] m, ids [n] int64 (decimation and the server's cache go by
  them), and fields by name, [n] or [n, k] arrays; `field` gives one of them at some rows,
  float32 on the wire (int64 for `id`, taken from the ids), and `X_magnitude` from a given
  [n, k] `X` when the caller did not give it.
* `cull_rows` picks the particles inside the requested regions (all when none), keeps every
  `decimate`-th of them by id (`id % decimate == 0`) and, for views with occlusion culling,
  those that may show (insitu.visibility); `chunk_fields` takes positions and the requested
  fields of given rows; `cull` is both. Bytes per particle: `particle_bytes`.
* `flow_stats` sums up a rank's particles for a `Stats` message (minority/{run}/stats):
  count, sum of |v|^2, max |v|, max |displacement|, and the speed histograms of the particles
  inside the regions of the spec's open windows and elsewhere.
"""

from __future__ import annotations

import math
import threading
import weakref
from dataclasses import dataclass, field

import numpy as np

from minority.insitu.visibility import visible_mask
from minority.protocol.fields import FIELDS
from minority.protocol.messages import SPEED_BINS, SPEED_EDGES_M_S, Stats
from minority.protocol.spec import DataRequest, Region, inside_mask

POSITION_BYTES = 12  # positions [n, 3] float32
ID_FIELD = "id"
MAGNITUDE = "_magnitude"


class BufferPool:
    """Arrays reused from one snapshot to the next: a fresh array of a few MB costs its page
    faults on first touch, about as much again as the copy into it. At most `keep` free
    arrays of each shape and dtype are kept. Thread-safe (the caller copies, the sender's
    last reference gives back)."""

    def __init__(self, keep: int = 8):
        self.keep = keep
        self._free: dict[tuple, list[np.ndarray]] = {}
        self._lock = threading.Lock()

    def copy(self, a: np.ndarray) -> np.ndarray:
        key = (a.shape, a.dtype.str)
        with self._lock:
            free = self._free.get(key)
            out = free.pop() if free else None
        if out is None:
            out = np.empty(a.shape, a.dtype)
        np.copyto(out, a)
        return out

    def give(self, arrays: list[np.ndarray]) -> None:
        with self._lock:
            for a in arrays:
                free = self._free.setdefault((a.shape, a.dtype.str), [])
                if len(free) < self.keep:
                    free.append(a)


@dataclass
class Particles:
    """One rank's particles at one step, as the caller gives them (not copied: the publisher
    takes a `snapshot` of what it needs before the call returns, or reads them later when
    they are lent: insitu.lend). positions [n, 3] m; ids [n] int64 >= 0; fields: name -> [n]
    or [n, k] values (SI units; protocol.fields names the usual ones), or (lent) a function
    of no argument returning them."""

    positions: np.ndarray
    ids: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.positions.shape[0]

    def has(self, name: str) -> bool:
        """Whether `field(name)` can be computed: given, `id`, or the magnitude of a given
        vector field."""
        if name in self.fields or name == ID_FIELD:
            return True
        base = name.removesuffix(MAGNITUDE)
        if base == name or base not in self.fields:
            return False
        given = self.fields[base]  # a function (a lent step's; insitu.lend): not called yet
        return callable(given) or given.ndim == 2

    def snapshot(self, names, pool: BufferPool | None = None, owned=()) -> Particles:
        """A copy of what `names` read (positions, ids and each named field, or the vector a
        `X_magnitude` is computed from), for the sender thread to cull and encode after the
        caller has moved on and changed its arrays; into `pool`'s arrays, which go back to
        it once the snapshot is gone. Fields named in `owned` are nobody else's (computed
        for this step): kept, not copied."""
        keep: dict[str, np.ndarray] = {}
        for name in names:
            base = name.removesuffix(MAGNITUDE)
            if name in self.fields:
                keep[name] = self.fields[name]
            elif base in self.fields:
                keep[base] = self.fields[base]
        if pool is None:
            return Particles(self.positions.copy(), self.ids.copy(),
                             {k: v if k in owned else v.copy() for k, v in keep.items()})
        copied = {k: pool.copy(v) for k, v in keep.items() if k not in owned}
        snap = Particles(pool.copy(self.positions), pool.copy(self.ids),
                         {k: copied.get(k, v) for k, v in keep.items()})
        weakref.finalize(snap, pool.give, [snap.positions, snap.ids, *copied.values()])
        return snap

    @property
    def nbytes(self) -> int:
        return (self.positions.nbytes + self.ids.nbytes
                + sum(v.nbytes for v in self.fields.values()))

    def field(self, name: str, rows: np.ndarray | None = None) -> np.ndarray:
        """The wire array of field `name` at `rows` [m] (None: all n): float32 [m] or [m, k]
        (`id`: int64 [m] of the ids). KeyError when `has(name)` is false."""
        def take(a: np.ndarray) -> np.ndarray:
            return a if rows is None else a[rows]

        if name == ID_FIELD:
            return take(self.ids).astype(np.int64)
        if name in self.fields:
            return take(self.fields[name]).astype(np.float32)
        base = name.removesuffix(MAGNITUDE)
        if base != name and base in self.fields and self.fields[base].ndim == 2:
            return np.linalg.norm(take(self.fields[base]), axis=1).astype(np.float32)
        raise KeyError(name)


def particle_bytes(fields) -> int:
    """Wire bytes per particle of a chunk with positions and `fields` (those of the
    protocol's table, protocol.fields)."""
    return POSITION_BYTES + sum(FIELDS[f].components * np.dtype(FIELDS[f].dtype).itemsize
                                for f in fields if f in FIELDS)


def cull(p: Particles, request: DataRequest, radius_m: float = 0.0) -> dict[str, np.ndarray]:
    """Chunk fields for one request: `positions` [m, 3] float32 (m) and each requested
    field the particles have (the others are skipped; the caller reports them), of the m
    particles `cull_rows` keeps."""
    return chunk_fields(p, cull_rows(p, request, radius_m), request.fields)


def cull_rows(p: Particles, request: DataRequest, radius_m: float = 0.0,
              inside: np.ndarray | None = None) -> np.ndarray | None:
    """Rows [m] of the particles a request needs now, None for all n: those inside the
    request's regions (all when it has none; `inside` [n] bool when the caller computed
    it), whose id is a multiple of its `decimate` and, when the request names views to cull
    for, that may show in one of them as spheres of `radius_m` (m; insitu.visibility)."""
    keep = None
    if request.regions is not None:
        keep = inside if inside is not None else inside_mask(p.positions, request.regions)
    if request.decimate > 1:
        every = p.ids % request.decimate == 0
        keep = every if keep is None else keep & every
    idx = None if keep is None else np.flatnonzero(keep)
    if request.visible_in and radius_m > 0.0:
        rows = np.arange(p.n) if idx is None else idx
        x, pid = p.positions[rows], p.ids[rows]
        seen = np.zeros(len(rows), dtype=bool)
        for view, regions in request.visible_in:
            # among the particles the server draws in this view: its regions, its stride
            own = np.ones(len(rows), dtype=bool) if regions is None else inside_mask(x, regions)
            if view.decimate > 1:
                own &= pid % view.decimate == 0
            sub = np.flatnonzero(own)
            seen[sub[visible_mask(x[sub], view, radius_m)]] = True
        idx = rows[seen]
    return idx


def scene_visible(p: Particles, request: DataRequest, radius_m: float) -> np.ndarray | None:
    """[n] bool: the particles that may show in one of the request's culled views when every
    particle is drawn (the server completes the step from its cache), each view among its
    own stride; None when the request culls for no view (or no radius is given)."""
    if not request.visible_in or radius_m <= 0.0:
        return None
    seen = np.zeros(p.n, dtype=bool)
    for view, _ in request.visible_in:
        sub = np.arange(p.n) if view.decimate <= 1 else np.flatnonzero(
            p.ids % view.decimate == 0)
        seen[sub[visible_mask(p.positions[sub], view, radius_m)]] = True
    return seen


def chunk_fields(p: Particles, rows: np.ndarray | None,
                 names: tuple[str, ...] | list[str]) -> dict[str, np.ndarray]:
    """`positions` [m, 3] float32 (m) and the fields of `names` the particles have (float32;
    int64 for `id`) at `rows` [m] (None: all n)."""
    x = p.positions if rows is None else p.positions[rows]
    out = {"positions": x.astype(np.float32)}
    for name in names:
        if p.has(name):
            out[name] = p.field(name, rows)
    return out


# SPEED_EDGES_M_S with -inf and +inf around: bin i holds speeds in [_BIN_BOUNDS[i], _BIN_BOUNDS[i + 1])
_BIN_BOUNDS = np.concatenate([[-np.inf], np.asarray(SPEED_EDGES_M_S), [np.inf]])


def speed_bins(speed_m_s: np.ndarray) -> np.ndarray:
    """[n] intp: the Stats histogram bin of each speed [n] (m/s, finite, >= 0); equal to
    np.searchsorted(SPEED_EDGES_M_S, speed, side="right") (tested), at a third of its cost:
    the edges are 10 per decade from 1e-4 m/s, so log10 gives the bin to within one, and
    one comparison with each neighbouring edge makes it exact."""
    with np.errstate(divide="ignore"):  # speed 0: log10 = -inf, bin 0
        k = np.floor(10.0 * np.log10(speed_m_s))
    k = np.clip(k + (1.0 - 10.0 * math.log10(SPEED_EDGES_M_S[0])), 0.0, SPEED_BINS - 1.0)
    k = k.astype(np.intp)
    k -= speed_m_s < _BIN_BOUNDS[k]
    k += speed_m_s >= _BIN_BOUNDS[k + 1]
    return k


STATS_FIELDS = ("velocity", "displacement")  # what flow_stats reads (displacement: optional)
STATS_READS = STATS_FIELDS + tuple(f + MAGNITUDE for f in STATS_FIELDS)  # or their magnitudes


def flow_stats(run: str, rank: int, step: int, time_s: float, p: Particles,
               regions: tuple[Region, ...] | None) -> Stats:
    """The Stats of a rank's particles at one step (time_s in s), from their `velocity`
    [n, 3] m/s (or `velocity_magnitude` [n]) and, for the max displacement, `displacement`
    [n, 3] m (or `displacement_magnitude`; without either it is reported as 0). `regions`:
    the spec's `active_regions(time_s)`; None: every particle counts as inside (an open
    window needs them all), (): none does (no window open, or no spec yet; windows_open is
    then False). Vectorized: a few passes over [n] and [n, 3] arrays (about 0.3 ms at 13k
    particles). KeyError when no velocity is given."""
    f = p.fields
    if "velocity" in f:
        v = f["velocity"]
        speed_sq = np.einsum("ij,ij->i", v, v)  # [n] m^2/s^2
    else:
        speed_sq = np.square(f["velocity_magnitude"], dtype=np.float64)
    speed = np.sqrt(speed_sq)  # [n] m/s
    n = speed.shape[0]
    if not n:
        max_d = 0.0
    elif "displacement" in f:
        d = f["displacement"]
        max_d = math.sqrt(float(np.einsum("ij,ij->i", d, d).max()))
    elif "displacement_magnitude" in f:
        max_d = float(np.abs(f["displacement_magnitude"]).max())
    else:
        max_d = 0.0
    bins = speed_bins(speed)
    every = np.bincount(bins, minlength=SPEED_BINS)
    if regions is None:
        hist_in, hist_out = every, np.zeros_like(every)
    elif not regions:
        hist_in, hist_out = np.zeros_like(every), every
    else:
        hist_in = np.bincount(bins[inside_mask(p.positions, regions)], minlength=SPEED_BINS)
        hist_out = every - hist_in
    return Stats(run, rank, step, float(time_s), n,
                 speed_sq_sum_m2_s2=float(speed_sq.sum()),
                 max_speed_m_s=float(speed.max()) if n else 0.0,
                 max_displacement_m=max_d,
                 windows_open=regions != (), hist_in_regions=hist_in.tolist(),
                 hist_elsewhere=hist_out.tolist())
