"""Initial pose estimates: odometry-chain composition and chordal relaxation.

Chordal initialisation (Carlone, Tron, Daniilidis, Dellaert, "Initialization techniques for 3D SLAM: a
survey on rotation estimation and its use in pose graph optimization", ICRA 2015, §IV-A / eq. 8): relax
SO(d) to ℝ^{d×d}, solve ``min Σ κ_ij ‖R_j − R_i R̃_ij‖_F²`` by linear least squares (one sparse system,
solved for the d rows of the rotations at once), project each R_i to SO(d), then solve
``min Σ τ_ij ‖t_j − t_i − R_i t̃_ij‖²`` for the translations (one graph-Laplacian system, d right-hand sides).
The gauge is fixed at the anchored nodes (FIX'ed nodes, else node 0 unless priors exist), which keep their
file pose (identity when none).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo

from .costs import chordal_weights
from .posegraph import GraphError, PoseGraph

Array = NDArray[np.float64]

__all__ = ["odometry_initialisation", "chordal_initialisation", "initial_poses"]


def _anchor_poses(graph: PoseGraph, anchors: NDArray[np.int64]) -> Array:
    P = graph.poses[anchors]
    bad = ~np.all(np.isfinite(P.reshape(len(anchors), -1)), axis=1)
    P[bad] = np.eye(4)
    return P


def odometry_initialisation(graph: PoseGraph) -> Array:
    """Compose the edges between consecutive nodes (index k → k+1, either direction) from node 0's pose.

    Returns ``(N, 4, 4)`` world_T_node poses. Raises :class:`GraphError` when a link of the chain is missing.
    """
    a = graph.edge_arrays()
    n = graph.num_nodes
    fwd = (a.jj == a.ii + 1) & (a.ii >= 0)
    bwd = (a.ii == a.jj + 1) & (a.ii >= 0)
    step = np.full((max(n - 1, 0), 4, 4), np.nan)
    # Last edge per link wins; backward edges are inverted.
    step[a.jj[bwd]] = geo.inverse(a.measurements[bwd])
    step[a.ii[fwd]] = a.measurements[fwd]
    missing = np.flatnonzero(np.isnan(step[:, 0, 0]))
    if missing.size:
        ids = graph.node_ids
        k = int(missing[0])
        raise GraphError(f"odometry initialisation: no edge between nodes {ids[k]} and {ids[k + 1]}")
    P = np.empty((n, 4, 4))
    P[0] = _anchor_poses(graph, np.zeros(1, dtype=np.int64))[0]
    for k in range(n - 1):  # a chain product is inherently sequential (N 4×4 products)
        P[k + 1] = P[k] @ step[k]
    if graph.dim == 2:
        P = geo.xytheta_to_matrix(geo.matrix_to_xytheta(P))  # keep planar poses exactly planar
    return P


def _solve_anchored(rows: Array, cols: NDArray[np.int64], vals: Array, weights: Array, n_vars: int,
                    rhs_rows: Array, fixed: NDArray[np.bool_], fixed_vals: Array) -> Array:
    """Weighted linear least squares ``min ‖W^½ (A x − b)‖²`` with some variables fixed.

    A is given in COO form (rows, cols, vals); b is ``rhs_rows`` ``(m, k)`` (k right-hand sides); variables
    with ``fixed`` keep ``fixed_vals`` ``(n_vars, k)``. Solved through the normal equations with SuperLU.
    """
    from slam.backends.linsolve import spd_solve

    m = rhs_rows.shape[0]
    A = sp.csr_matrix((vals, (rows, cols)), shape=(m, n_vars))
    b = rhs_rows - A[:, np.flatnonzero(fixed)] @ fixed_vals[fixed]
    free = np.flatnonzero(~fixed)
    Af = A[:, free]
    AtW = (Af.T @ sp.diags(weights)).tocsr()
    H = (AtW @ Af).tocsc()
    x = fixed_vals.copy()
    x[free] = spd_solve(H, AtW @ b)
    return x


def chordal_initialisation(graph: PoseGraph, edge_weights: ArrayLike | None = None) -> Array:
    """Chordal relaxation (Carlone et al. ICRA 2015): rotations, projection to SO(d), then translations.

    Returns ``(N, 4, 4)`` poses; uses the SE-Sync weights κ (rotation) and τ (translation), each multiplied
    by the optional per-edge *edge_weights* ``(M,)`` (used by :func:`robust_chordal_initialisation`).
    """
    d = graph.dim
    n = graph.num_nodes
    a = graph.edge_arrays()
    kappa, tau = chordal_weights(graph)
    if edge_weights is not None:
        w = np.asarray(edge_weights, dtype=float)
        kappa, tau = kappa * w, tau * w
    m = len(a.jj)
    prior = a.ii < 0
    anchors = graph.anchor_indices()
    fixed = np.zeros(n, dtype=bool)
    fixed[anchors] = True
    Pa = _anchor_poses(graph, anchors)
    Zr = a.measurements[:, :d, :d]
    Zt = a.measurements[:, :d, 3]

    # --- rotations: row u_i = R_i[r, :]ᵀ satisfies u_j − R̃ᵀ u_i = 0 for every row r (d right-hand sides).
    er = np.arange(m)[:, None] * d + np.arange(d)[None, :]  # (m, d) residual rows of each edge
    rows_j = er.ravel()
    cols_j = (a.jj[:, None] * d + np.arange(d)[None, :]).ravel()
    vals_j = np.ones(m * d)
    nb = ~prior
    ZrT = np.swapaxes(Zr[nb], 1, 2)  # (mb, d, d): coefficient of u_i is −R̃ᵀ
    rows_i = np.repeat(er[nb], d, axis=1).ravel()
    cols_i = np.tile(a.ii[nb][:, None] * d + np.arange(d)[None, :], (1, d)).ravel()
    vals_i = -ZrT.reshape(-1)
    # residual row (e, p) = u_j[p] − Σ_q R̃ᵀ[p, q] u_i[q]; rows_i repeats p, cols_i tiles q: matches ZrT[p, q].
    rhs = np.zeros((m * d, d))
    if prior.any():  # prior: u_j = R̃[r, :]ᵀ → rhs row (e, p) for right-hand side r is R̃[r, p]
        rhs[er[prior].ravel()] = np.swapaxes(Zr[prior], 1, 2).reshape(-1, d)
    fixed_r = np.repeat(fixed, d)
    fixed_vals = np.zeros((n * d, d))
    Ra = Pa[:, :d, :d]  # anchored rotations: u = R[r, :]ᵀ → variable (node, q) for rhs r is R[r, q]
    fixed_vals[(anchors[:, None] * d + np.arange(d)[None, :]).ravel()] = np.swapaxes(Ra, 1, 2).reshape(-1, d)
    U = _solve_anchored(np.concatenate([rows_j, rows_i]), np.concatenate([cols_j, cols_i]),
                        np.concatenate([vals_j, vals_i]), np.repeat(kappa, d), n * d, rhs, fixed_r, fixed_vals)
    M = np.swapaxes(U.reshape(n, d, d), 1, 2)  # M[i][r, q] = U[(i, q), r]
    R = geo.project_to_so2(M) if d == 2 else geo.project_to_so3(M)
    R[anchors] = Ra

    # --- translations: t_j − t_i = R_i t̃ (graph Laplacian, d right-hand sides).
    Ri = np.where(prior[:, None, None], np.eye(d), R[np.maximum(a.ii, 0)])
    b = np.einsum("mab,mb->ma", Ri, Zt)
    rows = np.concatenate([np.arange(m), np.flatnonzero(nb)])
    cols = np.concatenate([a.jj, a.ii[nb]])
    vals = np.concatenate([np.ones(m), -np.ones(int(nb.sum()))])
    fixed_t = np.zeros((n, d))
    fixed_t[anchors] = Pa[:, :d, 3]
    t = _solve_anchored(rows, cols, vals, tau, n, b, fixed, fixed_t)

    P = np.zeros((n, 4, 4))
    if d == 2:
        P[:] = geo.xytheta_to_matrix(t[:, 0], t[:, 1], np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    else:
        P[:, :3, :3] = R
        P[:, :3, 3] = t
        P[:, 3, 3] = 1.0
    return P


def initial_poses(graph: PoseGraph, method: str) -> Array:
    """``odometry`` | ``chordal`` | ``file`` (the graph's own node poses; every node must have one)."""
    if method == "odometry":
        return odometry_initialisation(graph)
    if method == "chordal":
        return chordal_initialisation(graph)
    if method == "file":
        if not graph.has_initial_guess:
            raise GraphError("--init file: the graph has nodes without an initial pose (no VERTEX lines)")
        return graph.poses.copy()
    raise GraphError(f"unknown initialisation {method!r}; expected odometry, chordal or file")
