"""Online calibration of a noise model by the normalised innovation squared (method of moments).

Two estimators of one quantity disagree by an *innovation* δ whose covariance is the sum of theirs,
``Σ_fixed + Σ_model``; if both are right, ``δᵀ (Σ_fixed + Σ_model)⁻¹ δ`` averages the dimension. With
``Σ_fixed`` trusted, the model is scaled per block (translation, rotation) so that this mean holds over
the innovations seen so far: a method-of-moments fit of the normalised innovation squared, as in
innovation-based adaptive estimation (Mehra, "Approaches to adaptive filtering", IEEE TAC 17(5), 1972,
§IV). The mean, not the median, of the statistic: errors are heavy-tailed, and the median fits scales
that are too small.

The model's σ per axis is a sum of *terms* (for wheels: one that grows with the distance driven, one
with the angle turned), each with its own scale. Wheels that hold their heading to 0.1° on a straight
stretch can lose 1–2° in a turn in place (slip), and one scale per block fits the straight stretches
that make most of the samples: in turns the wheels then claimed 2–4 × surer than they were (the
normalised innovation 2.4–5.5 in turns, 0.6–1.0 on straight stretches, on simulated rings and the
Freiburg hospital; docs/LOOP_CLOSURE.md "The wheels in a turn"). One moment condition per term — the
mean of the normalised innovation, each sample weighted by that term's share of its model σ
(a generalised method of moments, Hansen, Econometrica 50(4), 1982) — recovers each scale where
the samples exercise it; a term too few samples exercise keeps the block's common scale.

The trusted side's covariance may carry margins that are not its noise (the registration edge's floors,
which make a scan match on real data no surer than it measurably is). Where those margins alone exceed
the whole disagreement, the moment equation has no positive solution — a variance component estimated
at ≤ 0 — and the fit would end at its lower bound, making the model far surer than it is (a fast laser
and good wheels: the wheels 2.2–2.5 × surer than their true error, docs/LOOP_CLOSURE.md "The wheels'
calibration at a fast laser"). That block is then fitted against the trusted side's own claim, without
the margins, which measures the model's noise where the margins hid it.

Used for the wheel-odometry model against the scan registration, one innovation per keyframe interval
(:class:`slam.pipeline.frontend.FrontEnd`): robots' wheels agree with their scans up to ~7× better
in heading on one robot than on another (docs/ODOMETRY.md), and one generic wheel model cannot say so.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

Array = NDArray[np.float64]

MIN_TERM_WEIGHT = 10.0  # a term whose shares of the model σ sum to less (fewer than ~10 samples' worth) keeps the common scale


class NoiseScaleCalibration:
    """Running estimate of the scales of a noise model whose σ per axis is a sum of terms.

    Args:
        n_translation: translation dimensions of the tangent vector (2 planar, 3 in 3D); the rest
            are rotation. Covariances are in the ``(translation, rotation)`` tangent order.
        n_terms: terms of the model's σ (rows of the ``model_sigmas`` given to :meth:`add`).
        min_samples: below this many innovations the scales stay 1 (the model as configured).
        every: re-estimate after this many new innovations, or after 10 % more, whichever is
            later (each fit is O(samples); the estimate settles as they grow).
        bounds: the scales are kept within these (a calibration, not a switch that turns the
            model off or makes it exact).

    Attributes:
        scales: ``(2, n_terms)`` — per block (translation, rotation), the scale of each term.
    """

    def __init__(self, n_translation: int, n_terms: int = 1, min_samples: int = 50, every: int = 25,
                 bounds: tuple[float, float] = (0.05, 10.0)) -> None:
        self.n_translation = n_translation
        self.n_terms = n_terms
        self.min_samples = min_samples
        self.every = every
        self.bounds = bounds
        self.scales = np.ones((2, n_terms))
        self._innovations: list[Array] = []
        self._fixed: list[Array] = []
        self._own: list[Array] = []
        self._sigmas: list[Array] = []
        self._since_fit = 0

    @property
    def samples(self) -> int:
        return len(self._innovations)

    def add(self, innovation: Array, fixed_cov: Array, model_sigmas: Array, fixed_own_cov: Array | None = None) -> None:
        """One innovation (tangent vector), the covariance of the trusted estimator, the *uncalibrated*
        model's σ per term and axis (``(n_terms, dim)``; the model's σ of an axis is the column's sum) and,
        when *fixed_cov* includes margins, the trusted estimator's own covariance without them (the fit's
        fallback where the margins alone exceed the disagreement; default *fixed_cov*)."""
        self._innovations.append(np.asarray(innovation, dtype=float))
        self._fixed.append(np.asarray(fixed_cov, dtype=float))
        self._own.append(self._fixed[-1] if fixed_own_cov is None else np.asarray(fixed_own_cov, dtype=float))
        self._sigmas.append(np.asarray(model_sigmas, dtype=float).reshape(self.n_terms, -1))
        self._since_fit += 1
        # Refit every `every` samples, and no more often than every 10 % of them (the estimate has settled).
        due = self._since_fit >= max(self.every, self.samples // 10)
        if self.samples >= self.min_samples and (due or self.samples == self.min_samples):
            self._fit()

    def calibrated(self, model_sigmas: Array) -> Array:
        """The model covariance (diagonal) at the current scales: per axis (Σ_t k_t σ_t)²."""
        S = np.asarray(model_sigmas, dtype=float).reshape(self.n_terms, -1)
        return np.diag(self._sigma(S[None], self._block_scales(S.shape[1]))[0] ** 2)

    def _block_scales(self, dim: int) -> Array:
        """``(n_terms, dim)``: each axis's scales (its block's)."""
        n = self.n_translation
        return np.c_[np.repeat(self.scales[0][:, None], n, 1), np.repeat(self.scales[1][:, None], dim - n, 1)]

    @staticmethod
    def _sigma(S: Array, k: Array) -> Array:
        """σ per sample and axis from term σ ``S`` (samples, terms, axes) and scales ``k`` (terms, axes)."""
        return np.einsum("nta,ta->na", S, k)

    def _fit(self) -> None:
        self._since_fit = 0
        d = np.array(self._innovations)
        S = np.array(self._sigmas)
        n = self.n_translation
        for row, b in enumerate((slice(0, n), slice(n, None))):
            A = np.array(self._fixed)[:, b, b]
            k = self._solve_common(d[:, b], A, S[:, :, b])
            if k <= self.bounds[0]:  # the margins alone exceed the disagreement: measure against the own claim
                A = np.array(self._own)[:, b, b]
                k = self._solve_common(d[:, b], A, S[:, :, b])
            self.scales[row] = self._solve_terms(d[:, b], A, S[:, :, b], k) if self.n_terms > 1 else k

    @staticmethod
    def _nis(d: Array, A: Array, sigma: Array) -> Array:
        """dᵀ(A + diag σ²)⁻¹d per sample."""
        M = A + np.einsum("na,ab->nab", sigma**2, np.eye(d.shape[1]))
        if d.shape[1] == 1:
            return d[:, 0] ** 2 / M[:, 0, 0]
        if d.shape[1] == 2:  # the 2×2 inverse in closed form: np.linalg.solve costs ~10× more on tiny matrices
            a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 1, 1]
            return (c * d[:, 0] ** 2 - 2.0 * b * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / (a * c - b * b)
        return np.einsum("ni,ni->n", d, np.linalg.solve(M, d[..., None])[..., 0])

    def _solve_common(self, d: Array, A: Array, S: Array) -> float:
        """One k for every term with mean dᵀ(A + k² diag σ²)⁻¹d = dim, by bisection on log k (the mean
        falls as k grows)."""
        dim = d.shape[1]
        sigma = S.sum(1)

        def excess(k: float) -> float:
            return float(np.mean(self._nis(d, A, k * sigma))) - dim

        if excess(self.bounds[0]) <= 0:
            return float(self.bounds[0])
        if excess(self.bounds[1]) >= 0:
            return float(self.bounds[1])
        lo, hi = np.log(self.bounds[0]), np.log(self.bounds[1])
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if excess(np.exp(mid)) > 0:
                lo = mid
            else:
                hi = mid
        return float(np.exp(0.5 * (lo + hi)))

    def _solve_terms(self, d: Array, A: Array, S: Array, common: float) -> Array:
        """Per-term scales: for each term t, the mean of (NIS − dim) weighted by t's share of each sample's
        model σ is zero. Terms the samples exercise too little keep *common*."""
        dim = d.shape[1]
        total = S.sum(1, keepdims=True)
        share = np.mean(S / np.where(total > 0, total, 1.0), axis=2)  # (samples, terms)
        free = share.sum(0) >= MIN_TERM_WEIGHT
        k = np.full(self.n_terms, common)
        if free.sum() < 2:
            return k
        lo, hi = np.log(self.bounds[0]), np.log(self.bounds[1])

        def conditions(x: Array) -> Array:
            kk = k.copy()
            kk[free] = np.exp(x)
            e = self._nis(d, A, np.einsum("nta,t->na", S, kk)) - dim
            return share[:, free].T @ e / len(e)

        x0 = np.full(int(free.sum()), np.log(common))
        sol = least_squares(conditions, np.clip(x0, lo + 1e-9, hi - 1e-9), bounds=(lo, hi), xtol=1e-8)
        k[free] = np.exp(sol.x)
        return k
