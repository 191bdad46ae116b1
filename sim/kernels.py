"""MLS-MPM kernels (Hu et al. 2018) with APIC transfer and quadratic B-splines.

Numba kernels on plain arrays and scalars; the driver (`sim.driver.Simulator`) owns the
state and the phase order: bin -> P2G -> grid update -> G2P. Conventions:

* grid: [nx, ny, nz, 4] float64; [..., :3] momentum (kg m/s) after P2G and velocity (m/s)
  after the grid update, [..., 3] mass (kg). Local node (0, 0, 0) sits at x0 (m).
* a particle at local cell coordinate X = (x - x0) / dx has base node floor(X - 1/2) and
  touches the 3x3x3 nodes base + {0, 1, 2}.

Race-free parallel P2G: particles are counting-sorted by block of BLOCK_CELLS^3 base cells;
blocks are 8-colored by the parity of their block coordinates. A block writes nodes
[b*B, b*B + B + 1] per axis, so two blocks of one color (at least B cells apart) never write
the same node. Colors run one after another, blocks of a color in parallel, particles of a
block in sorted order: the summation order per node, hence the result, does not depend on
the thread count.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from sim.plasticity import elastoplastic_update

BLOCK_CELLS = 4  # block edge in cells; >= 2 keeps same-colored blocks' stencils disjoint
N_COLORS = 8
G2P_CHUNK = 512  # particles per parallel work item in G2P (scratch allocated per chunk)
APIC_D_INV = 4.0  # inverse of the quadratic B-spline inertia tensor D = dx^2 / 4 (per dx^2)
WALL_TOL_CELLS = 1e-6  # a node this close (in cells) to a wall plane counts as on it
# LLVM fast-math for P2G: contraction (FMA), reassociation, reciprocal and signed-zero
# freedom. The generated code does not depend on the thread count, so results stay bitwise
# independent of it. Not on G2P: there even these flags let LLVM fold away the
# finiteness checks (the NaN guard test failed), so G2P stays IEEE-exact.
FASTMATH = {"contract", "reassoc", "arcp", "nsz"}

FIELD_POSITION, FIELD_VELOCITY, FIELD_AFFINE, FIELD_DEFORMATION, FIELD_STRESS = range(5)
FIELD_NAMES = ("position", "velocity", "affine_velocity", "deformation_gradient", "stress")


@njit(parallel=True, cache=True)
def _block_keys(x, x0, inv_dx, grid_shape, nblocks3, key):
    """key[p] = linear block index of particle p's base cell, or -1 if its stencil would
    leave the grid (or its position is not finite)."""
    nby, nbz = nblocks3[1], nblocks3[2]
    for p in prange(x.shape[0]):
        k = 0
        for a in range(3):
            X = (x[p, a] - x0[a]) * inv_dx
            if not (X >= 0.5 and X < grid_shape[a] - 1.5):
                k = -1
                break
            b = int(X - 0.5) // BLOCK_CELLS  # X - 0.5 >= 0: truncation is floor
            k = b if a == 0 else (k * (nby if a == 1 else nbz) + b)
        key[p] = k


@njit(cache=True)
def bin_particles(x, x0, inv_dx, grid_shape, nblocks3, block_start, order, color_start,
                  color_blocks, key):
    """Counting sort of particles by block. Writes order [n] (sorted slot -> particle slot),
    block_start [nblocks + 1], color_start [9] and color_blocks [nblocks] (non-empty blocks
    grouped by color). Returns -1, or the first particle whose stencil leaves the grid."""
    n = x.shape[0]
    nby, nbz = nblocks3[1], nblocks3[2]
    nb = nblocks3[0] * nby * nbz
    _block_keys(x, x0, inv_dx, grid_shape, nblocks3, key)
    block_start[:] = 0
    for p in range(n):
        k = key[p]
        if k < 0:
            return p
        block_start[k + 1] += 1
    for k in range(nb):
        block_start[k + 1] += block_start[k]
    fill = block_start[:nb].copy()
    for p in range(n):
        k = key[p]
        order[fill[k]] = p
        fill[k] += 1
    color_start[:] = 0
    for k in range(nb):
        if block_start[k + 1] > block_start[k]:
            bz = k % nbz
            by = (k // nbz) % nby
            bx = k // (nbz * nby)
            c = (bx & 1) * 4 + (by & 1) * 2 + (bz & 1)
            color_start[c + 1] += 1
    for c in range(N_COLORS):
        color_start[c + 1] += color_start[c]
    cfill = color_start[:N_COLORS].copy()
    for k in range(nb):
        if block_start[k + 1] > block_start[k]:
            bz = k % nbz
            by = (k // nbz) % nby
            bx = k // (nbz * nby)
            c = (bx & 1) * 4 + (by & 1) * 2 + (bz & 1)
            color_blocks[cfill[c]] = k
            cfill[c] += 1
    return -1


@njit(cache=True, inline="always")
def _weights(X, w):
    """Quadratic B-spline weights w [3, 3] for local cell coords X [3]; returns nothing,
    fx = X - base is recomputed by the caller."""
    for a in range(3):
        fx = X[a] - math.floor(X[a] - 0.5)
        w[a, 0] = 0.5 * (1.5 - fx) ** 2
        w[a, 1] = 0.75 - (fx - 1.0) ** 2
        w[a, 2] = 0.5 * (fx - 0.5) ** 2


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def p2g(x, v, C, tau, mass, vol0, order, block_start, color_start, color_blocks, grid, x0,
        inv_dx, dt):
    """Particle to grid: scatter mass and APIC momentum plus the MLS stress impulse
    -dt vol0 (4 / dx^2) tau (x_i - x_p). grid must be zeroed by the caller."""
    dx = 1.0 / inv_dx
    stress_scale = -dt * APIC_D_INV * inv_dx * inv_dx
    for c in range(N_COLORS):
        for kb in prange(color_start[c], color_start[c + 1]):
            b = color_blocks[kb]
            X = np.empty(3)
            w = np.empty((3, 3))
            A = np.empty((3, 3))
            base = np.empty(3, np.int64)
            for s in range(block_start[b], block_start[b + 1]):
                p = order[s]
                m = mass[p]
                sv = stress_scale * vol0[p]
                for a in range(3):
                    X[a] = (x[p, a] - x0[a]) * inv_dx
                    base[a] = int(math.floor(X[a] - 0.5))
                _weights(X, w)
                for r in range(3):
                    for q in range(3):
                        A[r, q] = sv * tau[p, r, q] + m * C[p, r, q]
                mvx, mvy, mvz = m * v[p, 0], m * v[p, 1], m * v[p, 2]
                for i in range(3):
                    dxp = (i - (X[0] - base[0])) * dx
                    for j in range(3):
                        dyp = (j - (X[1] - base[1])) * dx
                        wij = w[0, i] * w[1, j]
                        for k in range(3):
                            dzp = (k - (X[2] - base[2])) * dx
                            wt = wij * w[2, k]
                            gi, gj, gk = base[0] + i, base[1] + j, base[2] + k
                            grid[gi, gj, gk, 0] += wt * (
                                mvx + A[0, 0] * dxp + A[0, 1] * dyp + A[0, 2] * dzp)
                            grid[gi, gj, gk, 1] += wt * (
                                mvy + A[1, 0] * dxp + A[1, 1] * dyp + A[1, 2] * dzp)
                            grid[gi, gj, gk, 2] += wt * (
                                mvz + A[2, 0] * dxp + A[2, 1] * dyp + A[2, 2] * dzp)
                            grid[gi, gj, gk, 3] += wt * m


@njit(parallel=True, cache=True)
def grid_update(grid, origin, dx, dt, gravity, wall_axis, wall_pos, wall_side, wall_mu,
                wall_lo, wall_hi):
    """Momentum -> velocity, add gravity dt, then Coulomb-friction walls: at a node inside
    wall w's solid half-space (side * (x[axis] - pos) <= 0, within lo..hi) an approaching
    normal velocity vn < 0 is removed and the tangential speed reduced by mu |vn| (stopped
    if smaller); separating velocities are kept."""
    nx, ny, nz = grid.shape[0], grid.shape[1], grid.shape[2]
    nw = wall_axis.shape[0]
    tol = WALL_TOL_CELLS * dx
    for i in prange(nx):
        vel = np.empty(3)
        pos = np.empty(3)
        for j in range(ny):
            for k in range(nz):
                m = grid[i, j, k, 3]
                if m <= 0.0:
                    grid[i, j, k, 0] = 0.0
                    grid[i, j, k, 1] = 0.0
                    grid[i, j, k, 2] = 0.0
                    continue
                pos[0] = (origin[0] + i) * dx
                pos[1] = (origin[1] + j) * dx
                pos[2] = (origin[2] + k) * dx
                for a in range(3):
                    vel[a] = grid[i, j, k, a] / m + dt * gravity[a]
                for w in range(nw):
                    a = wall_axis[w]
                    sd = wall_side[w]
                    if sd * (pos[a] - wall_pos[w]) > tol:
                        continue
                    inside = True
                    for b in range(3):
                        if b != a and (pos[b] < wall_lo[w, b] - tol or pos[b] > wall_hi[w, b] + tol):
                            inside = False
                    if not inside:
                        continue
                    vn = sd * vel[a]
                    if vn >= 0.0:
                        continue
                    vel[a] = 0.0
                    vt = math.sqrt(vel[0] ** 2 + vel[1] ** 2 + vel[2] ** 2)
                    mu = wall_mu[w]
                    if vt <= -mu * vn:
                        vel[0] = 0.0
                        vel[1] = 0.0
                        vel[2] = 0.0
                    else:
                        f = 1.0 + mu * vn / vt
                        for b in range(3):
                            vel[b] *= f
                grid[i, j, k, 0] = vel[0]
                grid[i, j, k, 1] = vel[1]
                grid[i, j, k, 2] = vel[2]


@njit(parallel=True, cache=True)
def g2p(x, v, C, F, tau, grid, x0, inv_dx, dt, lo, hi, lam, mu, alpha, out_stats):
    """Grid to particle: APIC velocity and affine field, advection (clamped to the domain
    lo..hi, m), F^E <- (I + dt C) F^E, Drucker-Prager return mapping, Kirchhoff stress.

    out_stats [3] float64 receives: max |v|^2 (m^2/s^2), non-finite particle count, clamped
    particle count. A particle with a non-finite velocity is left where it was."""
    n = x.shape[0]
    nchunks = (n + G2P_CHUNK - 1) // G2P_CHUNK
    chunk_stats = np.zeros((nchunks, 3))  # per chunk: max |v|^2, non-finite, clamped
    for ch in prange(nchunks):
        X = np.empty(3)
        w = np.empty((3, 3))
        base = np.empty(3, np.int64)
        Fn = np.empty((3, 3))
        U = np.empty((3, 3))
        V = np.empty((3, 3))
        sig = np.empty(3)
        eps = np.empty(3)
        S = np.empty((3, 3))
        Q = np.empty((3, 3))
        cvmax2 = 0.0
        cbad = 0
        cclamp = 0
        for p in range(ch * G2P_CHUNK, min(n, (ch + 1) * G2P_CHUNK)):
            for a in range(3):
                X[a] = (x[p, a] - x0[a]) * inv_dx
                base[a] = int(math.floor(X[a] - 0.5))
            _weights(X, w)
            vx = 0.0
            vy = 0.0
            vz = 0.0
            c00 = c01 = c02 = c10 = c11 = c12 = c20 = c21 = c22 = 0.0
            for i in range(3):
                dxp = i - (X[0] - base[0])
                for j in range(3):
                    dyp = j - (X[1] - base[1])
                    wij = w[0, i] * w[1, j]
                    for k in range(3):
                        dzp = k - (X[2] - base[2])
                        wt = wij * w[2, k]
                        gi, gj, gk = base[0] + i, base[1] + j, base[2] + k
                        gx = wt * grid[gi, gj, gk, 0]
                        gy = wt * grid[gi, gj, gk, 1]
                        gz = wt * grid[gi, gj, gk, 2]
                        vx += gx
                        vy += gy
                        vz += gz
                        c00 += gx * dxp
                        c01 += gx * dyp
                        c02 += gx * dzp
                        c10 += gy * dxp
                        c11 += gy * dyp
                        c12 += gy * dzp
                        c20 += gz * dxp
                        c21 += gz * dyp
                        c22 += gz * dzp
            # (x_i - x_p) = d * dx, so C = (4 / dx^2) sum w v d dx = (4 / dx) sum w v d
            cs = APIC_D_INV * inv_dx
            csum = c00 + c01 + c02 + c10 + c11 + c12 + c20 + c21 + c22
            if not (math.isfinite(vx + vy + vz) and math.isfinite(csum)):
                cbad += 1
                continue
            v[p, 0], v[p, 1], v[p, 2] = vx, vy, vz
            C[p, 0, 0], C[p, 0, 1], C[p, 0, 2] = cs * c00, cs * c01, cs * c02
            C[p, 1, 0], C[p, 1, 1], C[p, 1, 2] = cs * c10, cs * c11, cs * c12
            C[p, 2, 0], C[p, 2, 1], C[p, 2, 2] = cs * c20, cs * c21, cs * c22
            cvmax2 = max(cvmax2, vx * vx + vy * vy + vz * vz)
            vel = (vx, vy, vz)
            clamped = False
            for a in range(3):
                xa = x[p, a] + dt * vel[a]
                if xa < lo[a]:
                    xa = lo[a]
                    clamped = True
                elif xa > hi[a]:
                    xa = hi[a]
                    clamped = True
                x[p, a] = xa
            if clamped:
                cclamp += 1
            # F^E <- (I + dt C) F^E
            for r in range(3):
                for q in range(3):
                    acc = F[p, r, q]
                    for s in range(3):
                        acc += dt * C[p, r, s] * F[p, s, q]
                    Fn[r, q] = acc
            elastoplastic_update(Fn, F[p], tau[p], lam, mu, alpha, S, Q, U, V, sig, eps)
            fsum = 0.0
            for r in range(3):
                for q in range(3):
                    fsum += F[p, r, q] + tau[p, r, q]
            if not math.isfinite(fsum):
                cbad += 1
        chunk_stats[ch, 0] = cvmax2
        chunk_stats[ch, 1] = cbad
        chunk_stats[ch, 2] = cclamp
    out_stats[0] = 0.0
    out_stats[1] = 0.0
    out_stats[2] = 0.0
    for ch in range(nchunks):
        out_stats[0] = max(out_stats[0], chunk_stats[ch, 0])
        out_stats[1] += chunk_stats[ch, 1]
        out_stats[2] += chunk_stats[ch, 2]


@njit(cache=True)
def find_nonfinite(x, v, C, F, tau):
    """First (particle slot, field code) holding a non-finite value, or (-1, -1)."""
    for p in range(x.shape[0]):
        for a in range(3):
            if not math.isfinite(x[p, a]):
                return p, FIELD_POSITION
        for a in range(3):
            if not math.isfinite(v[p, a]):
                return p, FIELD_VELOCITY
        for r in range(3):
            for q in range(3):
                if not math.isfinite(C[p, r, q]):
                    return p, FIELD_AFFINE
        for r in range(3):
            for q in range(3):
                if not math.isfinite(F[p, r, q]):
                    return p, FIELD_DEFORMATION
        for r in range(3):
            for q in range(3):
                if not math.isfinite(tau[p, r, q]):
                    return p, FIELD_STRESS
    return -1, -1


@njit(parallel=True, cache=True)
def particle_sums(x, v, mass, gravity, out):
    """out [8]: mass (kg), momentum xyz (kg m/s), kinetic energy (J), gravitational
    potential energy -m g.x (J), max |v| (m/s), spare."""
    n = x.shape[0]
    msum = 0.0
    px = 0.0
    py = 0.0
    pz = 0.0
    ke = 0.0
    pe = 0.0
    vmax2 = 0.0
    for p in prange(n):
        m = mass[p]
        msum += m
        px += m * v[p, 0]
        py += m * v[p, 1]
        pz += m * v[p, 2]
        s2 = v[p, 0] ** 2 + v[p, 1] ** 2 + v[p, 2] ** 2
        ke += 0.5 * m * s2
        pe -= m * (gravity[0] * x[p, 0] + gravity[1] * x[p, 1] + gravity[2] * x[p, 2])
        vmax2 = max(vmax2, s2)
    out[0] = msum
    out[1] = px
    out[2] = py
    out[3] = pz
    out[4] = ke
    out[5] = pe
    out[6] = math.sqrt(vmax2)
    out[7] = 0.0
