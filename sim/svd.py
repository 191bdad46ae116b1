"""Fast 3x3 singular value decomposition for numba kernels.

F = U diag(sigma) V^T with U, V proper rotations (det = +1) and sigma sorted by decreasing
magnitude; sigma[2] carries the sign of det(F) (negative only for an inverted F). Method:
cyclic Jacobi eigen-decomposition of the symmetric F^T F gives V; the columns of F V,
orthonormalized, give U. Accurate to a few ulps for the well-conditioned deformation
gradients of MPM (singular values near 1); tested against numpy.linalg.svd.
"""

from __future__ import annotations

import math

from numba import njit

JACOBI_MAX_SWEEPS = 12
JACOBI_REL_TOL = 1e-30  # stop when off-diagonal^2 < tol * trace^2 (F^T F)
TINY = 1e-300


@njit(cache=True, inline="always")
def _rotate(S, V, p, q):
    """One Jacobi rotation zeroing S[p, q] (S symmetric 3x3), accumulated into V."""
    apq = S[p, q]
    if apq == 0.0:
        return
    theta = (S[q, q] - S[p, p]) / (2.0 * apq)
    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    for k in range(3):
        skp = S[k, p]
        skq = S[k, q]
        S[k, p] = c * skp - s * skq
        S[k, q] = s * skp + c * skq
    for k in range(3):
        spk = S[p, k]
        sqk = S[q, k]
        S[p, k] = c * spk - s * sqk
        S[q, k] = s * spk + c * sqk
    for k in range(3):
        vkp = V[k, p]
        vkq = V[k, q]
        V[k, p] = c * vkp - s * vkq
        V[k, q] = s * vkp + c * vkq


@njit(cache=True, inline="always")
def sym_eig3(S, Q, rel_tol):
    """Cyclic Jacobi on the symmetric S [3, 3] (overwritten: its diagonal ends holding the
    eigenvalues, in no particular order) until off-diagonal^2 <= rel_tol * trace^2; Q [3, 3]
    receives the eigenvectors as columns (S_in = Q diag(S) Q^T). No allocation."""
    for i in range(3):
        for j in range(3):
            Q[i, j] = 1.0 if i == j else 0.0
    scale = S[0, 0] + S[1, 1] + S[2, 2]
    tol = rel_tol * scale * scale + TINY
    for _ in range(JACOBI_MAX_SWEEPS):
        off = S[0, 1] * S[0, 1] + S[0, 2] * S[0, 2] + S[1, 2] * S[1, 2]
        if off <= tol:
            break
        _rotate(S, Q, 0, 1)
        _rotate(S, Q, 0, 2)
        _rotate(S, Q, 1, 2)


@njit(cache=True)
def svd3(F, U, sig, V, S):
    """Write U [3,3], sig [3], V [3,3] (float64) with F = U diag(sig) V^T. S [3,3] is
    scratch (no allocation inside, so it is cheap in a per-particle loop)."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += F[k, i] * F[k, j]
            S[i, j] = acc
    sym_eig3(S, V, JACOBI_REL_TOL)
    # sort eigenvalues (squared singular values) in decreasing order, permuting V
    for i in range(2):
        best = i
        for j in range(i + 1, 3):
            if S[j, j] > S[best, best]:
                best = j
        if best != i:
            S[i, i], S[best, best] = S[best, best], S[i, i]
            for k in range(3):
                V[k, i], V[k, best] = V[k, best], V[k, i]
    # make V a proper rotation
    det_v = (V[0, 0] * (V[1, 1] * V[2, 2] - V[1, 2] * V[2, 1])
             - V[0, 1] * (V[1, 0] * V[2, 2] - V[1, 2] * V[2, 0])
             + V[0, 2] * (V[1, 0] * V[2, 1] - V[1, 1] * V[2, 0]))
    if det_v < 0.0:
        for k in range(3):
            V[k, 2] = -V[k, 2]
    # B = F V, kept in U; U from Gram-Schmidt on B's columns, third column by cross product
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += F[i, k] * V[k, j]
            U[i, j] = acc
    n0 = math.sqrt(U[0, 0] ** 2 + U[1, 0] ** 2 + U[2, 0] ** 2)
    if n0 > TINY:
        for k in range(3):
            U[k, 0] = U[k, 0] / n0
    else:
        U[0, 0], U[1, 0], U[2, 0] = 1.0, 0.0, 0.0
    d = U[0, 0] * U[0, 1] + U[1, 0] * U[1, 1] + U[2, 0] * U[2, 1]
    u1x = U[0, 1] - d * U[0, 0]
    u1y = U[1, 1] - d * U[1, 0]
    u1z = U[2, 1] - d * U[2, 0]
    n1 = math.sqrt(u1x * u1x + u1y * u1y + u1z * u1z)
    if n1 > TINY * 1e10 and n1 > 1e-12 * n0:
        U[0, 1], U[1, 1], U[2, 1] = u1x / n1, u1y / n1, u1z / n1
    else:
        # rank <= 1: any unit vector orthogonal to U[:, 0]
        ax, ay, az = U[0, 0], U[1, 0], U[2, 0]
        if abs(ax) < 0.9:
            px, py, pz = 0.0, -az, ay  # e_x cross u0
        else:
            px, py, pz = az, 0.0, -ax  # e_y cross u0
        pn = math.sqrt(px * px + py * py + pz * pz)
        U[0, 1], U[1, 1], U[2, 1] = px / pn, py / pn, pz / pn
        n1 = 0.0
    cx = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
    cy = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
    cz = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    sig[0] = n0
    sig[1] = n1
    sig[2] = cx * U[0, 2] + cy * U[1, 2] + cz * U[2, 2]
    U[0, 2], U[1, 2], U[2, 2] = cx, cy, cz
