"""Consistency of the front end's relative-pose covariance: NEES along keyframe chains against ground truth.

The front end gives, between consecutive keyframes, a registration edge and (with wheel odometry) a
wheel edge, each with a covariance. Without loop closures the graph's estimate of keyframe *b*
relative to keyframe *a* is the chain of those steps (parallel edges of a step fused by adding their
information), and its covariance is the chain's compounded covariance (first-order propagation,
Barfoot, *State Estimation for Robotics*, §7.3.3). A ground-truth relative pose δ* (a Kümmerle et al.
2009 relation) gives the error ``e = Log(δ*⁻¹ · estimate)`` and the normalised estimation error
squared ``NEES = eᵀ Σ⁻¹ e`` (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking
and Navigation*, 2001, §5.4.2). For a consistent covariance NEES/dof averages 1 at every chain length:
above, the covariance is overconfident (search windows too small, closures over-trusted); below, it is
conservative.

The chain model may add the loop closer's random-constant heading rate (:mod:`slam.loops.uncertainty`): a
rate b ~ N(0, σ_b²) per metre turns step k by b·ℓ_k (ℓ_k its length), common to all steps, so it adds the
rank-one ``σ_b² u uᵀ`` with ``u = Σ_k Ad(C_b⁻¹ C_k) (0, 0, ℓ_k)`` to the chain's covariance; a scale error of
the rotation k ~ N(0, σ_k²) (every turn Δθ_k off by k·Δθ_k; Borenstein & Feng 1996, type-B odometry error)
adds ``σ_k² w wᵀ`` the same way, with Δθ_k for ℓ_k. :func:`heading_fit` measures both on the relations: the
heading error of long chains regressed on their path length and their summed signed turn.

A scan-to-map front end's steps are not independent: its error is largely jitter, which the next step undoes.
The chains' covariance is therefore split into a compounded walk and a jitter at both ends, with the shares the
run's own long closures calibrate (:mod:`evaluation.chain_model`); :func:`chain_sample` and :func:`closure_sample`
keep the parts apart, so any model's NEES is one product away.

Relations between scans that are not keyframes are carried to the keyframes before them with the
front end's own per-scan odometry (its error over those few scans is not in the chain's covariance).

Planar (SE(2)) chains only; poses are 4×4, covariances in the tangent order ``(x, y, θ)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core import geometry as G

from .chain_model import Chain, ChainSample

Array = NDArray[np.float64]

#: Chain-length bins (keyframes): [1], [2], [3, 5], [6, 10], [11, 30], [31, 100], [101, 300], [301, 1000], [1001, ∞)
BIN_EDGES = (1, 2, 3, 6, 11, 31, 101, 301, 1001, 10**9)


@dataclass(frozen=True)
class NeesBin:
    """Relations whose ends are ``lo`` … ``hi`` keyframes apart: how many, NEES/dof (mean, median), and
    the RMS error beside the mean predicted standard deviation (translation m, rotation deg)."""

    lo: int
    hi: int
    n: int
    nees_mean: float
    nees_median: float
    rms_translation_m: float
    sigma_translation_m: float
    rms_rotation_deg: float
    sigma_rotation_deg: float

    def as_dict(self) -> dict:
        return dict(vars(self))


def fuse_steps(K: int, edges: list[tuple[int, int, Array, Array]]) -> tuple[Array, Array]:
    """Per step k (keyframe k − 1 → k, k ≥ 1) the fused mean ``(K, 4, 4)`` and covariance ``(K, 3, 3)`` of the
    edges ``(i, j, measurement i_T_j, covariance)`` between consecutive keyframes: information added on
    the tangent space of the step's first edge (Gauss–Newton's first step, exact to first order).
    Raises ValueError when a step has no edge."""
    by_step: dict[int, list[tuple[Array, Array]]] = {}
    for i, j, T, cov in edges:
        step = forward_step(i, j, T, cov)
        if step is not None:
            by_step.setdefault(step[0], []).append(step[1:])
    mu = np.tile(np.eye(4), (K, 1, 1))
    cov = np.zeros((K, 3, 3))
    for k in range(1, K):
        if k not in by_step:
            raise ValueError(f"no edge between keyframes {k - 1} and {k}")
        mu[k], cov[k] = fuse_step(by_step[k])
    return mu, cov


def fuse_step(edges: list[tuple[Array, Array]]) -> tuple[Array, Array]:
    """Parallel edges ``(a_T_b, covariance)`` of one step fused: information added on the tangent space of the first
    edge (Gauss–Newton's first step, exact to first order); the fused mean and covariance."""
    base, _ = edges[0]
    info = np.zeros((3, 3))
    vec = np.zeros(3)
    for T, C in edges:
        W = np.linalg.inv(C)
        info += W
        vec += W @ G.se2_log(G.relative(base, T))
    S = np.linalg.inv(info)
    return base @ G.se2_exp(S @ vec), S


def forward_step(i: int, j: int, T: Array, cov: Array) -> tuple[int, Array, Array] | None:
    """An edge ``(i, j, i_T_j, covariance)`` between consecutive keyframes as the step k it measures (keyframe
    k − 1 → k), forward: ``(k, (k−1)_T_k, covariance)``; None for an edge between keyframes further apart."""
    if j == i + 1:
        return j, np.asarray(T, float), np.asarray(cov, float)
    if i == j + 1:
        return i, G.inverse(T), _inverse_covariance(T, cov)
    return None


def _inverse_covariance(T: Array, cov: Array) -> Array:
    """Covariance of ``T⁻¹`` with right perturbations: Ad(T) Σ Ad(T)ᵀ."""
    A = G.adjoint(T, planar=True)
    return A @ cov @ A.T


def chain_sample(mu: Array, cov: Array, keyframe_of_scan: NDArray[np.int64], scan_odometry: Array,
                 keyframe_odometry: Array, pairs: NDArray[np.int64], truth: Array, drift_rad_per_m: float = 0.0,
                 reference_cov: Array | None = None, drift_per_turn: float = 0.0) -> ChainSample:
    """The chains of relations ``(scan a, scan b)`` with true ``a_T_b`` *truth*, as a :class:`ChainSample` (the error
    signed as the estimate's minus the truth's).

    *mu*, *cov*: :func:`fuse_steps`; *keyframe_of_scan*: the last keyframe at or before each scan;
    *scan_odometry* ``(N, 4, 4)`` and *keyframe_odometry* ``(K, 4, 4)``: the front end's odometry poses,
    which carry each scan to its keyframe; *drift_rad_per_m*: σ_b of the heading rate, *drift_per_turn*: σ_k of the
    rotation's scale error (rad per rad; 0: none), both :class:`~evaluation.chain_model.Chain`'s;
    *reference_cov* ``(3, 3)``: the relations' own error (:func:`evaluation.relations.reference_noise`), added to
    the chain's (the test is then of ``e ~ N(0, Σ_chain + Σ_ref)``). Relations within one keyframe interval
    are left out."""
    chain = Chain(mu, cov, drift_rad_per_m, drift_per_turn)
    ref = np.zeros((3, 3)) if reference_cov is None else np.asarray(reference_cov, float)
    rows = []
    for (sa, sb), delta in zip(pairs, truth):
        if sa > sb:
            sa, sb, delta = sb, sa, G.inverse(delta)
        ka, kb = int(keyframe_of_scan[sa]), int(keyframe_of_scan[sb])
        if kb <= ka:
            continue
        A = G.relative(keyframe_odometry[ka], scan_odometry[sa])
        B = G.relative(keyframe_odometry[kb], scan_odometry[sb])
        T, P, Q, R = chain.parts(ka, kb)
        est = G.inverse(A) @ T @ B
        AdB = G.adjoint(G.inverse(B), planar=True)
        rows.append(_sample_row(chain, ka, kb, G.se2_log(G.relative(delta, est)),
                                AdB @ P @ AdB.T, AdB @ Q @ AdB.T, AdB @ R @ AdB.T + ref))
    return ChainSample.of(rows)


def chain_nees(mu: Array, cov: Array, keyframe_of_scan: NDArray[np.int64], scan_odometry: Array,
               keyframe_odometry: Array, pairs: NDArray[np.int64], truth: Array, drift_rad_per_m: float = 0.0,
               reference_cov: Array | None = None, drift_per_turn: float = 0.0, walk: float = 1.0,
               jitter: float = 0.0) -> Array:
    """:meth:`ChainSample.rows` of :func:`chain_sample` under *walk* and *jitter*: per relation (chain length in
    keyframes, NEES/dof, translation error m, rotation error rad, predicted translation σ m, predicted rotation σ
    rad, odometry path length between the keyframes m, signed heading error rad (estimate minus truth), summed
    signed odometry turn between the keyframes rad)."""
    return chain_sample(mu, cov, keyframe_of_scan, scan_odometry, keyframe_odometry, pairs, truth, drift_rad_per_m,
                        reference_cov, drift_per_turn).rows(walk, jitter)


def _sample_row(chain: Chain, a: int, b: int, e: Array, P: Array, Q: Array, R: Array) -> tuple:
    """One chain *a* → *b* of a :class:`ChainSample`: its error *e* and covariance parts."""
    return (b - a, e, P, Q, R, float(chain.path[b] - chain.path[a]), float(chain.turn[b] - chain.turn[a]))


def closure_sample(mu: Array, cov: Array, closures: list[tuple[int, int, Array, Array]],
                   drift_rad_per_m: float = 0.0, drift_per_turn: float = 0.0) -> ChainSample:
    """:func:`chain_sample` with a run's own loop closures as the reference, where a log has no relations: per closure
    ``(i, j, i_T_j, covariance)`` between keyframes, the chain's error against it, the closure's covariance added to
    the chain's (the test is of ``e ~ N(0, Σ_chain + Σ_closure)``; the heading error signed as the chain's minus the
    closure's). A closure was accepted because it agreed with the graph's estimate, which earlier closures had
    already corrected, so the gate truncates the sample only where the chain is short; for long chains the
    closures test the chain much as independent relations would (docs/LOOP_CLOSURE.md has both side by side)."""
    chain = Chain(mu, cov, drift_rad_per_m, drift_per_turn)
    rows = [closure_row(chain, i, j, Z, C) for i, j, Z, C in closures if i != j]
    return ChainSample.of(rows)


def closure_row(chain: Chain, i: int, j: int, Z: Array, C: Array, constants_scale: bool = False) -> tuple:
    """One closure ``(i, j, i_T_j, covariance)`` (i ≠ j, either older) as a :class:`ChainSample` row: the *chain*'s
    error against it, with the closure's covariance in the fixed part. *constants_scale*: the chain's random
    constants (heading rate, rotation scale) go with the walk part instead, so that a walk scales the chain's
    whole covariance."""
    if i > j:  # the same closure seen from the older keyframe (its covariance carried by the adjoint)
        i, j, Z, C = j, i, G.inverse(Z), _inverse_covariance(Z, C)
    T, P, Q, R = chain.parts(i, j)
    if constants_scale:
        P, R = P + R, np.zeros((3, 3))
    return _sample_row(chain, i, j, G.se2_log(G.relative(Z, T)), P, Q, R + C)


def closure_nees(mu: Array, cov: Array, closures: list[tuple[int, int, Array, Array]],
                 drift_rad_per_m: float = 0.0, drift_per_turn: float = 0.0, walk: float = 1.0,
                 jitter: float = 0.0) -> Array:
    """:meth:`ChainSample.rows` of :func:`closure_sample` under *walk* and *jitter* (rows as :func:`chain_nees`'s)."""
    return closure_sample(mu, cov, closures, drift_rad_per_m, drift_per_turn).rows(walk, jitter)


@dataclass(frozen=True)
class HeadingFit:
    """Least squares of the signed heading error of chains over at least ``min_path_m`` of odometry on a rate
    per metre of path and a scale of the summed signed turn (``error ≈ rate·path + scale·turn``): the two
    systematic odometry errors, measured. ``rms_deg`` is the residual of that fit, ``rms_rate_only_deg`` of the
    rate alone; ``turn_median_deg`` the chains' median |summed turn| (a robot circling one way gathers it)."""

    n: int
    min_path_m: float
    rate_deg_per_m: float
    scale_rad_per_rad: float
    rms_deg: float
    rms_rate_only_deg: float
    turn_median_deg: float

    def as_dict(self) -> dict:
        return dict(vars(self))


def heading_fit(rows: Array, min_path_m: float = 50.0) -> HeadingFit | None:
    """:class:`HeadingFit` of :func:`chain_nees` rows (None with fewer than 10 chains that long). The chains share
    steps, so the fit is a measurement of the log's systematic errors, not a test with independent samples."""
    r = rows[rows[:, 6] >= min_path_m]
    if len(r) < 10:
        return None
    err, path, turn = r[:, 7], r[:, 6], r[:, 8]
    (rate, scale), *_ = np.linalg.lstsq(np.column_stack([path, turn]), err, rcond=None)
    rate_only = float(path @ err / (path @ path))
    return HeadingFit(len(r), float(min_path_m), float(np.degrees(rate)), float(scale),
                      float(np.degrees(np.sqrt(np.mean((err - rate * path - scale * turn) ** 2)))),
                      float(np.degrees(np.sqrt(np.mean((err - rate_only * path) ** 2)))),
                      float(np.degrees(np.median(np.abs(turn)))))


#: Path-length bins (m) of :func:`heading_by_path`.
PATH_EDGES_M = (50.0, 100.0, 200.0, 400.0, 800.0, np.inf)


@dataclass(frozen=True)
class HeadingBin:
    """Relations whose chains run ``lo_m`` … ``hi_m`` metres of odometry: how many, the median and 95th
    percentile of the absolute heading error (°) and of its rate per metre of path, and the chain's
    median predicted heading σ (°). A rate that stays constant as the path grows is drift the
    independent edge noise cannot represent (:mod:`slam.loops.uncertainty`)."""

    lo_m: float
    hi_m: float
    n: int
    error_median_deg: float
    error_p95_deg: float
    rate_median_deg_per_m: float
    rate_p95_deg_per_m: float
    sigma_median_deg: float

    def as_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in vars(self).items()}


def heading_by_path(rows: Array, edges: tuple[float, ...] = PATH_EDGES_M, min_n: int = 3) -> list[HeadingBin]:
    """:class:`HeadingBin` per path-length bin of :func:`chain_nees` rows (bins of fewer than *min_n* left out)."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        r = rows[(rows[:, 6] >= lo) & (rows[:, 6] < hi)]
        if len(r) < min_n:
            continue
        err = np.degrees(r[:, 3])
        rate = err / r[:, 6]
        out.append(HeadingBin(float(lo), float(hi), len(r), float(np.median(err)), float(np.percentile(err, 95)),
                              float(np.median(rate)), float(np.percentile(rate, 95)), float(np.degrees(np.median(r[:, 5])))))
    return out


def bin_by_length(rows: Array, edges: tuple[int, ...] = BIN_EDGES) -> list[NeesBin]:
    """:class:`NeesBin` per chain-length bin of :func:`chain_nees` rows (empty bins left out)."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (rows[:, 0] >= lo) & (rows[:, 0] < hi)
        if not m.any():
            continue
        r = rows[m]
        out.append(NeesBin(lo, hi - 1, int(m.sum()), float(r[:, 1].mean()), float(np.median(r[:, 1])),
                           float(np.sqrt(np.mean(r[:, 2] ** 2))), float(np.mean(r[:, 4])),
                           float(np.degrees(np.sqrt(np.mean(r[:, 3] ** 2)))), float(np.degrees(np.mean(r[:, 5])))))
    return out
