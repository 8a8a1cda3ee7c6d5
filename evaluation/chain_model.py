"""The covariance of a keyframe chain: compounded walk, jitter at its ends, and its calibration from the run's closures.

Between consecutive keyframes the front end states one step (its registration and wheel edges fused) with a
covariance Σ_k. Compounding the Σ_k along a chain (first-order propagation, Barfoot, *State Estimation for
Robotics*, §7.3.3) is right when the steps' errors are independent. A scan-to-map front end's are not: each
keyframe's scan is registered against a local map with its own error j_k, which the next step undoes, so the
step's error is ``j_k − j_(k−1) + w_k`` with w_k the map's own drift (docs/LOOP_CLOSURE.md, "The registration's
error is jitter"; measured against ground truth, consecutive steps' heading errors correlate −0.2 to −0.5). Over a
chain a → b the jitter appears only at its two ends; the walk compounds.

:class:`Chain` gives any chain's relative pose with its covariance split into those parts, linear in their scales:
``walk · P + jitter · Q + R``, where P is the steps' compounded covariance, Q the median step covariance at both ends
(the older end's carried to the newer by the adjoint, so its heading moves the far end by the lever arm), and R
whatever does not scale (the loop closer's random-constant heading rate, a reference's own error).
:class:`ChainSample` holds those parts for many chains against a reference (relations or closures), so a model's
NEES needs no chain rebuilt.

**Calibration** (:func:`calibrate`). A step's stated covariance is kept as its whole error, ``2 J + W = Σ``, and
split into jitter and walk by the long chains (at least :data:`LONG_CHAIN_KEYFRAMES` keyframes, where the walk
dominates): the walk share w is the one at which they average NEES/dof 1 against the reference, and the jitter
share is then ``(1 − w) / 2`` (:func:`split_jitter`; 0 once w ≥ 1, steps overconfident even alone). Against the
run's own closures this needs no ground truth; a closure is accepted against the graph's corrected estimate, not
against the chain, so long chains are barely selected by the gate. On the development set the closures' walk is
the relations' to within 25 % wherever the relations are a clean reference (docs/LOOP_CLOSURE.md, "A chain model
calibrated by the run's closures").
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

from core import geometry as G

Array = NDArray[np.float64]

__all__ = ["Chain", "ChainSample", "ChainModel", "LONG_CHAIN_KEYFRAMES", "split_jitter", "fit_walk", "calibrate"]

#: Chains at least this long (keyframes) set the walk of :func:`fit_walk`: there the compounded walk, not the
#: jitter at the ends, makes the covariance.
LONG_CHAIN_KEYFRAMES = 101


class Chain:
    """Prefix products and compounded covariances of a keyframe chain, for any pair in O(1).

    With right perturbations, ``T_ab = Π_{k=a+1..b} μ_k Exp(ξ_k)`` gives ``Σ_ab = Ad(C_b)⁻¹ (S_b − S_a) Ad(C_b)⁻ᵀ``
    where ``C_k = μ_1 ⋯ μ_k`` and ``S_k = Σ_{m ≤ k} Ad(C_m) Σ_m Ad(C_m)ᵀ``. Two random constants may be added: the
    loop closer's heading rate (:mod:`slam.loops.uncertainty`), ``σ_b² u uᵀ``, and a scale error of the rotation
    (measured here; the closer does not model it), ``σ_k² w wᵀ``: a heading error ``b ℓ_m`` (``k Δθ_m``) at step *m*
    enters as ``Ad(C_m) (0, 0, ℓ_m)`` (``(0, 0, Δθ_m)``), so u and w are prefix sums, exact to first order.
    ``turn[k]`` is the summed signed turn Σ_{m ≤ k} Δθ_m. *walk* scales the steps' covariance before it compounds;
    *jitter* × the median step covariance is added at both ends of every chain (with walk 1 and jitter 0,
    independent steps)."""

    def __init__(self, mu: Array, cov: Array, drift_rad_per_m: float = 0.0, drift_per_turn: float = 0.0,
                 walk: float = 1.0, jitter: float = 0.0) -> None:
        self.drift = float(drift_rad_per_m)
        self.drift_turn = float(drift_per_turn)
        self.walk, self.jitter = float(walk), float(jitter)
        # Per keyframe k (lists, so that a chain can grow online): C_k, S_k, J_k = Σ_{m ≤ k} Ad(C_m) (0, 0, ℓ_m) (the
        # heading rate's prefix), W_k = Σ_{m ≤ k} Ad(C_m) (0, 0, Δθ_m) (the rotation scale error's), the summed signed
        # turn and the odometry path length.
        self.C, self.S = [np.eye(4)], [np.zeros((3, 3))]
        self.J, self.W = [np.zeros(3)], [np.zeros(3)]
        self.turn, self.path = [0.0], [0.0]
        self._covs: list[Array] = []
        self._median: Array | None = None
        for k in range(1, len(mu)):
            self.extend(mu[k], cov[k])

    def __len__(self) -> int:
        return len(self.C)

    def extend(self, step: Array, cov: Array) -> None:
        """One more keyframe: the step ``(4, 4)`` from the last one and its covariance ``(3, 3)``."""
        C = self.C[-1] @ step
        A = G.adjoint(C, planar=True)
        turn = float(np.arctan2(step[1, 0], step[0, 0]))
        length = float(np.linalg.norm(step[:2, 3]))
        self.C.append(C)
        self.S.append(self.S[-1] + A @ np.asarray(cov, float) @ A.T)
        self.J.append(self.J[-1] + A[:, 2] * length)
        self.W.append(self.W[-1] + A[:, 2] * turn)
        self.turn.append(self.turn[-1] + turn)
        self.path.append(self.path[-1] + length)
        self._covs.append(np.asarray(cov, float))
        self._median = None

    @property
    def step_median(self) -> Array:
        """The median step covariance (the jitter's unit)."""
        if self._median is None:
            self._median = np.median(np.array(self._covs), axis=0) if self._covs else np.zeros((3, 3))
        return self._median

    def parts(self, a: int, b: int) -> tuple[Array, Array, Array, Array]:
        """``a_T_b`` along the chain (a ≤ b) and its covariance's parts: the compounded steps P (walk 1), the jitter
        at both ends Q (jitter 1), and the random constants R (which do not scale)."""
        Ainv = np.linalg.inv(G.adjoint(self.C[b], planar=True))
        P = Ainv @ (self.S[b] - self.S[a]) @ Ainv.T
        R = np.zeros((3, 3))
        if self.drift > 0.0:
            u = Ainv @ (self.J[b] - self.J[a])
            R = R + self.drift**2 * np.outer(u, u)
        if self.drift_turn > 0.0:
            w = Ainv @ (self.W[b] - self.W[a])
            R = R + self.drift_turn**2 * np.outer(w, w)
        T = G.relative(self.C[a], self.C[b])
        Ad = G.adjoint(G.inverse(T), planar=True)  # a's own error seen from b
        Q = Ad @ self.step_median @ Ad.T + self.step_median
        return T, P, Q, R

    def relative(self, a: int, b: int) -> tuple[Array, Array]:
        """``a_T_b`` along the chain and its covariance under the chain's walk and jitter (a ≤ b)."""
        T, P, Q, R = self.parts(a, b)
        return T, self.walk * P + self.jitter * Q + R


@dataclass(frozen=True)
class ChainSample:
    """Chains tested against a reference: per chain its length (keyframes), the error e ``(n, 3)`` of the chain
    against the reference (x, y, θ), the covariance parts ``(n, 3, 3)`` of :meth:`Chain.parts` (R with the
    reference's own covariance added), the odometry path (m) and summed signed turn (rad) between its ends."""

    length: NDArray[np.int64]
    e: Array
    P: Array
    Q: Array
    R: Array
    path_m: Array
    turn_rad: Array

    @staticmethod
    def of(rows: list[tuple]) -> "ChainSample":
        """From ``(length, e, P, Q, R, path, turn)`` tuples (none: an empty sample)."""
        if not rows:
            z = np.zeros((0, 3, 3))
            return ChainSample(np.zeros(0, np.int64), np.zeros((0, 3)), z, z, z, np.zeros(0), np.zeros(0))
        cols = list(zip(*rows))
        return ChainSample(np.array(cols[0], np.int64), *(np.array(c, float) for c in cols[1:]))

    def __len__(self) -> int:
        return len(self.length)

    def joined(self, other: "ChainSample") -> "ChainSample":
        """This sample's chains followed by *other*'s (a sample that grows by its new chains, not rebuilt)."""
        return ChainSample(*(np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)))

    def nees(self, walk: float = 1.0, jitter: float = 0.0, mask: NDArray[np.bool_] | None = None) -> Array:
        """NEES/dof of each chain (of those in *mask*) under ``walk · P + jitter · Q + R``."""
        m = slice(None) if mask is None else mask
        S = walk * self.P[m] + jitter * self.Q[m] + self.R[m]
        e = self.e[m]
        return np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0]) / 3.0

    def rows(self, walk: float = 1.0, jitter: float = 0.0) -> Array:
        """Per chain: (length in keyframes, NEES/dof, translation error m, |rotation error| rad, predicted
        translation σ m, predicted rotation σ rad, odometry path m, signed heading error rad, summed signed turn rad)."""
        S = walk * self.P + jitter * self.Q + self.R
        return np.column_stack([self.length, self.nees(walk, jitter), np.hypot(self.e[:, 0], self.e[:, 1]),
                                np.abs(self.e[:, 2]), np.sqrt(S[:, 0, 0] + S[:, 1, 1]), np.sqrt(S[:, 2, 2]),
                                self.path_m, self.e[:, 2], self.turn_rad]).reshape(-1, 9)


def split_jitter(walk: float) -> float:
    """The jitter share that keeps a step's stated covariance as its whole error (``2 J + W = Σ``): (1 − w) / 2."""
    return max(0.0, (1.0 - float(walk)) / 2.0)


def fit_walk(sample: ChainSample, jitter: float | None = None, min_chains: int = 30,
             bounds: tuple[float, float] = (1e-3, 1e2), steps: int = 30) -> tuple[float, int] | None:
    """The walk at which the *sample*'s chains of at least :data:`LONG_CHAIN_KEYFRAMES` keyframes average NEES/dof 1,
    by bisection on its logarithm (their mean NEES falls as the walk grows), with the *jitter* given or, when None,
    :func:`split_jitter` of the walk. Returns (walk, chains) or None with fewer than *min_chains* such chains; a
    walk at a bound means the bound was not enough."""
    long = sample.length >= LONG_CHAIN_KEYFRAMES
    n = int(long.sum())
    if n < min_chains:
        return None
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    for _ in range(steps):
        w = float(np.exp(0.5 * (lo + hi)))
        j = split_jitter(w) if jitter is None else jitter
        if sample.nees(w, j, long).mean() > 1.0:
            lo = np.log(w)  # still overconfident: more walk
        else:
            hi = np.log(w)
    return float(np.exp(0.5 * (lo + hi))), n


@dataclass(frozen=True)
class ChainModel:
    """A run's calibrated chain model: the steps' covariance scaled by ``walk`` as it compounds, ``jitter`` × the
    median step covariance at both ends, fitted on ``long_chains`` closures of at least
    :data:`LONG_CHAIN_KEYFRAMES` keyframes; ``heading_drift_deg_per_m`` is the heading-rate σ it holds (0: none)."""

    walk: float
    jitter: float
    long_chains: int
    heading_drift_deg_per_m: float = 0.0

    def as_dict(self) -> dict:
        return dict(vars(self))


def calibrate(sample: ChainSample, min_chains: int = 30) -> ChainModel | None:
    """The walk and jitter shares of the steps' covariance from a *sample* of chains against a reference (the
    module's calibration), or None with fewer than *min_chains* long chains to fit them to."""
    fitted = fit_walk(sample, None, min_chains)
    if fitted is None:
        return None
    walk, n = fitted
    return ChainModel(walk, split_jitter(walk), n)
