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

DIM = 3
SIGMA_MIN = 1e-4  # clamp for singular values before log (an inverted/collapsed F^E)


@njit(cache=True, inline="always")
def dp_yield(e0, e1, e2, lam, mu, alpha):
    """Yield function dgamma (<= 0 inside the cone) for principal Hencky strains."""
    tr = e0 + e1 + e2
    m = tr / DIM
    dev = math.sqrt((e0 - m) ** 2 + (e1 - m) ** 2 + (e2 - m) ** 2)
    return dev + (DIM * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha


@njit(cache=True, inline="always")
def dp_project(sig, eps, lam, mu, alpha):
    """Principal stretches sig [3] -> projected Hencky strains eps [3]; returns dgamma >= 0
    (plastic strain increment, 0 for an elastic state)."""
    e0 = math.log(max(sig[0], SIGMA_MIN))
    e1 = math.log(max(sig[1], SIGMA_MIN))
    e2 = math.log(max(sig[2], SIGMA_MIN))
    tr = e0 + e1 + e2
    m = tr / DIM
    d0, d1, d2 = e0 - m, e1 - m, e2 - m
    dev = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if tr > 0.0:
        eps[0] = 0.0
        eps[1] = 0.0
        eps[2] = 0.0
        return math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    dgamma = dev + (DIM * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    if dgamma <= 0.0:  # inside the cone (includes dev = 0 with tr <= 0)
        eps[0], eps[1], eps[2] = e0, e1, e2
        return 0.0
    f = dgamma / dev  # dev > 0 here since tr <= 0
    eps[0] = e0 - f * d0
    eps[1] = e1 - f * d1
    eps[2] = e2 - f * d2
    return dgamma


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
