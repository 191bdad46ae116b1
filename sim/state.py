"""Simulation state as structures of arrays, and particle seeding from a scene.

Particle arrays are float64 in SI units and indexed by the *current* storage order; `pid`
maps storage slot -> original particle id (the order of the HDF5 output), so the driver may
reorder particles for memory locality. The grid is a block of nodes with an integer origin
(global index of local node 0), so a rank can own a slab of a larger grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from minority.sim.kernels import GRID_FIELDS, permute_particles
from minority.sim.scene import Scene, Shape

GRID_PAD_NODES = 2  # ghost nodes beyond each domain face (stencil reach + clamp margin)


@dataclass
class ParticleState:
    """Material points (structure of arrays). n = number of particles."""

    x: np.ndarray  # [n, 3] float64, m, position
    v: np.ndarray  # [n, 3] float64, m/s, velocity
    C: np.ndarray  # [n, 3, 3] float64, 1/s, APIC affine velocity field
    F: np.ndarray  # [n, 3, 3] float64, elastic deformation gradient F^E
    tau: np.ndarray  # [n, 3, 3] float64, Pa, Kirchhoff stress of F^E
    mass: np.ndarray  # [n] float64, kg
    vol0: np.ndarray  # [n] float64, m^3, initial volume
    x0: np.ndarray  # [n, 3] float64, m, initial position (for displacements)
    pid: np.ndarray  # [n] int64, original particle id of each storage slot

    @property
    def n(self) -> int:
        return self.x.shape[0]

    # spare arrays of the same shapes, reused by permute (no fresh 30 MB per reorder at 100k)
    _spare: dict = field(default_factory=dict, repr=False, compare=False)

    def permute(self, order: np.ndarray) -> None:
        """Reorder all arrays in place so that new slot k holds old slot order[k]. The
        previous arrays become the spares of the next call: do not keep references to
        particle arrays across a permute."""
        n = self.n
        src, dst = [], []
        for name in PARTICLE_FIELDS:
            a = getattr(self, name)
            out = self._spare.get(name)
            if (out is None or out.shape != a.shape or out.dtype != a.dtype
                    or not out.flags.writeable):
                out = np.empty_like(a, order="C")
            src.append(a.reshape(n, -1))
            dst.append(out.reshape(n, -1))
            self._spare[name] = a
            setattr(self, name, out)
        permute_particles(order, tuple(src), tuple(dst))


PARTICLE_FIELDS = ("x", "v", "C", "F", "tau", "mass", "vol0", "x0", "pid")


@dataclass
class GridState:
    """Background grid block. Node with local index (i, j, k) has global index
    origin + (i, j, k) and position (origin + (i, j, k)) * dx, m (domain lo is 0)."""

    origin: np.ndarray  # [3] int64, global index of local node (0, 0, 0)
    dx: float  # m, cell size
    data: np.ndarray  # [nx, ny, nz, GRID_FIELDS] float64, see sim.kernels: velocity, mass, dv

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.data.shape[:3]

    @property
    def x0(self) -> np.ndarray:
        """[3] float64, m: position of local node (0, 0, 0)."""
        return self.origin.astype(np.float64) * self.dx


def make_grid(scene: Scene) -> GridState:
    """Whole-domain grid with GRID_PAD_NODES ghost nodes beyond every face."""
    cells = np.array(scene.grid_cells, dtype=np.int64)
    origin = np.full(3, -GRID_PAD_NODES, dtype=np.int64)
    shape = tuple(int(c) + 1 + 2 * GRID_PAD_NODES for c in cells)
    return GridState(origin=origin, dx=scene.cell_size_m,
                     data=np.zeros(shape + (GRID_FIELDS,), dtype=np.float64))


def _lattice(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Lattice points (i + 1/2) * spacing (m) inside [lo, hi] per axis, [m, 3]."""
    axes = []
    for a in range(3):
        i0 = int(np.floor(lo[a] / spacing + 1e-9))
        i1 = int(np.ceil(hi[a] / spacing - 1e-9))
        c = (np.arange(i0, i1) + 0.5) * spacing
        axes.append(c[(c >= lo[a]) & (c <= hi[a])])
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grid], axis=1)


def seed_particles(scene: Scene) -> ParticleState:
    """Fill the scene's bodies with points on one lattice of spacing dx / ppc (m).

    A lattice point inside several bodies is seeded once (first body wins); particle ids
    follow body order then x-major lattice order."""
    s = scene.particle_spacing_m
    chunks, vels, taken = [], [], set()
    for body in scene.bodies:
        if body.shape is Shape.BOX:
            pts = _lattice(np.array(body.lo_m), np.array(body.hi_m), s)
        else:
            c = np.array(body.center_m)
            r = body.radius_m
            pts = _lattice(c - [r, r, 0.0], c + [r, r, body.height_m], s)
            d2 = (pts[:, 0] - c[0]) ** 2 + (pts[:, 1] - c[1]) ** 2
            pts = pts[d2 <= r * r]
        if len(scene.bodies) > 1:
            keys = np.rint(pts / s - 0.5).astype(np.int64)
            keep = np.array([tuple(k) not in taken for k in keys], dtype=bool)
            taken.update(tuple(k) for k in keys[keep])
            pts = pts[keep]
        chunks.append(pts)
        vels.append(np.broadcast_to(np.array(body.velocity_m_s), pts.shape))
    x = np.ascontiguousarray(np.concatenate(chunks, axis=0), dtype=np.float64)
    n = x.shape[0]
    if n == 0:
        raise ValueError(f"scene {scene.name!r} seeds no particles (bodies smaller than the "
                         f"particle spacing {s} m?)")
    vol = s**3
    # every array C-contiguous: the kernels are compiled per layout, and two layouts of the
    # same state (the concatenated broadcasts were Fortran-ordered) round differently
    return ParticleState(
        x=x,
        v=np.ascontiguousarray(np.concatenate(vels, axis=0), dtype=np.float64),
        C=np.zeros((n, 3, 3)),
        F=np.tile(np.eye(3), (n, 1, 1)),
        tau=np.zeros((n, 3, 3)),
        mass=np.full(n, scene.material.density_kg_m3 * vol),
        vol0=np.full(n, vol),
        x0=x.copy(),
        pid=np.arange(n, dtype=np.int64),
    )
