"""The MPM driver: owns particle and grid state, the phase order and the timing.

One step: bin particles by block (parallel stable counting sort; every
REORDER_INTERVAL_STEPS also permute the particle arrays into that order) -> P2G scatter into
per-block buffers -> grid: sum the buffers per node and update (gravity, walls) -> G2P
(advection, plasticity, stress). Phase times: bin, p2g (scatter), grid (gather + update),
g2p, and comm (a slab rank's exchanges, `sim.decomp.SlabSimulator`; 0 here). The hooks
`_exchange_particles`, `_order_blocks`, `_permute`, `_exchange_buffers` and `_reduce_stats`
are where a slab rank plugs in; here they do nothing beyond the single-process step. The
time step follows the CFL condition dt = cfl * dx / (c_p + max |v|), recomputed every step;
a fixed user dt is accepted only while it stays below that bound.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np

from minority.sim import kernels
from minority.sim.scene import FACES, Scene
from minority.sim.state import GridState, ParticleState, make_grid, seed_particles

REORDER_INTERVAL_STEPS = 20  # physically re-sort particle arrays this often (locality)
UNBOUNDED_M = 1e30  # extent of the domain-face walls along the other axes


class SimulationError(RuntimeError):
    """The simulation cannot continue; the message says why."""


class NonFiniteError(SimulationError):
    """A particle field became NaN or infinite."""


class TimeStepError(SimulationError, ValueError):
    """A requested time step exceeds the stable (CFL) bound."""


@dataclass
class PhaseTimes:
    """Accumulated wall time per phase, s."""

    bin: float = 0.0
    p2g: float = 0.0
    grid: float = 0.0
    g2p: float = 0.0
    comm: float = 0.0  # slab ranks: migration, buffer exchange, reductions
    # CPU time of the calling thread in bin + p2g + grid + g2p, s: the work itself, without
    # time lost to other processes (all of it with one numba thread; part of it with more)
    compute_cpu: float = 0.0
    lent: float = 0.0  # waiting for the publisher to read lent particle arrays (before_write)

    @property
    def total(self) -> float:
        return self.bin + self.p2g + self.grid + self.g2p + self.comm + self.lent


@dataclass
class WallArrays:
    """All walls (6 domain faces first, then interior walls) as kernel arrays."""

    axis: np.ndarray  # [w] int64
    pos: np.ndarray  # [w] float64, m
    side: np.ndarray  # [w] int64, +1 or -1: direction of the free region
    mu: np.ndarray  # [w] float64, Coulomb friction coefficient
    lo: np.ndarray  # [w, 3] float64, m, extent of the wall
    hi: np.ndarray  # [w, 3] float64, m

    @classmethod
    def from_scene(cls, scene: Scene) -> WallArrays:
        rows = []
        for f, face in enumerate(FACES):
            axis, is_max = divmod(f, 2)
            pos = scene.size_m[axis] if is_max else 0.0
            rows.append((axis, pos, -1 if is_max else 1, scene.face_friction[face],
                         (-UNBOUNDED_M,) * 3, (UNBOUNDED_M,) * 3))
        for w in scene.walls:
            rows.append((w.axis, w.position_m, w.side, w.friction, w.lo_m, w.hi_m))
        return cls(
            axis=np.array([r[0] for r in rows], dtype=np.int64),
            pos=np.array([r[1] for r in rows], dtype=np.float64),
            side=np.array([r[2] for r in rows], dtype=np.int64),
            mu=np.array([r[3] for r in rows], dtype=np.float64),
            lo=np.array([r[4] for r in rows], dtype=np.float64).reshape(-1, 3),
            hi=np.array([r[5] for r in rows], dtype=np.float64).reshape(-1, 3),
        )


@dataclass
class Diagnostics:
    """Particle sums at one instant."""

    mass_kg: float
    momentum_kg_m_s: np.ndarray  # [3]
    kinetic_energy_j: float
    potential_energy_j: float  # gravitational, -sum m g.x
    max_speed_m_s: float


@dataclass
class BlockBinning:
    """Scratch arrays of the counting sort and the per-block P2G buffers (reused every
    step; `buf` grows when more blocks become non-empty)."""

    nblocks3: np.ndarray  # [3] int64, blocks per axis
    block_start: np.ndarray  # [nblocks + 1] int64
    order: np.ndarray  # [capacity >= n] int64, sorted slot -> particle slot
    block_slot: np.ndarray  # [nblocks] int64, buffer slot of a non-empty block or -1
    active_blocks: np.ndarray  # [nblocks] int64, non-empty blocks (first n_active)
    key: np.ndarray  # [capacity >= n] int64, block of each particle
    counts: np.ndarray  # [BIN_CHUNKS, nblocks] int64, counting-sort scratch
    first_bad: np.ndarray  # [BIN_CHUNKS] int64
    buf: np.ndarray  # [slots, BUF_NODES, BUF_NODES, BUF_NODES, GRID_FIELDS] float64, P2G buffers
    n_active: int = 0

    @classmethod
    def allocate(cls, n: int, grid_shape) -> BlockBinning:
        nb3 = np.array([(s + kernels.BLOCK_CELLS - 1) // kernels.BLOCK_CELLS
                        for s in grid_shape], dtype=np.int64)
        nb = int(np.prod(nb3))
        return cls(nb3, np.zeros(nb + 1, np.int64), np.zeros(n, np.int64),
                   np.full(nb, -1, np.int64), np.zeros(nb, np.int64), np.zeros(n, np.int64),
                   np.zeros((kernels.BIN_CHUNKS, nb), np.int64),
                   np.zeros(kernels.BIN_CHUNKS, np.int64), cls._buffers(0))

    @staticmethod
    def _buffers(slots: int) -> np.ndarray:
        return np.empty((slots,) + (kernels.BUF_NODES,) * 3 + (kernels.GRID_FIELDS,))

    def ensure_buffers(self, extra: int = 0) -> None:
        """Room for the n_active block buffers plus `extra` (a slab rank's ghost blocks)."""
        need = self.n_active + extra
        if self.buf.shape[0] < need:
            self.buf = self._buffers(need + need // 4 + 8)


@dataclass
class Simulator:
    """Single-process MLS-MPM simulation of one scene."""

    scene: Scene
    fixed_dt: float | None = None
    threads: int | None = None
    particles: ParticleState = field(init=False)
    grid: GridState = field(init=False)
    time_s: float = field(init=False, default=0.0)
    step_count: int = field(init=False, default=0)
    clamp_count: int = field(init=False, default=0)  # particle-steps clamped to the domain
    times: PhaseTimes = field(init=False, default_factory=PhaseTimes)
    # called before a step writes the particle arrays (in situ: InSitu.reclaim, the arrays
    # lent by publish(copy=False) are read by then); its wait, s, adds to times.lent
    before_write: Callable[[], object] | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        if self.threads is not None:
            if not 1 <= self.threads <= numba.config.NUMBA_NUM_THREADS:
                raise ValueError(f"threads must be in [1, {numba.config.NUMBA_NUM_THREADS}], "
                                 f"got {self.threads}")
            numba.set_num_threads(self.threads)
        self.walls = WallArrays.from_scene(self.scene)
        self._init_state()
        self._stats = np.zeros(3)
        self._sums = np.zeros(8)
        self._gravity = np.array(self.scene.gravity_m_s2, dtype=np.float64)
        self._lo = np.zeros(3)
        self._hi = np.array(self.scene.size_m, dtype=np.float64)
        mat = self.scene.material
        self._lam, self._mu, self._alpha = mat.lame_lambda_pa, mat.shear_modulus_pa, mat.dp_alpha
        if self.fixed_dt is not None:
            self.check_dt(self.fixed_dt)

    def _init_state(self) -> None:
        """Seed the particles, make the grid and the binning scratch; set x0 (m, position of
        whole-domain node 0), the local grid's node offset and the max particle speed."""
        self.particles = seed_particles(self.scene)
        self.grid = make_grid(self.scene)
        self._bins = BlockBinning.allocate(self.particles.n, self.grid.shape)
        self._x0 = self.grid.x0
        self._off = np.zeros(3, np.int64)
        self._ghost_slots = 0  # extra P2G buffers a slab rank fills with its neighbours'
        self.max_speed_m_s = float(np.sqrt((self.particles.v ** 2).sum(axis=1).max()))

    # --- time step -------------------------------------------------------------------
    def stable_dt(self) -> float:
        """CFL bound, s: cfl * dx / (c_p + max particle speed)."""
        c = self.scene.material.p_wave_speed_m_s
        return self.scene.cfl * self.scene.cell_size_m / (c + self.max_speed_m_s)

    def check_dt(self, dt: float) -> None:
        bound = self.stable_dt()
        if not (math.isfinite(dt) and 0.0 < dt <= bound):
            raise TimeStepError(
                f"time step {dt:.6g} s exceeds the stable bound {bound:.6g} s at step "
                f"{self.step_count} (cfl {self.scene.cfl} * dx {self.scene.cell_size_m} m / "
                f"(p-wave speed {self.scene.material.p_wave_speed_m_s:.4g} m/s + max speed "
                f"{self.max_speed_m_s:.4g} m/s)); use dt <= {bound:.6g} s or no dt")

    def next_dt(self, until_s: float) -> float:
        """Time step for the next step so that the run lands exactly on until_s (s)."""
        if self.fixed_dt is not None:
            self.check_dt(self.fixed_dt)
            return self.fixed_dt
        remaining = until_s - self.time_s
        bound = self.stable_dt()
        if remaining <= 0.0:
            return bound
        return remaining / math.ceil(remaining / bound * (1.0 - 1e-12))

    # --- phases ----------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance one explicit MLS-MPM step of dt seconds."""
        t_comm = time.perf_counter()
        lent_comm = self.times.lent
        self._exchange_particles()
        t0 = time.perf_counter()
        c0 = time.thread_time()
        lent0 = self.times.lent
        ps, g, b = self.particles, self.grid, self._bins
        n = ps.n
        inv_dx = 1.0 / g.dx
        x0, off = self._x0, self._off
        bad, b.n_active = kernels.bin_particles(
            ps.x, x0, inv_dx, np.array(g.shape, np.int64), off, b.nblocks3, b.block_start,
            b.order[:n], b.block_slot, b.active_blocks, b.key[:n], b.counts, b.first_bad)
        if bad >= 0:
            self._raise_nonfinite_or_escape(bad)
        self._order_blocks()
        if self.step_count % REORDER_INTERVAL_STEPS == 0:
            self._writing()
            self._permute(b.order[:n])
            ps = self.particles
            b.order[:n] = np.arange(n)
        b.ensure_buffers(self._ghost_slots)
        t1 = time.perf_counter()
        lent1 = self.times.lent
        kernels.p2g_scatter(ps.x, ps.v, ps.C, ps.tau, ps.mass, ps.vol0, b.order, b.block_start,
                            b.active_blocks, b.n_active, b.nblocks3, b.buf, x0, off, inv_dx, dt)
        t2 = time.perf_counter()
        c2 = time.thread_time()
        self._exchange_buffers()
        t2c = time.perf_counter()
        c2c = time.thread_time()
        w = self.walls
        kernels.grid_gather_update(b.buf, b.block_slot, b.nblocks3, g.data, g.origin, g.dx, dt,
                                   self._gravity, w.axis, w.pos, w.side, w.mu, w.lo, w.hi)
        t3 = time.perf_counter()
        self._writing()
        t3w = time.perf_counter()
        kernels.g2p(ps.x, ps.v, ps.C, ps.F, ps.tau, g.data, x0, off, inv_dx, dt, self._lo,
                    self._hi, self._lam, self._mu, self._alpha, self.scene.flip, self._stats)
        t4 = time.perf_counter()
        c4 = time.thread_time()
        self._reduce_stats()
        t5 = time.perf_counter()
        self.times.bin += t1 - t0 - (lent1 - lent0)
        self.times.p2g += t2 - t1
        self.times.grid += t3 - t2c
        self.times.g2p += t4 - t3w
        self.times.comm += (t0 - t_comm) - (lent0 - lent_comm) + (t2c - t2) + (t5 - t4)
        self.times.compute_cpu += (c2 - c0) + (c4 - c2c)
        self.step_count += 1
        self.time_s += dt
        if self._stats[1] > 0:
            self.check_finite()  # a non-finite particle field: named
            raise NonFiniteError(  # or the grid's velocity was not finite where they read it
                f"non-finite grid velocity at step {self.step_count} (t = {self.time_s:.6g} s): "
                f"{int(self._stats[1])} particles could not be updated")
        self.clamp_count += int(self._stats[2])
        self.max_speed_m_s = math.sqrt(self._stats[0])

    def _writing(self) -> None:
        """Before the particle arrays are written: wait until the publisher no longer reads
        them (`before_write`)."""
        if self.before_write is not None:
            t0 = time.perf_counter()
            self.before_write()
            self.times.lent += time.perf_counter() - t0

    # --- hooks of a slab rank (sim.decomp.SlabSimulator); single process: no-ops -------
    def _exchange_particles(self) -> None:
        """Before binning: move particles to the rank that owns their block."""

    def _order_blocks(self) -> None:
        """After binning: make the order inside each block the single-process order."""

    def _permute(self, order: np.ndarray) -> None:
        """Physically reorder the particle arrays so that new slot k holds old order[k]."""
        self.particles.permute(order)

    def _exchange_buffers(self) -> None:
        """After the P2G scatter: add the neighbours' buffers of the shared nodes."""

    def _reduce_stats(self) -> None:
        """After G2P: combine the G2P stats [max |v|^2, non-finite, clamped] over ranks."""

    def reached(self, until_s: float) -> bool:
        """True once time_s is at until_s (within half a step for a fixed dt)."""
        if self.fixed_dt is not None:
            return self.time_s + 0.5 * self.fixed_dt >= until_s
        return self.time_s >= until_s * (1.0 - 1e-12)

    def advance_to(self, until_s: float, max_steps: int | None = None) -> int:
        """Step until reached(until_s) or max_steps steps were taken; returns steps."""
        steps = 0
        while not self.reached(until_s) and (max_steps is None or steps < max_steps):
            self.step(self.next_dt(until_s))
            steps += 1
        if self.fixed_dt is None and self.reached(until_s):
            self.time_s = max(self.time_s, until_s)  # drop the last ulps of drift
        return steps

    # --- guards and diagnostics ------------------------------------------------------
    def check_finite(self) -> None:
        """Raise NonFiniteError naming step, particle and field if any value is not finite."""
        ps = self.particles
        p, code = kernels.find_nonfinite(ps.x, ps.v, ps.C, ps.F, ps.tau)
        if p >= 0:
            count = int(self._stats[1])
            raise NonFiniteError(
                f"non-finite {kernels.FIELD_NAMES[code]} at step {self.step_count} "
                f"(t = {self.time_s:.6g} s), particle {int(ps.pid[p])}"
                + (f"; {count} particles affected" if count > 0 else ""))

    def _raise_nonfinite_or_escape(self, slot: int) -> None:
        self.check_finite()
        ps = self.particles
        raise SimulationError(
            f"particle {int(ps.pid[slot])} at {ps.x[slot].tolist()} m left the grid at step "
            f"{self.step_count}")

    def diagnostics(self) -> Diagnostics:
        ps = self.particles
        kernels.particle_sums(ps.x, ps.v, ps.mass, self._gravity, self._sums)
        s = self._sums
        return Diagnostics(float(s[0]), s[1:4].copy(), float(s[4]), float(s[5]), float(s[6]))

    def fields_by_id(self) -> dict[str, np.ndarray]:
        """Positions, velocities and displacements in original particle order, [n, 3]."""
        ps = self.particles
        out = {}
        for name, arr in (("positions", ps.x), ("velocities", ps.v),
                          ("displacements", ps.x - ps.x0)):
            a = np.empty_like(arr)
            a[ps.pid] = arr
            out[name] = a
        return out
