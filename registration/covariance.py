"""Pose covariance of an alignment (inverse Fisher information) and the residual χ² validity test.

Tangent convention (docs/ARCHITECTURE.md): the estimate ``T = target_T_source`` is perturbed on
the right, ``T_true = T · Exp(δ)``, δ translation first — 2D ``(x, y, θ)``, 3D ``(x, y, z, rx, ry, rz)``.
With ``Exp(δ) p ≈ p + ρ + φ × p`` the residual Jacobians at δ = 0 are, for a source point ``p'``
(source frame) and its match:

* ``point`` model, r = T p' − p (d rows):        J = R [I, −[p']×]
* ``plane`` model, e = nᵀ(T p' − p) (one row):  J = [mᵀ, (p' × m)ᵀ] with m = Rᵀ n
  (Chen & Medioni 1992; the Hessian of the nearest-neighbour distance to a smooth surface).

With f = ½ Σ w e² the Gauss-Newton Hessian is ∂²f/∂δ² = JᵀWJ (the Fisher information up to σ²),
and ``Cov(δ) = σ² (∂²f/∂δ²)⁻¹`` (Bengtsson & Baerveldt, RAS 2003; the course's Cov(x) = σ²(∂²f/∂x²)⁻¹).
The residual ``Res = Σ w e²`` is ~ σ² χ²(n − dof) for a correct alignment, n = scalar residuals
(Förstner & Wrobel, Photogrammetric Computer Vision, 2016: variance-factor test); the alignment is rejected when Res exceeds the threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core.errors import DegenerateInputError

Array = NDArray[np.float64]

__all__ = ["jacobian_point", "jacobian_plane", "fisher_information", "covariance_from_information",
           "Chi2Verdict", "chi2_test", "estimate_sigma2"]

# Eigenvalues of the information below this fraction of the largest are treated as unobserved.
_INFO_RTOL = 1e-9


def _cross_col_2d(p: Array) -> Array:
    """∂(R(θ) p)/∂θ at θ = 0: (−p_y, p_x)."""
    return np.column_stack([-p[:, 1], p[:, 0]])


def jacobian_point(source: Array, R: Array) -> Array:
    """Stacked ``(N, d, dof)`` Jacobians of r_i = T Exp(δ) p'_i − p_i w.r.t. δ at 0 (point model)."""
    n, d = source.shape
    if d == 2:
        J = np.empty((n, 2, 3))
        J[:, :, :2] = R
        J[:, :, 2] = _cross_col_2d(source) @ R.T
        return J
    J = np.empty((n, 3, 6))
    J[:, :, :3] = R
    # −R [p']× : column k of −[p']× is e_k × p' (cross product with the basis vector)
    px, py, pz = source[:, 0], source[:, 1], source[:, 2]
    z = np.zeros(n)
    neg_hat = np.stack([np.stack([z, pz, -py], -1), np.stack([-pz, z, px], -1), np.stack([py, -px, z], -1)], -2)
    J[:, :, 3:] = np.einsum("ij,njk->nik", R, neg_hat)
    return J


def jacobian_plane(source: Array, normals_target: Array, R: Array) -> Array:
    """``(N, dof)`` Jacobians of e_i = n_iᵀ(T Exp(δ) p'_i − p_i) w.r.t. δ at 0 (plane model)."""
    m = normals_target @ R  # rows m_i = Rᵀ n_i (normals in the source frame)
    if source.shape[1] == 2:
        return np.column_stack([m, source[:, 0] * m[:, 1] - source[:, 1] * m[:, 0]])
    return np.column_stack([m, np.cross(source, m)])


def fisher_information(J: Array, weights: Array | None = None) -> Array:
    """``H = Σ w_i J_iᵀ J_i`` for stacked Jacobians ``(N, dof)`` or ``(N, r, dof)``."""
    if J.ndim == 2:
        Jw = J if weights is None else J * weights[:, None]
        return J.T @ Jw
    Jf = J.reshape(-1, J.shape[-1])
    if weights is None:
        return Jf.T @ Jf
    w = np.repeat(weights, J.shape[1])
    return Jf.T @ (Jf * w[:, None])


def covariance_from_information(H: Array, sigma2: float) -> tuple[Array, bool]:
    """``(σ² H⁻¹, degenerate)``. Unobserved directions (eigenvalue < 1e-9 · max) get the variance
    σ² / (1e-9 · max eigenvalue) — huge but finite — and ``degenerate`` is True."""
    ev, V = np.linalg.eigh(0.5 * (H + H.T))
    if ev[-1] <= 0:
        raise DegenerateInputError("the alignment has no information (no inlier pairs)")
    floor = _INFO_RTOL * ev[-1]
    degenerate = bool(ev[0] < floor)
    ev = np.maximum(ev, floor)
    return sigma2 * (V / ev) @ V.T, degenerate


def estimate_sigma2(residual: float, n: int, dof: int) -> float:
    """σ̂² = Res / (n − dof), the unbiased residual variance."""
    if n <= dof:
        raise DegenerateInputError(f"{n} scalar residuals cannot estimate σ² for {dof} parameters")
    return residual / (n - dof)


@dataclass(frozen=True)
class Chi2Verdict:
    """Outcome of the residual test ``Res ≤ threshold``."""

    residual: float
    n: int
    dof: int
    sigma2: float
    sigma_estimated: bool
    threshold: float
    accepted: bool


def chi2_test(residual: float, n: int, dof: int, sigma2: float | None, factor: float = 3.0,
              false_rejection_rate: float | None = None) -> Chi2Verdict:
    """Residual test of a converged alignment (course rule: reject when Res > factor·(n − dof)·σ²).

    With ``false_rejection_rate`` α the threshold is σ² · χ²_{1−α}(n − dof) instead. When σ² is
    None it is estimated from the same residual, so the test degenerates to Res/(n−dof) ≤ σ̂² ·factor,
    which always passes: give σ for a meaningful test.
    """
    if n <= dof:
        raise DegenerateInputError(f"{n} scalar residuals for {dof} parameters: no redundancy for the χ² test")
    est = sigma2 is None
    s2 = estimate_sigma2(residual, n, dof) if est else float(sigma2)
    if false_rejection_rate is not None:
        from scipy.stats import chi2

        thr = s2 * float(chi2.ppf(1.0 - false_rejection_rate, n - dof))
    else:
        thr = factor * (n - dof) * s2
    return Chi2Verdict(float(residual), int(n), int(dof), s2, est, thr, bool(residual <= thr))
