"""Online calibration of a noise model by the normalised innovation squared (method of moments).

Two estimators of one quantity disagree by an *innovation* δ whose covariance is the sum of theirs,
``Σ_fixed + Σ_model``; if both are right, ``δᵀ (Σ_fixed + Σ_model)⁻¹ δ`` averages the dimension. With
``Σ_fixed`` trusted, the model is scaled per block — translation by ``k_t``, rotation by ``k_r`` — so
that this mean holds over the innovations seen so far: a method-of-moments fit of the normalised
innovation squared, as in innovation-based adaptive estimation (Mehra, "Approaches to adaptive
filtering", IEEE TAC 17(5), 1972, §IV). The mean, not the median, of the statistic: errors are
heavy-tailed, and the median fits scales that are too small.

The trusted side's covariance may carry margins that are not its noise (the registration edge's floors,
which make a scan match on real data no surer than it measurably is). Charged to the trusted side, they are
taken out of the model's share of the disagreement. Where they take most of it, what is left says more about
the margins than about the model: the moment equation has no positive solution at all when the margins
alone exceed the disagreement (a fast laser and good wheels: the wheels 2.2–2.5 × surer than their true
error, docs/LOOP_CLOSURE.md "The wheels' calibration at a fast laser"), and where they take 94 % of the
model's share the fit lands just above its bound and the wheels come out 3.6 × surer than they are (a
simulated RPLIDAR, docs/ODOMETRY.md "A deskewed scan's pose at its stamp"). So each block is also fitted
against the trusted side's own claim, without the margins, and that fit is taken where the one with the
margins reaches less than ``MARGIN_FIT_RATIO`` of it. On the logs of the development set the two fits agree to 0.85–1.0 (the
registration's own claim is overconfident on real data and the floors are part of its error, so the fit
with them stays there); on simulated logs, whose registration is as sure as it claims, the translation fit
with the floors is 0.25 of the other.

An error that repeats from interval to interval (a turn gain, unequal wheel diameters: Borenstein & Feng,
"Measurement and correction of systematic odometry errors in mobile robots", IEEE T-RA 12(6), 1996) only
widens the per-interval fit a little, but it adds up along the path, and a pose graph of independent
edges then trusts the model over long stretches more than it may. So the rotation scale is also tested
on sums over runs of consecutive innovations (whiteness: their NEES must not grow with the run's length)
and raised where they reject it (in a measured case the heading sums over 64 intervals disagree 11.6 ×
their expected χ², and the scale goes 0.92 → 3.13; docs/ODOMETRY.md "The wheels' systematic errors").
The mean of such an error is not corrected: against the scans alone it cannot be told from the
registration's own (measured there).

Used for the wheel-odometry model against the scan registration, one innovation per keyframe interval
(:class:`slam.pipeline.frontend.FrontEnd`): robots' wheels agree with their scans up to ~7× better
in heading on one robot than on another (docs/ODOMETRY.md), and one generic wheel model cannot say so.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# The whiteness test over runs of consecutive innovations: its χ² probability, and the fewest runs of one
# length it is made on (a mean of fewer χ² terms is too loose to test; Bar-Shalom, Li & Kirubarajan,
# "Estimation with Applications to Tracking and Navigation", 2001, §5.4.2, test the time-average NEES alike).
CHAIN_PROBABILITY = 0.99
CHAIN_MIN_RUNS = 20
# A fit with the trusted side's margins below this fraction of the fit against its own claim: the margins took
# more than three quarters of the model's share of the variance (module text).
MARGIN_FIT_RATIO = 0.5


class NoiseScaleCalibration:
    """Running estimate of the scales ``(k_t, k_r)`` of a noise model.

    Args:
        n_translation: translation dimensions of the tangent vector (2 planar, 3 in 3D); the rest
            are rotation. Covariances are in the ``(translation, rotation)`` tangent order.
        min_samples: below this many innovations the scales stay 1 (the model as configured).
        every: re-estimate after this many new innovations, or after 10 % more, whichever is
            later (each fit is O(samples); the estimate settles as they grow).
        bounds: the scales are kept within these (a calibration, not a switch that turns the
            model off or makes it exact).
    """

    def __init__(self, n_translation: int, min_samples: int = 50, every: int = 25,
                 bounds: tuple[float, float] = (0.05, 10.0)) -> None:
        self.n_translation = n_translation
        self.min_samples = min_samples
        self.every = every
        self.bounds = bounds
        self.scale_translation = 1.0
        self.scale_rotation = 1.0
        self._innovations: list[Array] = []
        self._fixed: list[Array] = []
        self._model: list[Array] = []
        self._own: list[Array] = []
        self._since_fit = 0

    @property
    def samples(self) -> int:
        return len(self._innovations)

    def add(self, innovation: Array, fixed_cov: Array, model_cov: Array, fixed_own_cov: Array | None = None) -> None:
        """One innovation (tangent vector), the covariance of the trusted estimator, the *uncalibrated*
        model covariance and, when *fixed_cov* includes margins, the trusted estimator's own covariance
        without them (the fit's fallback where the margins hide the model's noise; default *fixed_cov*)."""
        self._innovations.append(np.asarray(innovation, dtype=float))
        self._fixed.append(np.asarray(fixed_cov, dtype=float))
        self._model.append(np.asarray(model_cov, dtype=float))
        self._own.append(self._fixed[-1] if fixed_own_cov is None else np.asarray(fixed_own_cov, dtype=float))
        self._since_fit += 1
        # Refit every `every` samples, and no more often than every 10 % of them (the estimate has settled).
        due = self._since_fit >= max(self.every, self.samples // 10)
        if self.samples >= self.min_samples and (due or self.samples == self.min_samples):
            self._fit()

    def calibrated(self, model_cov: Array) -> Array:
        """The model covariance scaled by the current estimate (k² per block)."""
        n = self.n_translation
        s = np.r_[np.full(n, self.scale_translation), np.full(len(model_cov) - n, self.scale_rotation)]
        return model_cov * np.outer(s, s)

    def _fit(self) -> None:
        self._since_fit = 0
        d = np.array(self._innovations)
        A = np.array(self._fixed)
        B = np.array(self._model)
        n = self.n_translation
        own = np.array(self._own)
        scales = []
        for b in (slice(0, n), slice(n, None)):
            k = self._solve(d[:, b], A[:, b, b], B[:, b, b])
            k_own = self._solve(d[:, b], own[:, b, b], B[:, b, b])
            if k <= self.bounds[0] or k < MARGIN_FIT_RATIO * k_own:  # the margins hide the model's noise
                k = k_own
            scales.append(k)
        scales[1] = self._chain_scale(d[:, n:], A[:, n:, n:], B[:, n:, n:], scales[1])
        self.scale_translation, self.scale_rotation = scales

    def _chain_scale(self, d: Array, A: Array, B: Array, k: float) -> float:
        """The rotation scale *k* raised until sums over runs of consecutive innovations are consistent.

        Runs of L = 2, 4, 8, … consecutive samples (while there are at least ``CHAIN_MIN_RUNS`` of them):
        where ``Σ (Σδ)ᵀ (ΣA + k²ΣB)⁻¹ (Σδ)`` over the runs exceeds its χ² quantile at ``CHAIN_PROBABILITY``,
        the model's error accumulates beyond white noise, and *k* becomes the scale that fits the runs'
        sums (never lowered; not where that would pass the upper bound). Heading innovations add along a
        path exactly in the plane (to first order in 3D); translation ones are each in their own
        interval's frame and do not, so the translation block is not tested (tried with each turned into
        the run's frame: docs/ODOMETRY.md)."""
        from scipy.stats import chi2

        dim = d.shape[1]
        L = 2
        while len(d) // L >= CHAIN_MIN_RUNS:
            m = len(d) // L * L
            dL = d[:m].reshape(-1, L, dim).sum(1)
            AL = A[:m].reshape(-1, L, dim, dim).sum(1)
            BL = B[:m].reshape(-1, L, dim, dim).sum(1)
            q = float(np.einsum("ni,ni->", dL, np.linalg.solve(AL + (k * k) * BL, dL[..., None])[..., 0]))
            if q > chi2.ppf(CHAIN_PROBABILITY, len(dL) * dim):
                k_runs = self._solve(dL, AL, BL)
                if k_runs < self.bounds[1]:  # beyond the bounds' reach it is no noise level: left to the gate
                    k = max(k, k_runs)
            L *= 2
        return k

    def _solve(self, d: Array, A: Array, B: Array) -> float:
        """k with mean dᵀ(A + k²B)⁻¹d = dim, by bisection on log k (the mean falls as k grows)."""
        dim = d.shape[1]

        def excess(k: float) -> float:
            M = A + (k * k) * B
            if dim == 1:
                q = d[:, 0] ** 2 / M[:, 0, 0]
            elif dim == 2:  # the 2×2 inverse in closed form: np.linalg.solve costs ~10× more on tiny matrices
                a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 1, 1]
                q = (c * d[:, 0] ** 2 - 2.0 * b * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / (a * c - b * b)
            else:
                q = np.einsum("ni,ni->n", d, np.linalg.solve(M, d[..., None])[..., 0])
            return float(np.mean(q)) - dim

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
