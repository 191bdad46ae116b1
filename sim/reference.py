"""Plain vectorized NumPy implementation of one MLS-MPM step, for testing the kernels.

Same algorithm as sim.kernels (P2G with np.add.at, grid update, G2P with numpy's SVD), no
sorting, no parallelism. Slow; use on small cases only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minority.sim.kernels import APIC_D_INV, WALL_TOL_CELLS
from minority.sim.plasticity import dp_project_numpy


@dataclass
class ReferenceState:
    x: np.ndarray  # [n, 3] m
    v: np.ndarray  # [n, 3] m/s
    C: np.ndarray  # [n, 3, 3] 1/s
    F: np.ndarray  # [n, 3, 3]
    tau: np.ndarray  # [n, 3, 3] Pa


def _weights(X: np.ndarray):
    """Local cell coords X [n, 3] -> base [n, 3] int, fx [n, 3], w [3 nodes, n, 3 axes]."""
    base = np.floor(X - 0.5).astype(np.int64)
    fx = X - base
    w = np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
    return base, fx, w


def _offsets():
    for i in range(3):
        for j in range(3):
            for k in range(3):
                yield np.array([i, j, k])


def reference_step(s: ReferenceState, *, mass, vol0, grid_shape, origin, dx, dt, gravity,
                   walls, lo, hi, lam, mu, alpha, flip=0.0) -> tuple[ReferenceState, np.ndarray]:
    """One step; returns the new state and the grid [nx, ny, nz, 7] after the update
    (velocity, mass, velocity change)."""
    x0 = np.asarray(origin, dtype=np.float64) * dx
    X = (s.x - x0) / dx
    base, fx, w = _weights(X)
    # P2G
    A = (-dt * APIC_D_INV / dx**2) * vol0[:, None, None] * s.tau + mass[:, None, None] * s.C
    grid = np.zeros(tuple(grid_shape) + (4,))
    free = np.zeros(tuple(grid_shape) + (3,))  # APIC momentum without the stress impulse
    for off in _offsets():
        wt = w[off[0], :, 0] * w[off[1], :, 1] * w[off[2], :, 2]
        dpos = (off - fx) * dx
        mom = wt[:, None] * (mass[:, None] * s.v + np.einsum("nij,nj->ni", A, dpos))
        mom_free = wt[:, None] * mass[:, None] * (s.v + np.einsum("nij,nj->ni", s.C, dpos))
        idx = tuple((base + off).T)
        for a in range(3):
            np.add.at(grid[..., a], idx, mom[:, a])
            np.add.at(free[..., a], idx, mom_free[:, a])
        np.add.at(grid[..., 3], idx, wt * mass)
    # grid update
    m = grid[..., 3]
    has = m > 0.0
    vel = np.zeros(grid.shape[:3] + (3,))
    vel[has] = grid[has][:, :3] / m[has][:, None] + dt * np.asarray(gravity)
    ii = np.indices(grid.shape[:3]).transpose(1, 2, 3, 0)
    pos = (ii + np.asarray(origin)) * dx
    tol = WALL_TOL_CELLS * dx
    for wk in range(len(walls.axis)):
        a, sd = walls.axis[wk], walls.side[wk]
        inside = sd * (pos[..., a] - walls.pos[wk]) <= tol
        for b in range(3):
            if b != a:
                inside &= (pos[..., b] >= walls.lo[wk, b] - tol)
                inside &= (pos[..., b] <= walls.hi[wk, b] + tol)
        vn = sd * vel[..., a]
        hit = inside & has & (vn < 0.0)
        vh = vel[hit]
        vnh = vn[hit]
        vh[:, a] = 0.0
        vt = np.linalg.norm(vh, axis=1)
        stick = vt <= -walls.mu[wk] * vnh
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(stick, 0.0, 1.0 + walls.mu[wk] * vnh / vt)
        vel[hit] = vh * f[:, None]
    dvel = np.zeros_like(vel)
    dvel[has] = vel[has] - free[has] / m[has][:, None]
    grid_out = np.concatenate([vel, m[..., None], dvel], axis=-1)
    # G2P
    v_new = np.zeros_like(s.v)
    dv = np.zeros_like(s.v)
    c_new = np.zeros_like(s.C)
    for off in _offsets():
        wt = w[off[0], :, 0] * w[off[1], :, 1] * w[off[2], :, 2]
        idx = tuple((base + off).T)
        gv = vel[idx]
        v_new += wt[:, None] * gv
        dv += wt[:, None] * dvel[idx]
        c_new += (APIC_D_INV / dx) * wt[:, None, None] * np.einsum("ni,nj->nij", gv,
                                                                   off - fx)
    x_new = np.clip(s.x + dt * v_new, lo, hi)
    Fn = (np.eye(3) + dt * c_new) @ s.F
    U, sig, Vt = np.linalg.svd(Fn)
    eps = dp_project_numpy(sig, lam, mu, alpha)
    F_new = U @ (np.exp(eps)[:, :, None] * Vt)
    t_diag = 2.0 * mu * eps + lam * eps.sum(axis=1, keepdims=True)
    tau_new = U @ (t_diag[:, :, None] * U.transpose(0, 2, 1))
    v_particle = flip * (s.v + dv) + (1.0 - flip) * v_new
    return ReferenceState(x_new, v_particle, c_new, F_new, tau_new), grid_out
