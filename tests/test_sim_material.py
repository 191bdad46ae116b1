"""Fast 3x3 SVD against numpy, and the Drucker-Prager return mapping's properties."""

import math

import numpy as np
import pytest
from numba import njit

from minority.sim.plasticity import (
    SERIES_MAX_Y,
    dp_project,
    dp_project_numpy,
    dp_yield,
    elastoplastic_update,
    elastoplastic_update_scalar,
    elastoplastic_update_series,
)
from minority.sim.scene import DPCone, Material
from minority.sim.svd import svd3, sym_eig3_scalar

# tolerances (absolute, on O(1) quantities)
SVD_TOL = 1e-12
DP_TOL = 1e-12

SAND = Material(1800.0, 1.0e6, 0.3, 30.0)


@njit
def _svd_batch(Fs, Us, sigs, Vs):
    S = np.empty((3, 3))
    for p in range(Fs.shape[0]):
        svd3(Fs[p], Us[p], sigs[p], Vs[p], S)


@njit
def _eig_batch(A, lam, Q, rel_tol):
    for p in range(A.shape[0]):
        a = A[p]
        (lam[p, 0], lam[p, 1], lam[p, 2], Q[p, 0, 0], Q[p, 0, 1], Q[p, 0, 2], Q[p, 1, 0],
         Q[p, 1, 1], Q[p, 1, 2], Q[p, 2, 0], Q[p, 2, 1], Q[p, 2, 2]) = sym_eig3_scalar(
            a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2], rel_tol)


@njit
def _update_batch(Fn, F_arr, tau_arr, F_sc, tau_sc, ok, lam, mu, alpha):
    scratch = np.empty((4, 3, 3))
    vec = np.empty((2, 3))
    for p in range(Fn.shape[0]):
        f = Fn[p]
        elastoplastic_update(f, F_arr[p], tau_arr[p], lam, mu, alpha, scratch[0], scratch[1],
                             scratch[2], scratch[3], vec[0], vec[1])
        ok[p] = elastoplastic_update_scalar(f[0, 0], f[0, 1], f[0, 2], f[1, 0], f[1, 1],
                                            f[1, 2], f[2, 0], f[2, 1], f[2, 2], F_sc, tau_sc,
                                            p, lam, mu, alpha)


@njit
def _series_batch(Fn, F_out, tau_out, ok, lam, mu, alpha):
    for p in range(Fn.shape[0]):
        f = Fn[p]
        ok[p] = elastoplastic_update_series(f[0, 0], f[0, 1], f[0, 2], f[1, 0], f[1, 1],
                                            f[1, 2], f[2, 0], f[2, 1], f[2, 2], F_out,
                                            tau_out, p, lam, mu, alpha)


@njit
def _dp_batch(sigs, eps, lam, mu, alpha, dgamma):
    for p in range(sigs.shape[0]):
        dgamma[p] = dp_project(sigs[p], eps[p], lam, mu, alpha)


@njit
def _log(a):
    out = np.empty_like(a)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[i, j] = math.log(a[i, j])
    return out


def _random_rotations(rng, n):
    q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1.0
    return q


def _cases(rng):
    n = 2000
    near_identity = np.eye(3) + 0.05 * rng.normal(size=(n, 3, 3))
    general = rng.normal(size=(n, 3, 3))
    rot = _random_rotations(rng, n)
    stretches = rng.uniform(0.5, 1.5, size=(n, 3))
    stretches[: n // 4, 1] = stretches[: n // 4, 0]  # repeated singular values
    stretches[n // 4: n // 2] = 1.0  # pure rotations
    rotated = rot @ (stretches[:, :, None] * _random_rotations(rng, n).transpose(0, 2, 1))
    special = np.array([np.eye(3), np.diag([2.0, 2.0, 1.0]), np.zeros((3, 3)),
                        np.diag([1.0, 1e-9, 1e-9]), np.diag([3.0, 2.0, 1.0])[[2, 0, 1]]])
    return np.concatenate([near_identity, general, rotated, special])


def test_svd_matches_numpy():
    rng = np.random.default_rng(7)
    F = _cases(rng)
    n = F.shape[0]
    U, sig, V = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
    _svd_batch(F, U, sig, V)
    scale = np.maximum(1.0, np.abs(F).max(axis=(1, 2)))
    recon = U @ (sig[:, :, None] * V.transpose(0, 2, 1))
    assert np.abs(recon - F).max(axis=(1, 2)).max() / 1.0 <= SVD_TOL * scale.max()
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    assert np.abs(U.transpose(0, 2, 1) @ U - eye).max() < SVD_TOL
    assert np.abs(V.transpose(0, 2, 1) @ V - eye).max() < SVD_TOL
    assert np.allclose(np.linalg.det(U), 1.0) and np.allclose(np.linalg.det(V), 1.0)
    ref = np.linalg.svd(F, compute_uv=False)
    # ours: decreasing magnitude, last one signed with det(F)
    assert np.abs(np.abs(sig) - ref).max() < SVD_TOL * scale.max()
    det = np.linalg.det(F)
    nondegenerate = np.abs(det) > 1e-6
    assert np.all(np.sign(sig[nondegenerate, 2]) == np.sign(det[nondegenerate]))


def test_register_eigen_solver_matches_numpy():
    rng = np.random.default_rng(11)
    F = _cases(rng)
    A = F @ F.transpose(0, 2, 1)  # symmetric positive semi-definite, like b = F F^T
    n = A.shape[0]
    lam, Q = np.empty((n, 3)), np.empty((n, 3, 3))
    _eig_batch(A, lam, Q, 1e-30)
    scale = np.maximum(1.0, np.abs(A).max(axis=(1, 2)))[:, None, None]
    recon = Q @ (lam[:, :, None] * Q.transpose(0, 2, 1))
    assert (np.abs(recon - A) / scale).max() < SVD_TOL
    assert np.abs(Q.transpose(0, 2, 1) @ Q - np.eye(3)).max() < SVD_TOL
    ref = np.linalg.eigvalsh(A)
    assert (np.abs(np.sort(lam, axis=1) - ref) / scale[:, :, 0]).max() < SVD_TOL


def test_register_elastoplastic_update_matches_array_version():
    rng = np.random.default_rng(5)
    n = 4000
    Fn = np.eye(3) + 0.02 * rng.normal(size=(n, 3, 3))  # elastic, shear yield and tension
    Fn[:10] = np.eye(3)
    Fn[10:20] = np.diag([0.97, 0.98, 0.99])  # purely volumetric compression: elastic
    Fn[20] = np.diag([1.0, 1.0, -1.0])  # inverted: the scalar path declines
    Fn[21] = np.diag([1.0, 1.0, 1e-6])  # collapsed: declines
    lam, mu, alpha = SAND.lame_lambda_pa, SAND.shear_modulus_pa, SAND.dp_alpha
    F_arr, tau_arr = np.empty_like(Fn), np.empty_like(Fn)
    F_sc, tau_sc = np.full_like(Fn, np.nan), np.full_like(Fn, np.nan)
    ok = np.zeros(n, dtype=np.bool_)
    _update_batch(Fn, F_arr, tau_arr, F_sc, tau_sc, ok, lam, mu, alpha)
    assert not ok[20] and not ok[21] and ok[:20].all() and ok[22:].all()
    plastic = np.abs(F_arr - Fn).max(axis=(1, 2)) > 1e-12
    assert 100 < plastic[ok].sum() < ok.sum() - 100  # both branches exercised
    assert np.array_equal(F_sc[:20], F_arr[:20])  # elastic: F kept exactly
    # both stop the Jacobi sweeps at STRESS_JACOBI_REL_TOL (stress ~1e-11 relative)
    assert np.abs(F_sc[ok] - F_arr[ok]).max() < 1e-10
    assert np.abs(tau_sc[ok] - tau_arr[ok]).max() / SAND.youngs_modulus_pa < 1e-10


def _eigh_update(Fn, lam, mu, alpha):
    """The same update in NumPy from eigh(b) (eigenvalues to ~1e-16): F^E and tau."""
    sq, Q = np.linalg.eigh(Fn @ Fn.transpose(0, 2, 1))
    e = 0.5 * np.log(sq)
    eps = dp_project_numpy(np.exp(e), lam, mu, alpha)
    F = Q @ (np.exp(eps - e)[:, :, None] * Q.transpose(0, 2, 1)) @ Fn
    t = 2.0 * mu * eps + lam * eps.sum(axis=1, keepdims=True)
    return F, Q @ (t[:, :, None] * Q.transpose(0, 2, 1))


def test_series_elastoplastic_update_matches_eigen_reference():
    """The eigen-free path (matrix log by the atanh series, return mapping on the
    matrix, exp of the plastic increment) against eigh: 1e-13, far tighter than the
    Jacobi path's 1e-10; it declines inverted F, diagonal b and strains beyond the bound."""
    rng = np.random.default_rng(9)
    n = 3000
    scale = np.repeat([1e-5, 1e-4, 1e-3, 2e-3], n // 4)[:, None, None]
    Fn = _random_rotations(rng, n) @ (np.eye(3) + scale * rng.normal(size=(n, 3, 3)))
    Fn[:5] = np.eye(3)  # b diagonal: declined (the eigen path needs no rotation there)
    Fn[5:10] = np.diag([0.999, 0.998, 0.999])
    Fn[10] = np.diag([1.0, 1.0, -1.0]) @ _random_rotations(rng, 1)[0]  # inverted
    Fn[11] = np.eye(3) + 0.05 * rng.normal(size=(3, 3))  # beyond the series bound
    Fn[12] = np.diag([np.nan, 1.0, 1.0])
    Fn[13] = 3e51 * np.array([[1.0, 0.01, 0.0], [0.0, 1.0, 0.01], [0.0, 0.0, 1.0]])  # det(b + I) overflows
    lam, mu, alpha = SAND.lame_lambda_pa, SAND.shear_modulus_pa, SAND.dp_alpha
    F_out, tau_out = np.full_like(Fn, np.nan), np.full_like(Fn, np.nan)
    ok = np.zeros(n, dtype=np.bool_)
    _series_batch(Fn, F_out, tau_out, ok, lam, mu, alpha)
    b = Fn[14:] @ Fn[14:].transpose(0, 2, 1)
    y = (b - np.eye(3)) @ np.linalg.inv(b + np.eye(3))
    assert np.sqrt((y * y).sum(axis=(1, 2))).max() < SERIES_MAX_Y  # all inside the bound
    assert not ok[:14].any() and ok[14:].all()
    assert np.isnan(F_out[:14]).all() and np.isnan(tau_out[:14]).all()  # nothing written
    F_ref, tau_ref = _eigh_update(Fn[14:], lam, mu, alpha)
    assert np.abs(F_out[14:] - F_ref).max() < 1e-13
    assert np.abs(tau_out[14:] - tau_ref).max() / SAND.youngs_modulus_pa < 1e-13
    tr_eps = 0.5 * np.log(np.linalg.det(b))
    plastic = np.abs(F_out[14:] - Fn[14:]).max(axis=(1, 2)) > 0.0
    tip = tr_eps > 0.0
    assert 100 < (plastic & ~tip).sum() and 100 < tip.sum() and 100 < (~plastic).sum()
    assert np.array_equal(F_out[14:][~plastic], Fn[14:][~plastic])  # elastic: kept exactly
    assert np.abs(tau_out[14:][tip]).max() / SAND.youngs_modulus_pa < 1e-13  # tip: no stress


def _strains(rng, n=5000):
    e = rng.normal(scale=0.02, size=(n, 3))
    e[: n // 5] -= 0.05  # mostly compressed
    e[n // 5: 2 * n // 5] = -0.01  # purely volumetric compression (elastic)
    return e


def test_dp_projection_lands_inside_cone():
    rng = np.random.default_rng(3)
    sig = np.exp(_strains(rng))
    eps = _log(sig)  # the Hencky strains the projection sees (numba's log, bit for bit)
    lam, mu, alpha = SAND.lame_lambda_pa, SAND.shear_modulus_pa, SAND.dp_alpha
    out = np.empty_like(eps)
    dgamma = np.empty(len(eps))
    _dp_batch(sig, out, lam, mu, alpha, dgamma)
    yields = np.array([dp_yield(*e, lam, mu, alpha) for e in out])
    assert yields.max() <= DP_TOL
    assert (out.sum(axis=1) <= DP_TOL).all()  # no tension survives
    assert (dgamma >= 0.0).all()
    # elastic states (inside the cone, compressive) are unchanged, bit for bit
    inside = np.array([dp_yield(*e, lam, mu, alpha) <= 0.0 for e in eps]) & (eps.sum(1) <= 0)
    assert inside.sum() > 100
    assert np.array_equal(out[inside], eps[inside])
    assert (dgamma[inside] == 0.0).all()
    # yielded states were moved: on the cone surface (shear) or the tip (tension)
    moved = ~inside
    assert moved.sum() > 100
    tension = eps.sum(axis=1) > 0
    assert np.all(out[tension] == 0.0)
    shear = moved & ~tension
    assert np.abs(yields[shear]).max() < 1e-10
    # the projection keeps the volumetric strain in shear (radial return along deviator)
    assert np.allclose(out[shear].sum(1), eps[shear].sum(1), atol=1e-14)
    # idempotent
    again = np.empty_like(out)
    _dp_batch(np.exp(out), again, lam, mu, alpha, dgamma)
    assert np.allclose(again, out, atol=1e-13)
    # the numpy version used by the reference step agrees
    assert np.allclose(dp_project_numpy(sig, lam, mu, alpha), out, atol=1e-14)


def test_dp_alpha_formula():
    for phi in (10.0, 30.0, 60.0):
        s = math.sin(math.radians(phi))
        m = Material(1800.0, 1e6, 0.3, phi, DPCone.COMPRESSION)
        assert m.dp_alpha == pytest.approx(math.sqrt(2 / 3) * 2 * s / (3 - s))  # Klár 2016
        plane = Material(1800.0, 1e6, 0.3, phi, DPCone.PLANE_STRAIN)
        assert plane.dp_alpha == pytest.approx(math.sqrt(2) * s / 3)
        tan = math.tan(math.radians(phi))  # the default cone: sqrt(J2) <= tan(phi) p
        assert Material(1800.0, 1e6, 0.3, phi).dp_alpha == pytest.approx(math.sqrt(2) * tan / 3)


@pytest.mark.parametrize("cone", list(DPCone))
def test_plane_strain_yield_matches_mohr_coulomb(cone):
    """Yielded plane-strain state (intermediate principal stress = mean stress, as the
    non-dilatant flow requires for eps_yy = 0): the Mohr-Coulomb angle sin(phi_mc) =
    (s1 - s3) / -(s1 + s3) equals phi for PLANE_STRAIN, and exceeds it (about 44 deg for
    phi = 30 deg) for Klár's COMPRESSION cone. The same ratio is the shear over normal
    stress of simple shear under pressure (principal stresses -p + t, -p, -p - t): it is
    tan(phi) for SIMPLE_SHEAR."""
    phi = 30.0
    mat = Material(1800.0, 1e6, 0.3, phi, cone)
    lam, mu, alpha = mat.lame_lambda_pa, mat.shear_modulus_pa, mat.dp_alpha
    m, d = -0.01, 0.05  # mean and deviatoric Hencky strain: far outside the cone
    sig = np.exp(np.array([[m + d, m, m - d]]))
    eps = dp_project_numpy(sig, lam, mu, alpha)[0]
    t = 2.0 * mu * eps + lam * eps.sum()  # principal Kirchhoff stress, Pa
    sin_mc = (t[0] - t[2]) / -(t[0] + t[2])
    expect = {DPCone.PLANE_STRAIN: math.sin(math.radians(phi)),
              DPCone.SIMPLE_SHEAR: math.tan(math.radians(phi)),
              DPCone.COMPRESSION: mat.dp_slope_m / 3**0.5}[cone]
    assert sin_mc == pytest.approx(expect, rel=DP_TOL * 1e3)
    assert t[1] == pytest.approx(t.mean(), rel=DP_TOL * 1e3)
    if cone is DPCone.COMPRESSION:
        assert math.degrees(math.asin(sin_mc)) > 43.0
