"""Slab decomposition of the MPM grid along x (the main flow axis) over MPI ranks.

The whole-domain grid is cut into x-blocks of BLOCK_CELLS cells (the blocks of the P2G
scatter). Rank r owns the x-blocks [starts[r], starts[r + 1]) and every particle whose base
node lies in them; its local grid covers its slab plus one ghost x-block on each side.

Why the result does not depend on the rank count (bitwise, not only to round-off):

* A particle's B-spline weights come from whole-domain coordinates (`x0` of the
  whole-domain grid); a rank's slab only shifts integer node indices (`kernels`, `off`).
* P2G sums into one buffer per block; every block lives on exactly one rank, and inside a
  block particles are summed in the single-process order: the order of their storage slot
  at the last physical reorder (every REORDER_INTERVAL_STEPS). That slot is kept as a key
  (rank << KEY_RANK_SHIFT | local slot: the single-process storage order is rank-major,
  since blocks are sorted x-major), and `sort_blocks_by_key` restores it in blocks that
  migration disturbed.
* The nodes a slab shares with a neighbour (the first two of each x-block) sum the
  neighbour's block buffers: each rank sends its first owned x-block's buffers (local x
  nodes 0-1) to the left and its last one's (nodes 4-5) to the right, and both ranks run
  the same gather in the same order, so both hold bitwise the node values of one process.
* The time step uses the global max speed (one Allgather per step).

Per step: migrate particles that left the slab (to a neighbour: a particle moves less than
a cell per step and a slab is at least one block) -> bin -> fix block order -> P2G ->
exchange boundary buffers -> gather + grid update -> G2P -> Allgather of [max |v|^2,
non-finite count]. Every `rebalance_every` steps the slab boundaries move to balance the
particle count (whole x-blocks, each rank keeps at least one), and particles migrate until
every one is on its owner, hopping one rank per pass.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit, prange

from minority.sim import kernels
from minority.sim.driver import BlockBinning, NonFiniteError, Simulator
from minority.sim.state import (
    GRID_FIELDS,
    GRID_PAD_NODES,
    PARTICLE_FIELDS,
    GridState,
    ParticleState,
    seed_particles,
)

BLOCK = kernels.BLOCK_CELLS
KEY_RANK_SHIFT = 40  # storage key = rank << 40 | local slot at the last reorder
DEFAULT_REBALANCE_EVERY = 100  # steps between rebalancing of the slab boundaries
GROWTH = 1.25  # particle storage grows by this factor (plus a margin) when full
GROWTH_MARGIN = 256
SHARED_NODES = kernels.BUF_NODES - BLOCK  # x nodes of a block buffer in the next block (2)
STORED = PARTICLE_FIELDS + ("key",)  # what a migrating particle carries


# --- kernels -------------------------------------------------------------------------
@njit(parallel=True, cache=True)
def particle_xblocks(x, x0x, inv_dx, out):
    """out[p] = whole-domain x-block of particle p's base node, or -1 when its x is not
    finite or below the grid (the binning then names it)."""
    for p in prange(x.shape[0]):
        X = (x[p, 0] - x0x) * inv_dx
        out[p] = int(X - 0.5) // BLOCK if (X >= 0.5 and X < 1e15) else -1


@njit(cache=True)
def owner_ranks(xblock, starts, me, out):
    """out[p] = rank owning x-block xblock[p] (slabs [starts[r], starts[r + 1])); a particle
    without a block stays on `me`. Returns how many particles belong elsewhere."""
    ranks = starts.shape[0] - 1
    moving = 0
    for p in range(xblock.shape[0]):
        b = xblock[p]
        r = me
        if b >= 0:
            r = 0
            while r < ranks - 1 and b >= starts[r + 1]:
                r += 1
        out[p] = r
        if r != me:
            moving += 1
    return moving


@njit(parallel=True, cache=True)
def sort_blocks_by_key(order, block_start, active_blocks, n_active, key):
    """Inside every non-empty block, order its particles by key (the single-process storage
    order) unless they already are. Returns the number of blocks reordered."""
    fixed = np.zeros(n_active, np.int64)
    for sl in prange(n_active):
        b = active_blocks[sl]
        s0, s1 = block_start[b], block_start[b + 1]
        for s in range(s0 + 1, s1):
            if key[order[s]] < key[order[s - 1]]:
                seg = order[s0:s1].copy()
                idx = np.argsort(key[seg])
                for k in range(s1 - s0):
                    order[s0 + k] = seg[idx[k]]
                fixed[sl] = 1
                break
    return fixed.sum()


# --- slab geometry (no MPI) ----------------------------------------------------------
def grid_nodes(scene) -> tuple[int, int, int]:
    """Whole-domain grid nodes per axis, ghost nodes included (as `state.make_grid`)."""
    return tuple(int(c) + 1 + 2 * GRID_PAD_NODES for c in scene.grid_cells)


def balanced_starts(counts: np.ndarray, ranks: int) -> np.ndarray:
    """Slab boundaries [ranks + 1] in x-blocks for particle counts per x-block [nbx] that
    minimize the largest slab's count (each rank keeps at least one block): a binary search
    on that largest count, each candidate tried by filling slabs left to right as far as it
    allows. Deterministic, so every rank computes the same cuts."""
    nbx = counts.shape[0]
    if ranks > nbx:
        raise ValueError(f"{ranks} ranks but the grid has only {nbx} x-blocks of {BLOCK} "
                         f"cells; use at most {nbx} ranks")
    cum = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)  # particles in blocks < i

    def fill(limit: int) -> list[int]:
        starts = [0]
        for k in range(1, ranks):
            lo, hi = starts[-1] + 1, nbx - (ranks - k)
            furthest = int(np.searchsorted(cum, cum[starts[-1]] + limit, side="right")) - 1
            starts.append(min(max(furthest, lo), hi))
        return starts + [nbx]

    def largest(starts: list[int]) -> int:
        return int(np.max(cum[starts[1:]] - cum[starts[:-1]]))

    lo, hi = -(-int(cum[-1]) // ranks), int(cum[-1])  # the largest slab holds at least 1/ranks
    while lo < hi:
        mid = (lo + hi) // 2
        if largest(fill(mid)) <= mid:
            hi = mid
        else:
            lo = mid + 1
    return np.array(fill(lo), dtype=np.int64)


# --- one rank --------------------------------------------------------------------------
@dataclass
class SlabSimulator(Simulator):
    """One MPI rank of a slab-decomposed run (see the module docstring). `comm` is an
    mpi4py communicator; with one rank this is the single-process `Simulator`, step for
    step. Positions are bitwise those of the single-process run at any rank count."""

    comm: Any = None
    rebalance_every: int = DEFAULT_REBALANCE_EVERY  # steps; 0: never
    rebalances: int = field(init=False, default=0)  # slab boundary changes so far
    migrated: int = field(init=False, default=0)  # particles received from other ranks
    # polled at every step, its largest value over ranks kept in stop_signum (the stats'
    # exchange carries it: no collective of its own): a signal number asking the ranks to
    # stop, else 0 (sim.launcher.StopSignals)
    stop_source: Callable[[], int] | None = None
    stop_signum: int = field(init=False, default=0)  # after the last step, on every rank

    # --- set-up ---------------------------------------------------------------------
    def _init_state(self) -> None:
        from mpi4py import MPI

        if self.comm is None:
            raise ValueError("SlabSimulator needs an MPI communicator (comm)")
        self._MPI = MPI
        self.rank, self.ranks = self.comm.Get_rank(), self.comm.Get_size()
        everything = seed_particles(self.scene)  # same on every rank; keep our slab
        self.n_total = everything.n
        self.max_speed_m_s = float(np.sqrt((everything.v ** 2).sum(axis=1).max()))
        self._nodes = grid_nodes(self.scene)
        self._origin = np.full(3, -GRID_PAD_NODES, dtype=np.int64)
        dx = self.scene.cell_size_m
        self._x0 = self._origin.astype(np.float64) * dx  # as GridState.x0 of the whole grid
        self._inv_dx = 1.0 / dx
        self.nbx = (self._nodes[0] + BLOCK - 1) // BLOCK
        xb = np.empty(everything.n, np.int64)
        particle_xblocks(everything.x, self._x0[0], self._inv_dx, xb)
        starts = balanced_starts(np.bincount(xb[xb >= 0], minlength=self.nbx), self.ranks)
        dest = np.empty(everything.n, np.int64)
        owner_ranks(xb, starts, self.rank, dest)
        mine = np.flatnonzero(dest == self.rank)  # in particle id order
        self._n = 0
        self._cap = 0
        self._store: dict[str, np.ndarray] = {}
        self._spare: dict[str, np.ndarray] = {}
        self._ensure_capacity(mine.size, exact_store={
            **{name: getattr(everything, name)[mine] for name in PARTICLE_FIELDS},
            "key": everything.pid[mine].copy()})  # storage order = particle id order
        self._n = mine.size
        self._dest = np.empty(0, np.int64)
        self._xb = np.empty(0, np.int64)
        self._disordered = False
        self._gathered = np.zeros((self.ranks, 3))
        nyz = -(-self._nodes[1] // BLOCK) * -(-self._nodes[2] // BLOCK)
        self._ghost_slots = 2 * nyz if self.ranks > 1 else 0
        self._set_slab(starts)
        self._refresh_views()

    def _set_slab(self, starts: np.ndarray) -> None:
        """Own x-blocks [starts[rank], starts[rank + 1]); local grid = those plus one ghost
        x-block on each side (clipped to the domain)."""
        self.starts = starts
        a, b = int(starts[self.rank]), int(starts[self.rank + 1])
        self._la, lb = max(a - 1, 0), min(b + 1, self.nbx)
        nx = min(lb * BLOCK, self._nodes[0]) - self._la * BLOCK
        self._off = np.array([self._la * BLOCK, 0, 0], dtype=np.int64)
        self.grid = GridState(origin=self._origin + self._off, dx=self.scene.cell_size_m,
                              data=np.zeros((nx,) + self._nodes[1:] + (GRID_FIELDS,)))
        self._bins = BlockBinning.allocate(self._cap, self.grid.shape)

    @property
    def owned_xblocks(self) -> tuple[int, int]:
        return int(self.starts[self.rank]), int(self.starts[self.rank + 1])

    def _ensure_capacity(self, n: int, exact_store: dict | None = None) -> None:
        """Particle arrays hold at least n rows (views of the first _n are the particles)."""
        if exact_store is None and n <= self._cap:
            return
        cap = max(int(n * GROWTH) + GROWTH_MARGIN, self._cap)
        for name in STORED:
            src = exact_store[name] if exact_store is not None else self._store[name][:self._n]
            arr = np.empty((cap,) + src.shape[1:], dtype=src.dtype)
            arr[:src.shape[0]] = src
            self._store[name] = arr
            self._spare[name] = np.empty_like(arr)
        self._cap = cap
        if hasattr(self, "grid"):
            self._bins = BlockBinning.allocate(cap, self.grid.shape)

    def _refresh_views(self) -> None:
        n = self._n
        self.particles = ParticleState(**{name: self._store[name][:n] for name in PARTICLE_FIELDS})
        if self._dest.shape[0] < self._cap:
            self._dest = np.empty(self._cap, np.int64)
            self._xb = np.empty(self._cap, np.int64)

    # --- hooks of Simulator.step ------------------------------------------------------
    def _exchange_particles(self) -> None:
        if self.ranks == 1:
            return
        self._writing()  # migration and rebalancing move particle rows
        k = self.rebalance_every
        if k and self.step_count > 0 and self.step_count % k == 0:
            self.rebalance()
        else:
            self._migrate(settle=False)

    def _order_blocks(self) -> None:
        if self._disordered:
            b = self._bins
            sort_blocks_by_key(b.order, b.block_start, b.active_blocks, b.n_active,
                               self._store["key"][:self._n])

    def _permute(self, order: np.ndarray) -> None:
        n = self._n
        self._disordered = False
        if n == 0:  # a rank may own no particle for a while
            return
        src = tuple(self._store[name][:n].reshape(n, -1) for name in PARTICLE_FIELDS)
        dst = tuple(self._spare[name][:n].reshape(n, -1) for name in PARTICLE_FIELDS)
        kernels.permute_particles(order, src, dst)
        for name in PARTICLE_FIELDS:
            self._store[name], self._spare[name] = self._spare[name], self._store[name]
        self._store["key"][:n] = (self.rank << KEY_RANK_SHIFT) + np.arange(n)
        self._refresh_views()

    def _exchange_buffers(self) -> None:
        if self.ranks == 1:
            return
        b, MPI = self._bins, self._MPI
        a, bb = self.owned_xblocks
        left = self.rank - 1 if self.rank > 0 else MPI.PROC_NULL
        right = self.rank + 1 if self.rank < self.ranks - 1 else MPI.PROC_NULL
        to_left = self._boundary(a - self._la, slice(0, SHARED_NODES)) if self.rank > 0 else None
        to_right = (self._boundary(bb - 1 - self._la, slice(BLOCK, BLOCK + SHARED_NODES))
                    if self.rank < self.ranks - 1 else None)
        from_right = self.comm.sendrecv(to_left, dest=left, source=right)
        from_left = self.comm.sendrecv(to_right, dest=right, source=left)
        slot = b.n_active
        if from_left is not None:  # ghost x-block a - 1: its nodes 4-5 are our nodes 0-1
            slot = self._add_ghost(a - 1 - self._la, from_left, slice(BLOCK, BLOCK + SHARED_NODES),
                                   slot)
        if from_right is not None:  # ghost x-block b: its nodes 0-1 are our last two
            self._add_ghost(bb - self._la, from_right, slice(0, SHARED_NODES), slot)

    def _boundary(self, xl: int, nodes: slice):
        """(yz block indices, buffers [k, 2, BUF_NODES, BUF_NODES, GRID_FIELDS]) of the non-empty blocks
        of local x-block xl, restricted to the x nodes the neighbour shares."""
        b = self._bins
        nyz = int(b.nblocks3[1] * b.nblocks3[2])
        slots = b.block_slot[xl * nyz:(xl + 1) * nyz]
        yz = np.flatnonzero(slots >= 0)
        return yz, np.ascontiguousarray(b.buf[slots[yz], nodes])

    def _add_ghost(self, xl: int, message, nodes: slice, slot: int) -> int:
        yz, data = message
        b = self._bins
        nyz = int(b.nblocks3[1] * b.nblocks3[2])
        slots = np.arange(slot, slot + yz.size)
        b.buf[slots] = 0.0
        b.buf[slots, nodes] = data
        b.block_slot[xl * nyz + yz] = slots
        return slot + yz.size

    def _reduce_stats(self) -> None:
        if self.ranks == 1:
            return
        stop = self.stop_source() if self.stop_source is not None else 0
        mine = np.array([self._stats[0], self._stats[1], float(stop)])
        self.comm.Allgather(mine, self._gathered)
        self._stats[0] = self._gathered[:, 0].max()  # max |v|^2: the next time step
        self._stats[1] = self._gathered[:, 1].sum()  # non-finite particles on any rank
        self.stop_signum = int(self._gathered[:, 2].max())  # a stop asked on any rank

    # --- migration and rebalancing ----------------------------------------------------
    def _owners(self) -> int:
        n = self._n
        particle_xblocks(self._store["x"][:n], self._x0[0], self._inv_dx, self._xb[:n])
        return owner_ranks(self._xb[:n], self.starts, self.rank, self._dest[:n])

    def _migrate(self, settle: bool) -> None:
        """Send particles owned elsewhere one rank towards their owner; with settle, repeat
        until every particle is on its owner (after a rebalance)."""
        MPI = self._MPI
        left = self.rank - 1 if self.rank > 0 else MPI.PROC_NULL
        right = self.rank + 1 if self.rank < self.ranks - 1 else MPI.PROC_NULL
        while True:
            moving = self._owners()
            dest = self._dest[:self._n]
            go_left = np.flatnonzero(dest < self.rank) if moving else np.empty(0, np.int64)
            go_right = np.flatnonzero(dest > self.rank) if moving else np.empty(0, np.int64)
            from_right = self.comm.sendrecv(self._pack(go_left), dest=left, source=right)
            from_left = self.comm.sendrecv(self._pack(go_right), dest=right, source=left)
            self._replace(np.sort(np.concatenate([go_left, go_right])),
                          [m for m in (from_left, from_right) if m is not None])
            if not settle or self.comm.allreduce(self._owners(), op=MPI.SUM) == 0:
                return

    def _pack(self, idx: np.ndarray) -> dict | None:
        if idx.size == 0:
            return None
        return {name: self._store[name][idx] for name in STORED}

    def _replace(self, holes: np.ndarray, incoming: list[dict]) -> None:
        """Remove the particles in the slots `holes` (sorted) and add the incoming ones:
        they fill holes first, then the end; remaining holes take particles from the end.
        O(moved particles); the block order is then fixed by key."""
        m = sum(d["pid"].shape[0] for d in incoming)
        h = holes.size
        if m == 0 and h == 0:
            return
        n = self._n
        new_n = n - h + m
        self._ensure_capacity(new_n)
        store = self._store
        fill = min(m, h)
        if m:
            new = {name: np.concatenate([d[name] for d in incoming]) for name in STORED}
            for name in STORED:
                store[name][holes[:fill]] = new[name][:fill]
                store[name][n:new_n] = new[name][fill:]
            self.migrated += m
        if h > m:
            rest = holes[fill:]
            keep = np.ones(n - new_n, dtype=bool)
            keep[rest[rest >= new_n] - new_n] = False
            src = np.arange(new_n, n)[keep]
            dst = rest[rest < new_n]
            for name in STORED:
                store[name][dst] = store[name][src]
        self._n = new_n
        self._disordered = True
        self._refresh_views()

    def rebalance(self) -> bool:
        """Move the slab boundaries to balance the particle count (collective); returns
        whether they moved."""
        MPI = self._MPI
        self._owners()  # fills self._xb
        xb = self._xb[:self._n]
        counts = np.bincount(xb[xb >= 0], minlength=self.nbx).astype(np.int64)
        self.comm.Allreduce(MPI.IN_PLACE, counts, op=MPI.SUM)
        starts = balanced_starts(counts, self.ranks)
        moved = not np.array_equal(starts, self.starts)
        if moved:
            self._set_slab(starts)
            self.rebalances += 1
        self._migrate(settle=moved)
        return moved

    # --- guards, diagnostics and output over all ranks ----------------------------------
    def check_finite(self) -> None:
        super().check_finite()
        if self._stats[1] > 0:
            raise NonFiniteError(f"non-finite values on another rank at step {self.step_count} "
                                 f"(t = {self.time_s:.6g} s); {int(self._stats[1])} particles "
                                 f"affected")

    def diagnostics(self):
        d = super().diagnostics()
        if self.ranks == 1:
            return d
        parts = self.comm.allgather(
            (d.mass_kg, d.momentum_kg_m_s, d.kinetic_energy_j, d.potential_energy_j,
             d.max_speed_m_s))
        d.mass_kg = math.fsum(p[0] for p in parts)
        d.momentum_kg_m_s = np.sum([p[1] for p in parts], axis=0)
        d.kinetic_energy_j = math.fsum(p[2] for p in parts)
        d.potential_energy_j = math.fsum(p[3] for p in parts)
        d.max_speed_m_s = max(p[4] for p in parts)
        return d

    def gather_fields(self, root: int = 0) -> dict[str, np.ndarray] | None:
        """Positions, velocities, displacements [N, 3] float64 of every particle in original
        id order, on `root` (None on the other ranks). Collective."""
        ps = self.particles
        data = np.concatenate([ps.x, ps.v, ps.x - ps.x0], axis=1)
        parts = self.comm.gather((ps.pid, data), root=root)
        if parts is None:
            return None
        out = np.empty((self.n_total, 9))
        for pid, rows in parts:
            out[pid] = rows
        return {"positions": out[:, 0:3], "velocities": out[:, 3:6],
                "displacements": out[:, 6:9]}

    def total_count(self, value: int) -> int:
        """Sum of an integer over the ranks (collective)."""
        return int(self.comm.allreduce(int(value), op=self._MPI.SUM))
