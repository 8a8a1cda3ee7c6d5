"""What every ICP variant shares: its result, the preparation of its inputs, the robust weights of its
pairs, and the final evaluation at the pose it reached — correspondences at the last gate, RMSE, the
pose covariance from the Fisher information of the chosen residual model and the residual χ² test
(:mod:`registration.covariance`; Förstner & Wrobel 2016). :mod:`registration.icp` (point-to-point) and
:mod:`registration.point_to_plane` both build on it; neither imports the other."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.errors import DegenerateInputError, GeometryError

from .config import IcpConfig
from .covariance import (Chi2Verdict, chi2_test, covariance_from_information, fisher_information,
                         jacobian_plane, jacobian_point)
from .matching import pair_distances
from .target import IcpTarget, gated_nearest
from .voxel import voxel_downsample

Array = NDArray[np.float64]

__all__ = ["COMPILED_2D", "COMPILED_3D", "ROBUST_CODES", "IcpResult", "as_target", "evaluate_alignment", "evaluate_matches",
           "prepare", "robust_weights"]

#: 2D alignments (without a prior) run the compiled iterations of registration.kernels_icp; the numpy loops of
#: registration.icp and registration.point_to_plane are the same algorithms, kept for priors, trimming and as
#: the reference the tests compare with.
COMPILED_2D = True
#: 3D alignments run compiled iterations on a cell grid of the target instead of the numpy loops on its k-d tree
#: (same algorithms, kept as the references): point-to-plane without a prior registration.kernels_icp3d,
#: point-to-point registration.kernels_icp3d_point
COMPILED_3D = True
#: IcpConfig.robust → the compiled loop's code (trimming needs a partial sort: numpy loop)
ROBUST_CODES = {"none": 0, "huber": 1, "cauchy": 2}


def compiled_loop_args(S: NDArray[np.float64], T: NDArray[np.float64], config: IcpConfig, dim: int) -> tuple:
    """The leading arguments every compiled ICP loop takes (``registration.kernels_icp*``): the source points, the
    start's rotation and translation (*dim* = 2 or 3), the gates and the stopping, weighting and inlier settings."""
    return (np.ascontiguousarray(S), T[:dim, :dim].copy(), T[:dim, 3].copy(),
            np.asarray(config.gates_m, dtype=np.float64), config.max_iterations, config.tol_translation_m,
            config.tol_rotation_rad, ROBUST_CODES[config.robust], config.robust_scale_m, config.min_inliers)


@dataclass(frozen=True)
class IcpResult:
    """Outcome of one alignment.

    Attributes:
        transform: 4×4 ``target_T_source`` (planar for 2D inputs).
        rmse: root mean square distance of the inlier pairs (m) at the final gate.
        inliers: number of gated (and kept) pairs; fitness = inliers / source points used.
        iterations: ICP iterations over all stages.
        converged: the last stage met the increment tolerance before the iteration cap.
        residual: Res = Σ w e² of the covariance model's scalar residuals (m²).
        n_residuals, dof: scalar residual count and pose dimension (3 or 6).
        covariance: ``(dof, dof)`` covariance of δ with T_true = T·Exp(δ), translation first.
        degenerate: the information matrix had unobserved directions (see covariance module).
        chi2: the residual test verdict (σ², threshold, accepted).
    """

    transform: Array
    rmse: float
    inliers: int
    fitness: float
    iterations: int
    converged: bool
    residual: float
    n_residuals: int
    dof: int
    covariance: Array
    degenerate: bool
    chi2: Chi2Verdict

    @property
    def accepted(self) -> bool:
        """True when the χ² test accepts the alignment."""
        return self.chi2.accepted

    @property
    def information(self) -> Array:
        """Inverse covariance (for pose-graph edges)."""
        return np.linalg.inv(self.covariance)


def robust_weights(dist: Array, config: IcpConfig) -> Array:
    """Per-pair weights: 1 (``none``), 0/1 keeping the closest ``trim_fraction`` (``trim``), Huber
    ``min(1, k/|r|)`` or Cauchy ``1/(1 + (r/k)²)`` with k = ``robust_scale`` (Zhang, IVC 1997)."""
    if config.robust == "none":
        return np.ones_like(dist)
    if config.robust == "trim":
        keep = max(3, int(np.ceil(config.trim_fraction * len(dist))))
        w = np.zeros_like(dist)
        if keep >= len(dist):
            w[:] = 1.0
        else:
            w[np.argpartition(dist, keep - 1)[:keep]] = 1.0
        return w
    k = config.robust_scale_m
    if config.robust == "huber":
        return np.minimum(1.0, k / np.maximum(dist, 1e-300))
    return 1.0 / (1.0 + (dist / k) ** 2)


def as_target(target: ArrayLike | IcpTarget, config: IcpConfig) -> IcpTarget:
    if isinstance(target, IcpTarget):
        return target
    return IcpTarget(target, config.target_voxel_m, config.normal_neighbors, config.workers)


def prepare(source: ArrayLike, tgt: IcpTarget, init: ArrayLike | None, config: IcpConfig) -> tuple[Array, Array]:
    S = np.asarray(source, dtype=np.float64)
    if S.ndim != 2 or S.shape[1] != tgt.dim:
        raise GeometryError(f"source must be (N, {tgt.dim}) like the target, got shape {S.shape}")
    if config.voxel_m:
        S = voxel_downsample(S, config.voxel_m)
    if len(S) < 3:
        raise DegenerateInputError(f"source has {len(S)} points; ICP needs at least 3")
    T = np.eye(4) if init is None else np.array(init, dtype=np.float64)
    if T.shape != (4, 4):
        raise GeometryError(f"initial guess must be a 4×4 pose, got shape {T.shape}")
    return S, T


def evaluate_alignment(S: Array, tgt: IcpTarget, T: Array, gate: float, config: IcpConfig, iterations: int = 0,
                       converged: bool = True) -> IcpResult:
    """Correspondences at *gate*, RMSE, covariance and χ² test of a given pose ``T = target_T_source``.

    Used at the end of every ICP, and to attach a covariance to poses found by another
    registration (KISS-ICP). *S* is ``(N, d)`` in the source frame (m)."""
    d = tgt.dim
    moved = S @ T[:d, :d].T + T[:d, 3]
    idx = gated_nearest(tgt, moved, gate, config.workers)
    return evaluate_matches(S, tgt, T, moved, idx, gate, config, iterations, converged)


def evaluate_matches(S: Array, tgt: IcpTarget, T: Array, moved: Array, idx: NDArray[np.intp], gate: float,
              config: IcpConfig, iterations: int, converged: bool) -> IcpResult:
    """:func:`evaluate_alignment` from the gated nearest neighbours *idx* of ``moved = T S``
    (unmatched = number of target points)."""
    d = tgt.dim
    R = T[:d, :d]
    n_tgt = len(tgt.points)
    if idx[-1] < n_tgt and idx.max() < n_tgt:  # every point matched: no mask copies
        src, mv, idx_in = S, moved, idx
    else:
        ok = idx < n_tgt
        src, mv, idx_in = S[ok], moved[ok], idx[ok]
    n_in = len(idx_in)
    if n_in < config.min_inliers:
        raise DegenerateInputError(f"ICP ended with {n_in} pairs within {gate} m (need {config.min_inliers})")
    matched = tgt.points.take(idx_in, axis=0)
    w = None
    if config.robust != "none":
        w = robust_weights(pair_distances(mv, matched), config)
        keep = w > 0
        src, w, idx_in, mv, matched = src[keep], w[keep], idx_in[keep], mv[keep], matched[keep]
    diff = mv - matched
    dof = 3 if d == 2 else 6
    if config.covariance_model == "plane":
        nrm = tgt.normals(idx_in)
        e = np.einsum("ij,ij->i", diff, nrm)
        J = jacobian_plane(src, nrm, R)
        w_res = w
    else:
        e = diff.reshape(-1)
        J = jacobian_point(src, R)
        w_res = None if w is None else np.repeat(w, d)
    n_res = e.size
    res = float(e @ e) if w_res is None else float(np.sum(w_res * e * e))
    verdict = chi2_test(res, n_res, dof, None if config.sigma_m is None else config.sigma_m**2,
                        config.chi2_factor, config.false_rejection_rate)
    cov, degenerate = covariance_from_information(fisher_information(J, w), verdict.sigma2)
    rmse = math.sqrt(float(np.vdot(diff, diff)) / len(diff))
    return IcpResult(T, rmse, int(len(src)), len(src) / len(S), iterations, converged, res, n_res, dof,
                     cov, degenerate, verdict)
