"""Drucker–Prager return mapping for sand (Klár et al. 2016, SIGGRAPH, Sec. 7.3).

Works on the Hencky (logarithmic) principal strains eps = log(sigma) of the elastic
deformation gradient F^E = U diag(sigma) V^T:

* tension, tr(eps) > 0 -> project to the cone tip, eps = 0 (Klár's text also sends
  |dev eps| = 0 there; a purely volumetric *compression* is inside the cone, so we keep
  it elastic);
* shear yield, dgamma = |dev eps| + (d lam + 2 mu) / (2 mu) tr(eps) alpha > 0 ->
  eps <- eps - dgamma dev(eps) / |dev eps|;
* otherwise elastic, unchanged.

alpha = sqrt(2/3) * 2 sin(phi) / (3 - sin(phi)), d = 3, no cohesion. The Kirchhoff stress is
tau = U diag(2 mu eps + lam tr(eps)) U^T.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from minority.sim.svd import svd3, sym_eig3, sym_eig3_scalar

DIM = 3
SIGMA_MIN = 1e-4  # clamp for singular values before log (an inverted/collapsed F^E)
# Jacobi stop for the stress path: off-diagonal <= 1e-11 * trace of b, i.e. stress errors
# ~1e-11 relative; saves the last (fourth) sweep that the SVD's 1e-30 needs near F = I.
STRESS_JACOBI_REL_TOL = 1e-22


@njit(cache=True, inline="always")
def dp_excess(dev, tr, lam, mu, alpha):
    """dgamma = |dev eps| + (d lam + 2 mu) / (2 mu) tr(eps) alpha: how far a Hencky strain
    with that deviator norm and trace lies outside the cone (<= 0 inside)."""
    return dev + (DIM * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha


@njit(cache=True, inline="always")
def dp_yield(e0, e1, e2, lam, mu, alpha):
    """Yield function dgamma (<= 0 inside the cone) for principal Hencky strains."""
    tr = e0 + e1 + e2
    m = tr / DIM
    dev = math.sqrt((e0 - m) ** 2 + (e1 - m) ** 2 + (e2 - m) ** 2)
    return dp_excess(dev, tr, lam, mu, alpha)


@njit(cache=True, inline="always")
def dp_return_scalar(e0, e1, e2, lam, mu, alpha):
    """Principal Hencky strains (e0, e1, e2) -> (eps0, eps1, eps2, dgamma): projected
    strains and dgamma >= 0 (plastic strain increment, 0 for an elastic state)."""
    tr = e0 + e1 + e2
    m = tr / DIM
    d0, d1, d2 = e0 - m, e1 - m, e2 - m
    dev = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if tr > 0.0:
        return 0.0, 0.0, 0.0, math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    dgamma = dp_excess(dev, tr, lam, mu, alpha)
    if dgamma <= 0.0:  # inside the cone (includes dev = 0 with tr <= 0)
        return e0, e1, e2, 0.0
    f = dgamma / dev  # dev > 0 here since tr <= 0
    return e0 - f * d0, e1 - f * d1, e2 - f * d2, dgamma


@njit(cache=True, inline="always")
def dp_return(e0, e1, e2, eps, lam, mu, alpha):
    """Principal Hencky strains (e0, e1, e2) -> projected strains eps [3]; returns dgamma
    >= 0 (plastic strain increment, 0 for an elastic state)."""
    eps[0], eps[1], eps[2], dgamma = dp_return_scalar(e0, e1, e2, lam, mu, alpha)
    return dgamma


@njit(cache=True, inline="always")
def dp_project(sig, eps, lam, mu, alpha):
    """Principal stretches sig [3] -> projected Hencky strains eps [3]; returns dgamma >= 0
    (plastic strain increment, 0 for an elastic state)."""
    return dp_return(math.log(max(sig[0], SIGMA_MIN)), math.log(max(sig[1], SIGMA_MIN)),
                     math.log(max(sig[2], SIGMA_MIN)), eps, lam, mu, alpha)


def dp_project_numpy(sig: np.ndarray, lam: float, mu: float, alpha: float) -> np.ndarray:
    """Vectorized NumPy version: sig [n, 3] -> projected Hencky strains [n, 3]."""
    e = np.log(np.maximum(sig, SIGMA_MIN))
    tr = e.sum(axis=1, keepdims=True)
    d = e - tr / DIM
    dev = np.sqrt((d * d).sum(axis=1, keepdims=True))
    tip = tr > 0.0
    dgamma = dev + (DIM * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    with np.errstate(divide="ignore", invalid="ignore"):
        shear = e - np.where(dev > 0.0, dgamma / dev, 0.0) * d
    out = np.where(dgamma > 0.0, shear, e)
    return np.where(tip, 0.0, out)


@njit(cache=True, inline="always")
def _write_projected(Fn, U, sig, V, eps, F_out, tau_out, lam, mu):
    """F_out = U diag(exp eps) V^T and tau_out = U diag(2 mu eps + lam tr eps) U^T."""
    tr = eps[0] + eps[1] + eps[2]
    for s in range(3):
        sig[s] = math.exp(eps[s])
        eps[s] = 2.0 * mu * eps[s] + lam * tr  # principal Kirchhoff stress, Pa
    for r in range(3):
        for q in range(3):
            fe = 0.0
            te = 0.0
            for s in range(3):
                fe += U[r, s] * sig[s] * V[q, s]
                te += U[r, s] * eps[s] * U[q, s]
            F_out[r, q] = fe
            tau_out[r, q] = te


@njit(cache=True, inline="always")
def _q_diag_qt(Q, d, out):
    """out [3, 3] = Q diag(d) Q^T (symmetric), Q [3, 3], d [3]."""
    for r in range(3):
        for q in range(r, 3):
            acc = 0.0
            for s in range(3):
                acc += Q[r, s] * d[s] * Q[q, s]
            out[r, q] = acc
            out[q, r] = acc


@njit(cache=True, inline="always")
def elastoplastic_update(Fn, F_out, tau_out, lam, mu, alpha, B, Q, U, V, sig, eps):
    """Trial elastic gradient Fn [3, 3] -> projected F^E (F_out [3, 3]) and Kirchhoff stress
    (tau_out [3, 3], Pa). B, Q, U, V [3, 3] and sig, eps [3] are scratch.

    Uses the left stretch b = Fn Fn^T = Q diag(sigma^2) Q^T: eps = log(sigma) and
    tau = Q diag(2 mu eps + lam tr eps) Q^T need Q and sigma only, and the projected
    F^E = U diag(exp eps) V^T equals Q diag(exp(eps) / sigma) Q^T Fn (since
    V^T = diag(1 / sigma) Q^T Fn), so no V and no Gram-Schmidt. An elastic trial state
    keeps Fn exactly. The principal strains are still needed for the yield check and the
    stress, so this eigen-decomposition cannot be skipped. An inverted or nearly collapsed
    Fn (det <= 0 or a stretch below SIGMA_MIN) takes the full SVD path."""
    det = (Fn[0, 0] * (Fn[1, 1] * Fn[2, 2] - Fn[1, 2] * Fn[2, 1])
           - Fn[0, 1] * (Fn[1, 0] * Fn[2, 2] - Fn[1, 2] * Fn[2, 0])
           + Fn[0, 2] * (Fn[1, 0] * Fn[2, 1] - Fn[1, 1] * Fn[2, 0]))
    for i in range(3):
        for j in range(i, 3):
            acc = 0.0
            for k in range(3):
                acc += Fn[i, k] * Fn[j, k]
            B[i, j] = acc
            B[j, i] = acc
    sym_eig3(B, Q, STRESS_JACOBI_REL_TOL)
    l0, l1, l2 = B[0, 0], B[1, 1], B[2, 2]  # squared stretches
    if not (det > 0.0 and min(l0, min(l1, l2)) > SIGMA_MIN * SIGMA_MIN):
        svd3(Fn, U, sig, V, B)
        dp_project(sig, eps, lam, mu, alpha)
        _write_projected(Fn, U, sig, V, eps, F_out, tau_out, lam, mu)
        return
    dgamma = dp_return(0.5 * math.log(l0), 0.5 * math.log(l1), 0.5 * math.log(l2), eps,
                       lam, mu, alpha)
    tr = eps[0] + eps[1] + eps[2]
    if dgamma > 0.0:  # U diag(exp(eps) / sigma) U^T, U = Q
        sig[0] = math.exp(eps[0]) / math.sqrt(l0)
        sig[1] = math.exp(eps[1]) / math.sqrt(l1)
        sig[2] = math.exp(eps[2]) / math.sqrt(l2)
        _q_diag_qt(Q, sig, U)
        for r in range(3):
            for q in range(3):
                acc = 0.0
                for s in range(3):
                    acc += U[r, s] * Fn[s, q]
                F_out[r, q] = acc
    else:
        for r in range(3):
            for q in range(3):
                F_out[r, q] = Fn[r, q]
    for s in range(3):
        eps[s] = 2.0 * mu * eps[s] + lam * tr  # principal Kirchhoff stress, Pa
    _q_diag_qt(Q, eps, tau_out)


@njit(cache=True, inline="always")
def _write_sym_times(F_out, p, m00, m01, m02, m11, m12, m22, f00, f01, f02, f10, f11, f12,
                     f20, f21, f22):
    """F_out[p] = M Fn for a symmetric M (upper triangle given) and Fn (row major)."""
    F_out[p, 0, 0] = m00 * f00 + m01 * f10 + m02 * f20
    F_out[p, 0, 1] = m00 * f01 + m01 * f11 + m02 * f21
    F_out[p, 0, 2] = m00 * f02 + m01 * f12 + m02 * f22
    F_out[p, 1, 0] = m01 * f00 + m11 * f10 + m12 * f20
    F_out[p, 1, 1] = m01 * f01 + m11 * f11 + m12 * f21
    F_out[p, 1, 2] = m01 * f02 + m11 * f12 + m12 * f22
    F_out[p, 2, 0] = m02 * f00 + m12 * f10 + m22 * f20
    F_out[p, 2, 1] = m02 * f01 + m12 * f11 + m22 * f21
    F_out[p, 2, 2] = m02 * f02 + m12 * f12 + m22 * f22


@njit(cache=True, inline="always")
def elastoplastic_update_scalar(f00, f01, f02, f10, f11, f12, f20, f21, f22, F_out, tau_out,
                                p, lam, mu, alpha):
    """`elastoplastic_update` in registers: trial F^E given as nine scalars (row major),
    results written to F_out[p] and tau_out[p] ([n, 3, 3] arrays). Same method (eigen of
    b = Fn Fn^T); exp(eps) / sigma is formed as exp(eps - log sigma). Returns False, writing
    nothing, for an inverted or nearly collapsed Fn (det <= 0 or a stretch below
    SIGMA_MIN): the caller then takes the full SVD path (`elastoplastic_update`)."""
    det = (f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20)
           + f02 * (f10 * f21 - f11 * f20))
    b00 = f00 * f00 + f01 * f01 + f02 * f02
    b01 = f00 * f10 + f01 * f11 + f02 * f12
    b02 = f00 * f20 + f01 * f21 + f02 * f22
    b11 = f10 * f10 + f11 * f11 + f12 * f12
    b12 = f10 * f20 + f11 * f21 + f12 * f22
    b22 = f20 * f20 + f21 * f21 + f22 * f22
    l0, l1, l2, q00, q01, q02, q10, q11, q12, q20, q21, q22 = sym_eig3_scalar(
        b00, b01, b02, b11, b12, b22, STRESS_JACOBI_REL_TOL)
    if not (det > 0.0 and min(l0, min(l1, l2)) > SIGMA_MIN * SIGMA_MIN):
        return False
    e0, e1, e2 = 0.5 * math.log(l0), 0.5 * math.log(l1), 0.5 * math.log(l2)
    eps0, eps1, eps2, dgamma = dp_return_scalar(e0, e1, e2, lam, mu, alpha)
    if dgamma > 0.0:  # F^E = Q diag(exp(eps) / sigma) Q^T Fn
        s0, s1, s2 = math.exp(eps0 - e0), math.exp(eps1 - e1), math.exp(eps2 - e2)
        m00 = q00 * s0 * q00 + q01 * s1 * q01 + q02 * s2 * q02
        m01 = q00 * s0 * q10 + q01 * s1 * q11 + q02 * s2 * q12
        m02 = q00 * s0 * q20 + q01 * s1 * q21 + q02 * s2 * q22
        m11 = q10 * s0 * q10 + q11 * s1 * q11 + q12 * s2 * q12
        m12 = q10 * s0 * q20 + q11 * s1 * q21 + q12 * s2 * q22
        m22 = q20 * s0 * q20 + q21 * s1 * q21 + q22 * s2 * q22
        _write_sym_times(F_out, p, m00, m01, m02, m11, m12, m22,
                         f00, f01, f02, f10, f11, f12, f20, f21, f22)
    else:
        F_out[p, 0, 0], F_out[p, 0, 1], F_out[p, 0, 2] = f00, f01, f02
        F_out[p, 1, 0], F_out[p, 1, 1], F_out[p, 1, 2] = f10, f11, f12
        F_out[p, 2, 0], F_out[p, 2, 1], F_out[p, 2, 2] = f20, f21, f22
    tr = eps0 + eps1 + eps2
    t0 = 2.0 * mu * eps0 + lam * tr  # principal Kirchhoff stress, Pa
    t1 = 2.0 * mu * eps1 + lam * tr
    t2 = 2.0 * mu * eps2 + lam * tr
    tau01 = q00 * t0 * q10 + q01 * t1 * q11 + q02 * t2 * q12
    tau02 = q00 * t0 * q20 + q01 * t1 * q21 + q02 * t2 * q22
    tau12 = q10 * t0 * q20 + q11 * t1 * q21 + q12 * t2 * q22
    tau_out[p, 0, 0] = q00 * t0 * q00 + q01 * t1 * q01 + q02 * t2 * q02
    tau_out[p, 1, 1] = q10 * t0 * q10 + q11 * t1 * q11 + q12 * t2 * q12
    tau_out[p, 2, 2] = q20 * t0 * q20 + q21 * t1 * q21 + q22 * t2 * q22
    tau_out[p, 0, 1] = tau01
    tau_out[p, 1, 0] = tau01
    tau_out[p, 0, 2] = tau02
    tau_out[p, 2, 0] = tau02
    tau_out[p, 1, 2] = tau12
    tau_out[p, 2, 1] = tau12
    return True


# Series path (no eigen-solve) for small elastic strains: |Y|_F <= SERIES_MAX_Y, where
# Y = (b - I)(b + I)^-1 and log b = 2 atanh(Y) = 2 (Y + Y^3/3 + Y^5/5 + Y^7/7 + ...).
# Truncation after Y^7: error <= 2 |Y|^9 / 9 ~ 2e-19 (strain) at the bound; the plastic
# increment D (|D| <= |eps| ~ |Y|) enters as exp(D) by Taylor through D^6 / 6!
# (error <= |D|^7 / 7! ~ 2e-18). Beyond the bound the eigen path above runs.
SERIES_MAX_Y = 1e-2


@njit(cache=True, inline="always")
def _sym_mul(a00, a01, a02, a11, a12, a22, b00, b01, b02, b11, b12, b22):
    """Upper triangle of A B for commuting symmetric A, B (the product is symmetric)."""
    return (a00 * b00 + a01 * b01 + a02 * b02,
            a00 * b01 + a01 * b11 + a02 * b12,
            a00 * b02 + a01 * b12 + a02 * b22,
            a01 * b01 + a11 * b11 + a12 * b12,
            a01 * b02 + a11 * b12 + a12 * b22,
            a02 * b02 + a12 * b12 + a22 * b22)


@njit(cache=True, inline="always")
def _hencky_series(x00, x01, x02, x11, x12, x22):
    """Hencky strain eps = log(b) / 2 = atanh(Y) for b = I + X (X symmetric, |X| small),
    by the series: returns (ok, eps00, eps01, eps02, eps11, eps12, eps22); ok is False (and
    eps meaningless) when |Y|_F > SERIES_MAX_Y."""
    m00, m11, m22 = 2.0 + x00, 2.0 + x11, 2.0 + x22  # M = b + I, inverted by cofactors
    c00 = m11 * m22 - x12 * x12
    c01 = x02 * x12 - x01 * m22
    c02 = x01 * x12 - x02 * m11
    c11 = m00 * m22 - x02 * x02
    c12 = x01 * x02 - m00 * x12
    c22 = m00 * m11 - x01 * x01
    det_m = m00 * c00 + x01 * c01 + x02 * c02
    if not 0.0 < det_m < math.inf:  # NaN, or an overflow from a huge F (Y would read 0)
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inv_det = 1.0 / det_m
    y00, y01, y02, y11, y12, y22 = _sym_mul(x00, x01, x02, x11, x12, x22, c00 * inv_det,
                                            c01 * inv_det, c02 * inv_det, c11 * inv_det,
                                            c12 * inv_det, c22 * inv_det)
    z00, z01, z02, z11, z12, z22 = _sym_mul(y00, y01, y02, y11, y12, y22,
                                            y00, y01, y02, y11, y12, y22)
    if not z00 + z11 + z22 <= SERIES_MAX_Y * SERIES_MAX_Y:  # |Y|_F^2 = tr(Y^2); NaN fails
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    # P = I + Z/3 + Z^2/5 + Z^3/7 by Horner; eps = Y P
    s7 = 1.0 / 7.0  # folded: multiplications, not divisions
    p00, p01, p02 = s7 * z00 + 0.2, s7 * z01, s7 * z02
    p11, p12, p22 = s7 * z11 + 0.2, s7 * z12, s7 * z22 + 0.2
    p00, p01, p02, p11, p12, p22 = _sym_mul(z00, z01, z02, z11, z12, z22,
                                            p00, p01, p02, p11, p12, p22)
    p00, p11, p22 = p00 + 1.0 / 3.0, p11 + 1.0 / 3.0, p22 + 1.0 / 3.0
    p00, p01, p02, p11, p12, p22 = _sym_mul(z00, z01, z02, z11, z12, z22,
                                            p00, p01, p02, p11, p12, p22)
    p00, p11, p22 = p00 + 1.0, p11 + 1.0, p22 + 1.0
    e00, e01, e02, e11, e12, e22 = _sym_mul(y00, y01, y02, y11, y12, y22,
                                            p00, p01, p02, p11, p12, p22)
    return True, e00, e01, e02, e11, e12, e22


@njit(cache=True, inline="always")
def _exp_series(d00, d01, d02, d11, d12, d22):
    """exp(D) for a small symmetric D: Taylor through D^6 / 6! by Horner."""
    e00, e01, e02, e11, e12, e22 = 1.0, 0.0, 0.0, 1.0, 0.0, 1.0
    for k in range(6, 0, -1):  # E <- I + D E / k
        e00, e01, e02, e11, e12, e22 = _sym_mul(d00, d01, d02, d11, d12, d22,
                                                e00, e01, e02, e11, e12, e22)
        s = 1.0 / k
        e00, e01, e02 = 1.0 + s * e00, s * e01, s * e02
        e11, e12, e22 = 1.0 + s * e11, s * e12, 1.0 + s * e22
    return e00, e01, e02, e11, e12, e22


@njit(cache=True, inline="always")
def elastoplastic_update_series(f00, f01, f02, f10, f11, f12, f20, f21, f22, F_out, tau_out,
                                p, lam, mu, alpha):
    """`elastoplastic_update_scalar` without an eigen-solve, for small elastic strains:
    the Hencky strain as the matrix eps = log(b) / 2 by a series, the return mapping on
    eps itself (Drucker-Prager is isotropic, so projecting the matrix is projecting its
    eigenvalues: eps <- eps - dgamma dev(eps) / |dev eps|, or 0 at the tip), F^E <-
    exp(eps_new - eps) Fn (coaxial with b = exp(2 eps)) and tau = 2 mu eps + lam tr(eps) I.
    b - I is formed as G + G^T + G G^T with G = Fn - I (no cancellation). Returns False,
    writing nothing, for det Fn <= 0 or a strain beyond the series bound."""
    det = (f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20)
           + f02 * (f10 * f21 - f11 * f20))
    if not det > 0.0:
        return False
    g00, g11, g22 = f00 - 1.0, f11 - 1.0, f22 - 1.0
    x00 = 2.0 * g00 + g00 * g00 + f01 * f01 + f02 * f02
    x11 = 2.0 * g11 + f10 * f10 + g11 * g11 + f12 * f12
    x22 = 2.0 * g22 + f20 * f20 + f21 * f21 + g22 * g22
    x01 = f01 + f10 + g00 * f10 + f01 * g11 + f02 * f12
    x02 = f02 + f20 + g00 * f20 + f01 * f21 + f02 * g22
    x12 = f12 + f21 + f10 * f20 + g11 * f21 + f12 * g22
    trb = 3.0 + x00 + x11 + x22
    if x01 * x01 + x02 * x02 + x12 * x12 <= STRESS_JACOBI_REL_TOL * trb * trb:
        return False  # b is diagonal to the eigen path's tolerance: no rotation there
    ok, e00, e01, e02, e11, e12, e22 = _hencky_series(x00, x01, x02, x11, x12, x22)
    if not ok:
        return False
    tr = e00 + e11 + e22
    m = tr * (1.0 / DIM)
    d00, d11, d22 = e00 - m, e11 - m, e22 - m
    dev = math.sqrt(d00 * d00 + d11 * d11 + d22 * d22
                    + 2.0 * (e01 * e01 + e02 * e02 + e12 * e12))
    plastic = True
    if tr > 0.0:  # tension: to the cone tip, eps = 0
        s00, s01, s02, s11, s12, s22 = -e00, -e01, -e02, -e11, -e12, -e22
    else:
        dgamma = dp_excess(dev, tr, lam, mu, alpha)
        if dgamma <= 0.0:
            plastic = False
            s00 = s01 = s02 = s11 = s12 = s22 = 0.0
        else:
            f = -dgamma / dev
            s00, s01, s02, s11, s12, s22 = f * d00, f * e01, f * e02, f * d11, f * e12, f * d22
    if plastic:  # F^E = exp(S) Fn, S = eps_new - eps
        a00, a01, a02, a11, a12, a22 = _exp_series(s00, s01, s02, s11, s12, s22)
        _write_sym_times(F_out, p, a00, a01, a02, a11, a12, a22,
                         f00, f01, f02, f10, f11, f12, f20, f21, f22)
        e00, e01, e02 = e00 + s00, e01 + s01, e02 + s02
        e11, e12, e22 = e11 + s11, e12 + s12, e22 + s22
        tr = e00 + e11 + e22
    else:
        F_out[p, 0, 0], F_out[p, 0, 1], F_out[p, 0, 2] = f00, f01, f02
        F_out[p, 1, 0], F_out[p, 1, 1], F_out[p, 1, 2] = f10, f11, f12
        F_out[p, 2, 0], F_out[p, 2, 1], F_out[p, 2, 2] = f20, f21, f22
    two_mu, lt = 2.0 * mu, lam * tr  # Kirchhoff stress, Pa
    tau_out[p, 0, 0] = two_mu * e00 + lt
    tau_out[p, 1, 1] = two_mu * e11 + lt
    tau_out[p, 2, 2] = two_mu * e22 + lt
    t01, t02, t12 = two_mu * e01, two_mu * e02, two_mu * e12
    tau_out[p, 0, 1], tau_out[p, 1, 0] = t01, t01
    tau_out[p, 0, 2], tau_out[p, 2, 0] = t02, t02
    tau_out[p, 1, 2], tau_out[p, 2, 1] = t12, t12
    return True
