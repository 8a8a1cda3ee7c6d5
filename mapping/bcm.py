"""Bayesian Committee Machine fusion of Gaussian cell estimates and the probit squash.

BCM (Tresp 2000; Yuan et al. 2018 eq. 5, O'Callaghan & Ramos 2012 eq. 18): independent estimates
(μᵢ, σᵢ²) of a cell fuse to σ⁻² = Σ σᵢ⁻², μ = σ² Σ μᵢ σᵢ⁻². Grids are therefore kept in
information form — ``info = Σ μᵢ/σᵢ²`` and ``prec = Σ 1/σᵢ²`` — where fusion is a sum; a cell
with ``prec == 0`` has never been observed.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

Array = NDArray[np.float64]

#: variances are floored here before inversion (a zero GP variance would give infinite precision)
MIN_VARIANCE = 1e-6


def fuse(mean_a: Array, var_a: Array, mean_b: Array, var_b: Array) -> tuple[Array, Array]:
    """Precision-weighted fusion of two Gaussian estimates (BCM of two members)."""
    pa = 1.0 / np.maximum(var_a, MIN_VARIANCE)
    pb = 1.0 / np.maximum(var_b, MIN_VARIANCE)
    var = 1.0 / (pa + pb)
    return var * (mean_a * pa + mean_b * pb), var


def add_estimate(info: Array, prec: Array, mean: Array, var: Array) -> None:
    """In place: fuse local estimates (μ, σ²) into an information-form grid (same shapes or masks)."""
    p = 1.0 / np.maximum(var, MIN_VARIANCE)
    info += mean * p
    prec += p


def mean_variance(info: Array, prec: Array, prior_variance: float = np.inf) -> tuple[Array, Array]:
    """(μ, σ²) from information form; unobserved cells get μ = 0 and *prior_variance*."""
    seen = prec > 0
    safe = np.where(seen, prec, 1.0)
    mean = np.where(seen, info / safe, 0.0)
    var = np.where(seen, 1.0 / safe, prior_variance)
    return mean, var


def probit_squash(mean: Array, var: Array, alpha: float = 100.0, beta: float = 0.0) -> Array:
    """p = Φ((αμ + β)/√(1 + α²σ²)) (Yuan et al. 2018 eq. 6); σ² = ∞ gives p = 0.5 when β = 0."""
    mean = np.asarray(mean, dtype=float)
    var = np.asarray(var, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (alpha * mean + beta) / np.sqrt(1.0 + alpha * alpha * var)
    z = np.where(np.isfinite(var), z, 0.0)
    return ndtr(z)
