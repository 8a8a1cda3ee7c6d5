"""Costs of a pose-graph solution: the SE-Sync objective and GTSAM's χ² (``NonlinearFactorGraph.error``).

SE-Sync objective (Rosen et al., "SE-Sync", IJRR 2019, eq. 12; no ½ factor), summed over edges (i, j):
``f = Σ κ_ij ‖R_j − R_i R̃_ij‖_F² + τ_ij ‖t_j − t_i − R_i t̃_ij‖²``, with the isotropic weights κ, τ
(Rosen et al. 2019, eq. 14) obtained from the g2o information matrix exactly as SE-Sync's
``SESync_utils.cpp`` does (``../shared/data/PUBLISHED_RESULTS.md`` §2): 2D ``τ = 2 / tr(I_tt⁻¹)``,
``κ = I_θθ``; 3D ``τ = 3 / tr(I_tt⁻¹)``, ``κ = 3 / (2 tr(I_rr⁻¹))``. They use the translation and rotation
blocks only, so an edge whose whole information is not positive definite (a strong translation–rotation
coupling) still has usable weights when both are positive. Priors count with R_i = I, t_i = 0.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .posegraph import EdgeArrays, GraphError, PoseGraph

Array = NDArray[np.float64]

__all__ = ["chordal_weights", "sesync_weights", "sesync_objective", "chordal_residuals", "gtsam_error"]


def _trace_of_inverse(M: Array) -> Array:
    """``tr(M⁻¹)`` of each ``(k, k)`` matrix of a stack; +inf for a singular one (its weight is then 0)."""
    try:
        return np.trace(np.linalg.inv(M), axis1=1, axis2=2)
    except np.linalg.LinAlgError:
        out = np.full(len(M), np.inf)
        for k, A in enumerate(M):
            try:
                out[k] = np.trace(np.linalg.inv(A))
            except np.linalg.LinAlgError:
                pass
        return out


def sesync_weights(information: Array, dim: int) -> tuple[Array, Array]:
    """Per-edge (κ, τ) ``(M,)`` of stacked information matrices ``(M, D, D)`` (translation block first),
    Rosen et al. 2019, eq. 14; not positive for an edge no back end can use."""
    It = information[:, :dim, :dim]
    Ir = information[:, dim:, dim:]
    tau = dim / _trace_of_inverse(It)
    if dim == 2:
        kappa = Ir[:, 0, 0].copy()
    else:
        kappa = 3.0 / (2.0 * _trace_of_inverse(Ir))
    return kappa, tau


def chordal_weights(graph: PoseGraph) -> tuple[Array, Array]:
    """Per-edge (κ, τ) ``(M,)`` from the graph's information matrices (:func:`sesync_weights`)."""
    return sesync_weights(graph.edge_arrays().information, graph.dim)


def _endpoints(poses: Array, ii: NDArray[np.int64], dim: int) -> tuple[Array, Array]:
    """Rotations and translations of the edges' first node; identity/zero for priors (ii = −1)."""
    R = poses[:, :dim, :dim]
    t = poses[:, :dim, 3]
    Ri = R[ii]
    ti = t[ii]
    prior = ii < 0
    if prior.any():
        Ri[prior] = np.eye(dim)
        ti[prior] = 0.0
    return Ri, ti


def chordal_residuals(poses: Array, edges: EdgeArrays, dim: int) -> tuple[Array, Array]:
    """Per-edge chordal errors ``E_R = R_iᵀR_j − R̃`` ``(M, d, d)`` and ``e_t = R_iᵀ(t_j − t_i) − t̃`` ``(M, d)``.

    ‖E_R‖_F = ‖R_j − R_i R̃‖_F and ‖e_t‖ = ‖t_j − t_i − R_i t̃‖ (rotation invariance), so the weighted sum
    of their squares is the SE-Sync objective.
    """
    Ri, ti = _endpoints(poses, edges.ii, dim)
    Rj = poses[edges.jj, :dim, :dim]
    tj = poses[edges.jj, :dim, 3]
    Z = edges.measurements
    RiT = np.swapaxes(Ri, 1, 2)
    ER = RiT @ Rj - Z[:, :dim, :dim]
    et = np.einsum("mab,mb->ma", RiT, tj - ti) - Z[:, :dim, 3]
    return ER, et


def sesync_objective(graph: PoseGraph, poses: ArrayLike | None = None) -> float:
    """SE-Sync objective of *poses* ``(N, 4, 4)`` (default: the graph's node poses) on *graph*."""
    P = graph.poses if poses is None else np.asarray(poses, dtype=float)
    if not np.all(np.isfinite(P)):
        raise GraphError("every node needs a pose to evaluate the objective")
    kappa, tau = chordal_weights(graph)
    ER, et = chordal_residuals(P, graph.edge_arrays(), graph.dim)
    return float(np.sum(kappa * np.einsum("mab,mab->m", ER, ER)) + np.sum(tau * np.einsum("ma,ma->m", et, et)))


def gtsam_error(graph: PoseGraph, poses: ArrayLike | None = None, *, robust: bool = True) -> float:
    """GTSAM's ``NonlinearFactorGraph.error`` = ½ Σ eᵀΩe on the log-map errors (robust losses when the edges
    carry kernels and *robust* is true), without any gauge prior."""
    from slam.backends.gtsam_backend import build_factor_graph, to_values

    P = graph.poses if poses is None else np.asarray(poses, dtype=float)
    fg = build_factor_graph(graph, use_kernels=robust, anchor=False)
    return float(fg.error(to_values(P, graph.dim)))
