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


@njit(cache=True, inline="always")
def _rot_scalar(app, aqq, apq, arp, arq, v0p, v1p, v2p, v0q, v1q, v2q, skip2):
    """One Jacobi rotation on scalars zeroing a_pq of a symmetric 3x3 (r = the third
    index), with the symmetric update of Numerical Recipes (a_pp - t a_pq, a_qq + t a_pq,
    only the r row rotated) and eigenvector columns p, q rotated. Same rotation as
    `_rotate` (t = tan of the angle, |angle| <= pi/4), formed with a shorter chain of
    divisions and square roots: r = sqrt(d^2 + 4 a_pq^2), d = a_qq - a_pp,
    t = 2 a_pq sign(d) / (|d| + r), c^2 = (1 + |d| / r) / 2 (= 1 / (1 + t^2)), s = t c.
    Skipped (nothing changes) when a_pq^2 <= skip2. Returns (app, aqq, arp, arq, v0p, v1p,
    v2p, v0q, v1q, v2q); the new a_pq is 0 unless skipped."""
    if apq * apq <= skip2:
        return app, aqq, arp, arq, v0p, v1p, v2p, v0q, v1q, v2q
    d = aqq - app
    ad = abs(d)
    r = math.sqrt(d * d + 4.0 * apq * apq)
    t = 2.0 * apq / (ad + r)
    if d < 0.0:
        t = -t
    c = math.sqrt(0.5 + 0.5 * (ad / r))
    s = t * c
    return (app - t * apq, aqq + t * apq, c * arp - s * arq, s * arp + c * arq,
            c * v0p - s * v0q, c * v1p - s * v1q, c * v2p - s * v2q,
            s * v0p + c * v0q, s * v1p + c * v1q, s * v2p + c * v2q)


@njit(cache=True, inline="always")
def sym_eig3_scalar(a00, a01, a02, a11, a12, a22, rel_tol):
    """`sym_eig3` on the six entries of a symmetric 3x3, in registers (no arrays): cyclic
    Jacobi until off-diagonal^2 <= rel_tol * trace^2. Returns (l0, l1, l2, q00, q01, q02,
    q10, q11, q12, q20, q21, q22): eigenvalues (no particular order) and the eigenvector
    matrix Q (columns), A = Q diag(l) Q^T."""
    q00, q01, q02 = 1.0, 0.0, 0.0
    q10, q11, q12 = 0.0, 1.0, 0.0
    q20, q21, q22 = 0.0, 0.0, 1.0
    scale = a00 + a11 + a22
    tol = rel_tol * scale * scale + TINY
    skip2 = tol / 3.0  # a rotation of an entry this small is not needed to reach tol
    for _ in range(JACOBI_MAX_SWEEPS):
        if a01 * a01 + a02 * a02 + a12 * a12 <= tol:
            break
        # (p, q) = (0, 1), r = 2
        a00, a11, a02, a12, q00, q10, q20, q01, q11, q21 = _rot_scalar(
            a00, a11, a01, a02, a12, q00, q10, q20, q01, q11, q21, skip2)
        if a01 * a01 > skip2:
            a01 = 0.0
        # (p, q) = (0, 2), r = 1
        a00, a22, a01, a12, q00, q10, q20, q02, q12, q22 = _rot_scalar(
            a00, a22, a02, a01, a12, q00, q10, q20, q02, q12, q22, skip2)
        if a02 * a02 > skip2:
            a02 = 0.0
        # (p, q) = (1, 2), r = 0
        a11, a22, a01, a02, q01, q11, q21, q02, q12, q22 = _rot_scalar(
            a11, a22, a12, a01, a02, q01, q11, q21, q02, q12, q22, skip2)
        if a12 * a12 > skip2:
            a12 = 0.0
    return a00, a11, a22, q00, q01, q02, q10, q11, q12, q20, q21, q22
