"""MLS-MPM kernels (Hu et al. 2018) with an APIC/FLIP transfer and quadratic B-splines.

Numba kernels on plain arrays and scalars; the driver (`sim.driver.Simulator`) owns the
state and the phase order: bin -> P2G scatter -> grid gather + update -> G2P. Conventions:

* grid: [nx, ny, nz, GRID_FIELDS] float64; [..., :3] momentum (kg m/s) after the P2G sum
  and velocity (m/s) after the grid update, [..., 3] mass (kg), [..., 4:7] the APIC momentum
  without the stress impulse (kg m/s) after the P2G sum and the velocity change of the
  step (m/s, for the FLIP part of G2P) after the grid update. Local node (0, 0, 0) sits at
  x0 (m).
* a particle at cell coordinate X = (x - x0) / dx has base node floor(X - 1/2) and
  touches the 3x3x3 nodes base + {0, 1, 2}. x0 (m) is the position of node 0 of the
  *whole-domain* grid, and `off` [3] int64 is the whole-domain index of the local grid's
  node (0, 0, 0): a rank's slab of the grid reads node base - off. Only integer indices
  depend on off, so a particle's weights are bitwise the same on every rank (0 for a
  single process).

Race-free, deterministic parallel P2G: particles are counting-sorted (stable, parallel over
fixed chunks) by block of BLOCK_CELLS^3 base cells. Each non-empty block scatters its
particles, in sorted order, into a private buffer of BUF_NODES^3 nodes ([b*B, b*B + B + 1]
per axis); blocks run in parallel and share nothing. Then every grid node sums the (at
most 8) buffers covering it in a fixed order, fused with the grid update. The summation
order per node, hence the result, does not depend on the thread count; two parallel loops
per step instead of one per color (fewer barriers, which matters on a shared machine).

Per-particle work in P2G and G2P is on scalars (no scratch arrays): weights per axis,
separable sums over the 3x3x3 stencil, the 3x3 eigen-solve in registers.

Kernels release the GIL (nogil): an in situ publisher's sender thread (minority.insitu)
culls and encodes beside them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from minority.sim.plasticity import (
    elastoplastic_update,
    elastoplastic_update_scalar,
    elastoplastic_update_series,
)

BLOCK_CELLS = 4  # block edge in cells (>= 2: a node is covered by at most 2 blocks per axis)
BIN_CHUNKS = 16  # chunks of the parallel counting sort (fixed: the sort is the serial one)
BUF_NODES = BLOCK_CELLS + 2  # nodes per axis a block's particles reach: [b*B, b*B + B + 1]
GATHER_GROUP = 8  # blocks per parallel work item of the grid gather + update
G2P_CHUNK = 512  # particles per parallel work item in G2P
# Per node: momentum/velocity x, y, z; mass; force-free momentum/velocity change x, y, z;
# one unused field, so that a node is 64 bytes (stride 7 made P2G 1.4x slower than 8).
GRID_FIELDS = 8
APIC_D_INV = 4.0  # inverse of the quadratic B-spline inertia tensor D = dx^2 / 4 (per dx^2)
WALL_TOL_CELLS = 1e-6  # a node this close (in cells) to a wall plane counts as on it
# LLVM fast-math for the P2G scatter: contraction (FMA), reassociation, reciprocal and
# signed-zero freedom. The generated code does not depend on the thread count, so results
# stay bitwise independent of it. G2P gets contraction (FMA) only: with more flags LLVM
# folded away its finiteness checks once (the NaN guard test failed); "contract" cannot.
FASTMATH = {"contract", "reassoc", "arcp", "nsz"}
G2P_FASTMATH = {"contract"}

FIELD_POSITION, FIELD_VELOCITY, FIELD_AFFINE, FIELD_DEFORMATION, FIELD_STRESS = range(5)
FIELD_NAMES = ("position", "velocity", "affine_velocity", "deformation_gradient", "stress")


@njit(cache=True, inline="always")
def _block_key(x, p, x0, inv_dx, grid_shape, off, nby, nbz):
    """Linear block index (local grid) of particle p's base cell, or -1 if its stencil would
    leave the local grid (or its position is not finite)."""
    k = 0
    for a in range(3):
        X = (x[p, a] - x0[a]) * inv_dx
        if not (X >= 0.5 + off[a] and X < grid_shape[a] + off[a] - 1.5):
            return -1
        b = (int(X - 0.5) - off[a]) // BLOCK_CELLS  # X - 0.5 >= off >= 0: truncation is floor
        k = b if a == 0 else (k * (nby if a == 1 else nbz) + b)
    return k


@njit(parallel=True, cache=True, nogil=True)
def _count_keys(x, x0, inv_dx, grid_shape, off, nblocks3, key, counts, first_bad):
    """Per chunk c of the particles (counts.shape[0] equal chunks): key[p] (block of particle
    p, or -1), counts[c, k] (particles of chunk c in block k), first_bad[c] (first p with
    key -1, or n)."""
    n = x.shape[0]
    nby, nbz = nblocks3[1], nblocks3[2]
    nch = counts.shape[0]
    size = (n + nch - 1) // nch
    for c in prange(nch):
        counts[c, :] = 0
        first_bad[c] = n
        for p in range(c * size, min(n, (c + 1) * size)):
            k = _block_key(x, p, x0, inv_dx, grid_shape, off, nby, nbz)
            key[p] = k
            if k < 0:
                if first_bad[c] == n:
                    first_bad[c] = p
            else:
                counts[c, k] += 1


@njit(parallel=True, cache=True, nogil=True)
def _place_keys(key, offsets, order):
    """order[offsets[c, k]++] = p over the particles p of chunk c, in increasing p."""
    n = key.shape[0]
    nch = offsets.shape[0]
    size = (n + nch - 1) // nch
    for c in prange(nch):
        for p in range(c * size, min(n, (c + 1) * size)):
            k = key[p]
            order[offsets[c, k]] = p
            offsets[c, k] += 1


@njit(cache=True, nogil=True)
def bin_particles(x, x0, inv_dx, grid_shape, off, nblocks3, block_start, order, block_slot,
                  active_blocks, key, counts, first_bad):
    """Stable counting sort of particles by block, in parallel over counts.shape[0] equal
    chunks of particles (the result is the serial stable sort, whatever the thread count).
    Writes order [n] (sorted slot -> particle slot), block_start [nblocks + 1], block_slot
    [nblocks] (index of a non-empty block among the active ones, -1 for an empty block)
    and active_blocks [nblocks] (the non-empty blocks in block order, first n_active
    entries). counts [nchunks, nblocks] and first_bad [nchunks] are scratch. Returns
    (bad, n_active): bad is -1, or the first particle whose stencil leaves the grid."""
    n = x.shape[0]
    nb = nblocks3[0] * nblocks3[1] * nblocks3[2]
    nch = counts.shape[0]
    _count_keys(x, x0, inv_dx, grid_shape, off, nblocks3, key, counts, first_bad)
    bad = n
    for c in range(nch):
        bad = min(bad, first_bad[c])
    if bad < n:
        return bad, 0
    # counts -> start offset of each (chunk, block), block by block, chunks in order
    run = 0
    n_active = 0
    for k in range(nb):
        block_start[k] = run
        for c in range(nch):
            m = counts[c, k]
            counts[c, k] = run
            run += m
        if run > block_start[k]:
            block_slot[k] = n_active
            active_blocks[n_active] = k
            n_active += 1
        else:
            block_slot[k] = -1
    block_start[nb] = run
    _place_keys(key, counts, order)
    return -1, n_active


@njit(cache=True, inline="always")
def _weights3(X):
    """Quadratic B-spline along one axis: local cell coordinate X -> (base node, fx =
    X - base, weights of nodes base + 0, 1, 2)."""
    fb = math.floor(X - 0.5)
    fx = X - fb
    return (int(fb), fx, 0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2,
            0.5 * (fx - 0.5) ** 2)


@njit(parallel=True, cache=True, nogil=True, fastmath=FASTMATH)
def p2g_scatter(x, v, C, tau, mass, vol0, order, block_start, active_blocks, n_active,
                nblocks3, buf, x0, off, inv_dx, dt):
    """Particle to grid, part 1: each non-empty block scatters mass and APIC momentum plus
    the MLS stress impulse -dt vol0 (4 / dx^2) tau (x_i - x_p) of its particles (in sorted
    order), and the APIC momentum alone (for FLIP), into its own buffer buf[slot]
    [BUF_NODES^3, GRID_FIELDS] covering nodes
    [b*B, b*B + B + 1] per axis. Blocks run in parallel and share nothing. Per particle on
    scalars: the affine part A (x_i - x_p) is built up per (i, j) row, then per node."""
    dx = 1.0 / inv_dx
    stress_scale = -dt * APIC_D_INV * inv_dx * inv_dx
    nby, nbz = nblocks3[1], nblocks3[2]
    for sl in prange(n_active):
        b = active_blocks[sl]
        ox = (b // (nby * nbz)) * BLOCK_CELLS + off[0]
        oy = ((b // nbz) % nby) * BLOCK_CELLS + off[1]
        oz = (b % nbz) * BLOCK_CELLS + off[2]
        bb = buf[sl].reshape(-1)  # flat [BUF_NODES^3 * GRID_FIELDS]: contiguous node fields
        for e in range(bb.shape[0]):
            bb[e] = 0.0
        for s in range(block_start[b], block_start[b + 1]):
            p = order[s]
            m = mass[p]
            sv = stress_scale * vol0[p]
            bx, fx, wx0, wx1, wx2 = _weights3((x[p, 0] - x0[0]) * inv_dx)
            by, fy, wy0, wy1, wy2 = _weights3((x[p, 1] - x0[1]) * inv_dx)
            bz, fz, wz0, wz1, wz2 = _weights3((x[p, 2] - x0[2]) * inv_dx)
            bx -= ox
            by -= oy
            bz -= oz
            m00, m01, m02 = m * C[p, 0, 0], m * C[p, 0, 1], m * C[p, 0, 2]
            m10, m11, m12 = m * C[p, 1, 0], m * C[p, 1, 1], m * C[p, 1, 2]
            m20, m21, m22 = m * C[p, 2, 0], m * C[p, 2, 1], m * C[p, 2, 2]
            a00 = sv * tau[p, 0, 0] + m00
            a01 = sv * tau[p, 0, 1] + m01
            a02 = sv * tau[p, 0, 2] + m02
            a10 = sv * tau[p, 1, 0] + m10
            a11 = sv * tau[p, 1, 1] + m11
            a12 = sv * tau[p, 1, 2] + m12
            a20 = sv * tau[p, 2, 0] + m20
            a21 = sv * tau[p, 2, 1] + m21
            a22 = sv * tau[p, 2, 2] + m22
            mvx, mvy, mvz = m * v[p, 0], m * v[p, 1], m * v[p, 2]
            dz0, dz1, dz2 = -fz * dx, (1.0 - fz) * dx, (2.0 - fz) * dx
            for i in range(3):
                dxp = (i - fx) * dx
                wx = wx0 if i == 0 else (wx1 if i == 1 else wx2)
                for j in range(3):
                    dyp = (j - fy) * dx
                    wy = wy0 if j == 0 else (wy1 if j == 1 else wy2)
                    wij = wx * wy
                    hx = mvx + a00 * dxp + a01 * dyp
                    hy = mvy + a10 * dxp + a11 * dyp
                    hz = mvz + a20 * dxp + a21 * dyp
                    qx = mvx + m00 * dxp + m01 * dyp
                    qy = mvy + m10 * dxp + m11 * dyp
                    qz = mvz + m20 * dxp + m21 * dyp
                    o = (((bx + i) * BUF_NODES + by + j) * BUF_NODES + bz) * GRID_FIELDS
                    for k in range(3):
                        wz = wz0 if k == 0 else (wz1 if k == 1 else wz2)
                        dzp = dz0 if k == 0 else (dz1 if k == 1 else dz2)
                        wt = wij * wz
                        ok = o + GRID_FIELDS * k
                        bb[ok] += wt * (hx + a02 * dzp)
                        bb[ok + 1] += wt * (hy + a12 * dzp)
                        bb[ok + 2] += wt * (hz + a22 * dzp)
                        bb[ok + 3] += wt * m
                        bb[ok + 4] += wt * (qx + m02 * dzp)
                        bb[ok + 5] += wt * (qy + m12 * dzp)
                        bb[ok + 6] += wt * (qz + m22 * dzp)


@njit(cache=True, inline="always")
def _node_update(grid, i, j, k, origin, dx, dt, gravity, wall_axis, wall_pos, wall_side,
                 wall_mu, wall_lo, wall_hi, tol, vel, pos):
    """Grid update of node (i, j, k): momentum -> velocity, add gravity dt, then
    Coulomb-friction walls: at a node inside wall w's solid half-space
    (side * (x[axis] - pos) <= 0, within lo..hi) an approaching normal velocity vn < 0 is
    removed and the tangential speed reduced by mu |vn| (stopped if smaller); separating
    velocities are kept. Fields 4:7 become the step's velocity change (new velocity minus
    the force-free APIC velocity). vel, pos [3] are scratch."""
    m = grid[i, j, k, 3]
    if m <= 0.0:
        for f in range(GRID_FIELDS):
            if f != 3:
                grid[i, j, k, f] = 0.0
        return
    pos[0] = (origin[0] + i) * dx
    pos[1] = (origin[1] + j) * dx
    pos[2] = (origin[2] + k) * dx
    for a in range(3):
        vel[a] = grid[i, j, k, a] / m + dt * gravity[a]
    for w in range(wall_axis.shape[0]):
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
    for a in range(3):
        grid[i, j, k, a] = vel[a]
        grid[i, j, k, 4 + a] = vel[a] - grid[i, j, k, 4 + a] / m


@njit(parallel=True, cache=True, nogil=True)
def grid_gather_update(buf, block_slot, nblocks3, grid, origin, dx, dt, gravity, wall_axis,
                       wall_pos, wall_side, wall_mu, wall_lo, wall_hi):
    """Particle to grid, part 2, fused with the grid update. Every node of the grid (all
    of it is written, no zeroing needed) sums the buffers of the blocks whose stencil range
    covers it: the node's own block b and, for its first two nodes per axis, block b - 1 —
    up to 8 buffers, always in the same order (b - 1 before b per axis, x then y then z).
    The summed node (momentum, kg m/s; mass, kg) then gets `_node_update` (velocity, m/s).
    Parallel over groups of GATHER_GROUP blocks; the sum per node, hence the grid, does not
    depend on the thread count."""
    nbx, nby, nbz = nblocks3[0], nblocks3[1], nblocks3[2]
    nx, ny, nz = grid.shape[0], grid.shape[1], grid.shape[2]
    nb = nbx * nby * nbz
    tol = WALL_TOL_CELLS * dx
    for grp in prange((nb + GATHER_GROUP - 1) // GATHER_GROUP):
        vel = np.empty(3)
        pos = np.empty(3)
        for b in range(grp * GATHER_GROUP, min(nb, (grp + 1) * GATHER_GROUP)):
            cx = b // (nby * nbz)
            cy = (b // nbz) % nby
            cz = b % nbz
            x_lo, y_lo, z_lo = cx * BLOCK_CELLS, cy * BLOCK_CELLS, cz * BLOCK_CELLS
            x_hi = min(x_lo + BLOCK_CELLS, nx)
            y_hi = min(y_lo + BLOCK_CELLS, ny)
            z_hi = min(z_lo + BLOCK_CELLS, nz)
            for gi in range(x_lo, x_hi):
                for gj in range(y_lo, y_hi):
                    for gk in range(z_lo, z_hi):
                        for f in range(GRID_FIELDS):
                            grid[gi, gj, gk, f] = 0.0
            touched = False
            for sx in range(max(cx - 1, 0), cx + 1):
                for sy in range(max(cy - 1, 0), cy + 1):
                    for sz in range(max(cz - 1, 0), cz + 1):
                        if block_slot[(sx * nby + sy) * nbz + sz] >= 0:
                            touched = True
            if not touched:
                continue  # no particle reaches this block: zero momentum, mass, velocity
            for sx in range(max(cx - 1, 0), cx + 1):
                for sy in range(max(cy - 1, 0), cy + 1):
                    for sz in range(max(cz - 1, 0), cz + 1):
                        sl = block_slot[(sx * nby + sy) * nbz + sz]
                        if sl < 0:
                            continue
                        bb = buf[sl]
                        for gi in range(x_lo, min(x_hi, sx * BLOCK_CELLS + BUF_NODES)):
                            li = gi - sx * BLOCK_CELLS
                            for gj in range(y_lo, min(y_hi, sy * BLOCK_CELLS + BUF_NODES)):
                                lj = gj - sy * BLOCK_CELLS
                                for gk in range(z_lo, min(z_hi, sz * BLOCK_CELLS + BUF_NODES)):
                                    lk = gk - sz * BLOCK_CELLS
                                    for f in range(GRID_FIELDS):
                                        grid[gi, gj, gk, f] += bb[li, lj, lk, f]
            for gi in range(x_lo, x_hi):
                for gj in range(y_lo, y_hi):
                    for gk in range(z_lo, z_hi):
                        _node_update(grid, gi, gj, gk, origin, dx, dt, gravity, wall_axis,
                                     wall_pos, wall_side, wall_mu, wall_lo, wall_hi, tol, vel,
                                     pos)


@njit(parallel=True, cache=True, nogil=True, fastmath=G2P_FASTMATH)
def g2p(x, v, C, F, tau, grid, x0, off, inv_dx, dt, lo, hi, lam, mu, alpha, flip,
        out_stats):
    """Grid to particle: APIC affine field C, advection with the grid velocity (clamped to
    the domain lo..hi, m), F^E <- (I + dt C) F^E, Drucker-Prager return mapping, Kirchhoff
    stress. The particle velocity blends FLIP and PIC (Fei et al. 2021's APIC/FLIP hybrid):
    v <- flip (v + sum w dv) + (1 - flip) sum w v_grid, dv the nodes' velocity change.

    out_stats [3] float64 receives: max |v|^2 (m^2/s^2), non-finite particle count, clamped
    particle count. A particle with a non-finite velocity is left where it was.
    Per-particle work is on scalars (no scratch arrays) except the rare full-SVD fallback
    of an inverted or collapsed F^E."""
    n = x.shape[0]
    nchunks = (n + G2P_CHUNK - 1) // G2P_CHUNK
    chunk_stats = np.zeros((nchunks, 3))  # per chunk: max |v|^2, non-finite, clamped
    cs = APIC_D_INV * inv_dx  # C = (4 / dx^2) sum w v (x_i - x_p) = (4 / dx) sum w v d
    gf = grid.reshape(-1)  # flat [nx * ny * nz * GRID_FIELDS] view: one offset per z row
    gny, gnz = grid.shape[1], grid.shape[2]
    for ch in prange(nchunks):
        cvmax2 = 0.0
        cbad = 0
        cclamp = 0
        for p in range(ch * G2P_CHUNK, min(n, (ch + 1) * G2P_CHUNK)):
            bx, fx, wx0, wx1, wx2 = _weights3((x[p, 0] - x0[0]) * inv_dx)
            by, fy, wy0, wy1, wy2 = _weights3((x[p, 1] - x0[1]) * inv_dx)
            bz, fz, wz0, wz1, wz2 = _weights3((x[p, 2] - x0[2]) * inv_dx)
            bx -= off[0]
            by -= off[1]
            bz -= off[2]
            # Separable gather: v = sum w g and sum w g d_b = sum w g n_b - f_b v, with the
            # node offset n in {0, 1, 2} per axis; sums over z, then y, then x.
            wz1b, wz2b = wz1, 2.0 * wz2  # weight * n along z
            vx = vy = vz = 0.0
            xx = xy = xz = 0.0  # sum w g n_x, components x, y, z
            yx = yy = yz = 0.0  # sum w g n_y
            zx = zy = zz = 0.0  # sum w g n_z
            dvx = dvy = dvz = 0.0  # sum w dv (grid fields 4:7)
            for i in range(3):
                tx = ty = tz = 0.0  # sum over j, k of wy wz g
                ux = uy = uz = 0.0  # sum of wy n_y wz g
                sx = sy = sz = 0.0  # sum of wy wz n_z g
                rx = ry = rz = 0.0  # sum of wy wz dv
                for j in range(3):
                    o0 = (((bx + i) * gny + by + j) * gnz + bz) * GRID_FIELDS  # node (i, j, 0)
                    o1, o2 = o0 + GRID_FIELDS, o0 + 2 * GRID_FIELDS  # nodes (i, j, 1), (i, j, 2)
                    g0x, g0y, g0z = gf[o0], gf[o0 + 1], gf[o0 + 2]
                    g1x, g1y, g1z = gf[o1], gf[o1 + 1], gf[o1 + 2]
                    g2x, g2y, g2z = gf[o2], gf[o2 + 1], gf[o2 + 2]
                    kx = wz0 * g0x + wz1 * g1x + wz2 * g2x
                    ky = wz0 * g0y + wz1 * g1y + wz2 * g2y
                    kz = wz0 * g0z + wz1 * g1z + wz2 * g2z
                    nx_ = wz1b * g1x + wz2b * g2x
                    ny_ = wz1b * g1y + wz2b * g2y
                    nz_ = wz1b * g1z + wz2b * g2z
                    lx = wz0 * gf[o0 + 4] + wz1 * gf[o1 + 4] + wz2 * gf[o2 + 4]
                    ly = wz0 * gf[o0 + 5] + wz1 * gf[o1 + 5] + wz2 * gf[o2 + 5]
                    lz = wz0 * gf[o0 + 6] + wz1 * gf[o1 + 6] + wz2 * gf[o2 + 6]
                    wy = wy0 if j == 0 else (wy1 if j == 1 else wy2)
                    wyn = wy * j
                    rx += wy * lx
                    ry += wy * ly
                    rz += wy * lz
                    tx += wy * kx
                    ty += wy * ky
                    tz += wy * kz
                    ux += wyn * kx
                    uy += wyn * ky
                    uz += wyn * kz
                    sx += wy * nx_
                    sy += wy * ny_
                    sz += wy * nz_
                wx = wx0 if i == 0 else (wx1 if i == 1 else wx2)
                wxn = wx * i
                dvx += wx * rx
                dvy += wx * ry
                dvz += wx * rz
                vx += wx * tx
                vy += wx * ty
                vz += wx * tz
                xx += wxn * tx
                xy += wxn * ty
                xz += wxn * tz
                yx += wx * ux
                yy += wx * uy
                yz += wx * uz
                zx += wx * sx
                zy += wx * sy
                zz += wx * sz
            c00, c01, c02 = xx - fx * vx, yx - fy * vx, zx - fz * vx
            c10, c11, c12 = xy - fx * vy, yy - fy * vy, zy - fz * vy
            c20, c21, c22 = xz - fx * vz, yz - fy * vz, zz - fz * vz
            csum = c00 + c01 + c02 + c10 + c11 + c12 + c20 + c21 + c22
            pvx = flip * (v[p, 0] + dvx) + (1.0 - flip) * vx
            pvy = flip * (v[p, 1] + dvy) + (1.0 - flip) * vy
            pvz = flip * (v[p, 2] + dvz) + (1.0 - flip) * vz
            if not (math.isfinite(vx + vy + vz) and math.isfinite(csum)
                    and math.isfinite(pvx + pvy + pvz)):
                cbad += 1
                continue
            c00, c01, c02 = cs * c00, cs * c01, cs * c02
            c10, c11, c12 = cs * c10, cs * c11, cs * c12
            c20, c21, c22 = cs * c20, cs * c21, cs * c22
            v[p, 0], v[p, 1], v[p, 2] = pvx, pvy, pvz
            C[p, 0, 0], C[p, 0, 1], C[p, 0, 2] = c00, c01, c02
            C[p, 1, 0], C[p, 1, 1], C[p, 1, 2] = c10, c11, c12
            C[p, 2, 0], C[p, 2, 1], C[p, 2, 2] = c20, c21, c22
            cvmax2 = max(cvmax2, vx * vx + vy * vy + vz * vz, pvx * pvx + pvy * pvy + pvz * pvz)
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
            # F^E <- (I + dt C) F^E, as F + dt (C F) row by row
            e00, e01, e02 = F[p, 0, 0], F[p, 0, 1], F[p, 0, 2]
            e10, e11, e12 = F[p, 1, 0], F[p, 1, 1], F[p, 1, 2]
            e20, e21, e22 = F[p, 2, 0], F[p, 2, 1], F[p, 2, 2]
            f00 = e00 + dt * c00 * e00 + dt * c01 * e10 + dt * c02 * e20
            f01 = e01 + dt * c00 * e01 + dt * c01 * e11 + dt * c02 * e21
            f02 = e02 + dt * c00 * e02 + dt * c01 * e12 + dt * c02 * e22
            f10 = e10 + dt * c10 * e00 + dt * c11 * e10 + dt * c12 * e20
            f11 = e11 + dt * c10 * e01 + dt * c11 * e11 + dt * c12 * e21
            f12 = e12 + dt * c10 * e02 + dt * c11 * e12 + dt * c12 * e22
            f20 = e20 + dt * c20 * e00 + dt * c21 * e10 + dt * c22 * e20
            f21 = e21 + dt * c20 * e01 + dt * c21 * e11 + dt * c22 * e21
            f22 = e22 + dt * c20 * e02 + dt * c21 * e12 + dt * c22 * e22
            # the series path succeeds only on a finite state with finite results
            if not elastoplastic_update_series(f00, f01, f02, f10, f11, f12, f20, f21, f22,
                                               F, tau, p, lam, mu, alpha):
                if not elastoplastic_update_scalar(f00, f01, f02, f10, f11, f12, f20, f21,
                                                   f22, F, tau, p, lam, mu, alpha):
                    _collapsed_update(f00, f01, f02, f10, f11, f12, f20, f21, f22, F[p],
                                      tau[p], lam, mu, alpha)
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


@njit(cache=True, nogil=True)
def _collapsed_update(f00, f01, f02, f10, f11, f12, f20, f21, f22, F_out, tau_out, lam, mu,
                      alpha):
    """Rare path (inverted or collapsed trial F^E): the array-based full-SVD update."""
    Fn = np.empty((3, 3))
    Fn[0, 0], Fn[0, 1], Fn[0, 2] = f00, f01, f02
    Fn[1, 0], Fn[1, 1], Fn[1, 2] = f10, f11, f12
    Fn[2, 0], Fn[2, 1], Fn[2, 2] = f20, f21, f22
    scratch = np.empty((4, 3, 3))
    vec = np.empty((2, 3))
    elastoplastic_update(Fn, F_out, tau_out, lam, mu, alpha, scratch[0], scratch[1],
                         scratch[2], scratch[3], vec[0], vec[1])


@njit(cache=True, inline="always")
def _take_row(src, p, dst, k):
    for f in range(src.shape[1]):
        dst[k, f] = src[p, f]


@njit(parallel=True, cache=True, nogil=True)
def permute_particles(order, src, dst):
    """dst[i][k] = src[i][order[k]] for the nine particle arrays (x, v, C, F, tau, mass,
    vol0, x0, pid), each viewed as [n, m]; src and dst are tuples. One parallel loop."""
    for k in prange(order.shape[0]):
        p = order[k]
        _take_row(src[0], p, dst[0], k)
        _take_row(src[1], p, dst[1], k)
        _take_row(src[2], p, dst[2], k)
        _take_row(src[3], p, dst[3], k)
        _take_row(src[4], p, dst[4], k)
        _take_row(src[5], p, dst[5], k)
        _take_row(src[6], p, dst[6], k)
        _take_row(src[7], p, dst[7], k)
        _take_row(src[8], p, dst[8], k)


@njit(cache=True, nogil=True)
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


@njit(parallel=True, cache=True, nogil=True)
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
