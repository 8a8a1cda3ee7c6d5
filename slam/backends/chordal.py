"""Hand-written chordal Gauss-Newton pose-graph solver (vectorised sparse assembly).

Grisetti, "Multi-pose registration and Graph-SLAM" (Probabilistic Robotics course slides, Sapienza):
state = the poses X_k; perturbation on the **left** in world coordinates, ``X' = v2t(Δx)·X`` with
``Δx = (Δt, Δα)``; chordal error ``e_ij = flatten(X_i⁻¹ X_j) − flatten(Z_ij)`` (the rotation entries and
the translation: 12-D in 3D, 6-D in 2D); ``J_j = ∂e/∂Δx_j`` at 0 and ``J_i = −J_j``; ``H = Σ JᵀΩJ``,
``b = Σ JᵀΩe``; ``H Δx = −b`` with the gauge fixed by anchoring nodes.

With the isotropic weights ``Ω = diag(κ I_{d²}, τ I_d)`` (SE-Sync's κ, τ from the rotation and translation blocks of
each edge's information, Rosen et al. IJRR 2019, eq. 14; :func:`slam.graph.costs.chordal_weights`) the cost
``Σ eᵀΩe`` *is* the SE-Sync objective (Rosen et al. IJRR 2019, eq. 12), because ‖R_iᵀR_j − R̃‖_F =
‖R_j − R_i R̃‖_F and ‖R_iᵀ(t_j − t_i) − t̃‖ = ‖t_j − t_i − R_i t̃‖. The Jacobian then has a closed-form
normal-equation block (derived from the slides' J_j; ``[t]×`` the skew matrix of t_j):

* 3D: ``JᵀΩJ = [[τI, −τ[t]×], [τ[t]×, 2κI − τ[t]×²]]``;
  ``JᵀΩe = [τ R_i e_t ; τ [t]× R_i e_t + κ g]`` with ``g = vee(A − Aᵀ)``, ``A = I − R_i R̃ R_jᵀ``;
* 2D: the same with ``[t]× → S t`` (S the 90° rotation) and ``g = A₁₀ − A₀₁``.

The blocks depend on t_j only, so the sparsity pattern (BSR block index arrays) is computed once, with the
free nodes numbered in a fill-reducing (minimum-degree) order of the block graph; each iteration only scatters
new values with ``np.bincount`` and factorises with SuperLU (:func:`slam.backends.linsolve.spd_factor`). Levenberg damping (``H + λ diag H``) is optional and also switched
on automatically when a Gauss-Newton step increases the cost.

Since only κ and τ enter, an edge whose whole information matrix is not positive definite (a strong
translation–rotation coupling) is solved like any other when both are positive, as SE-Sync does; the
solver warns once with the number of such edges (the GTSAM back end refuses them).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from slam.graph.costs import chordal_weights
from slam.graph.posegraph import GraphError, PoseGraph

from .linsolve import spd_factor

Array = NDArray[np.float64]

__all__ = ["ChordalResult", "solve_chordal"]


@dataclass
class ChordalResult:
    """Optimised ``poses`` ``(N, 4, 4)``; ``cost`` = SE-Sync objective; ``history`` = cost per iteration."""

    poses: Array
    cost: float
    initial_cost: float
    iterations: int
    time_s: float
    converged: bool
    history: list[float] = field(default_factory=list)


class _Pattern:
    """Block sparsity pattern of H over the free (non-anchored) nodes, built once per graph (and once more
    after the fill-reducing ordering is known): D×D blocks in BSR form, converted to CSC for SuperLU."""

    def __init__(self, ii: NDArray[np.int64], jj: NDArray[np.int64], var: NDArray[np.int64], D: int) -> None:
        m = len(jj)
        vi = np.where(ii >= 0, var[np.maximum(ii, 0)], -1)
        vj = var[jj]
        e = np.arange(m)
        # blocks (row var, col var, sign, edge): jj, ii, ij, ji
        br = np.concatenate([vj, vi, vi, vj])
        bc = np.concatenate([vj, vi, vj, vi])
        bs = np.concatenate([np.ones(m), np.ones(m), -np.ones(m), -np.ones(m)])
        be = np.concatenate([e, e, e, e])
        keep = (br >= 0) & (bc >= 0)
        br, bc, bs, be = br[keep], bc[keep], bs[keep], be[keep]
        self.n = int(var.max()) + 1 if var.size and var.max() >= 0 else 0
        self.D = D
        n = self.n
        uniq, inverse = np.unique(br.astype(np.int64) * n + bc, return_inverse=True)
        self.nnzb = len(uniq)
        self.indices = (uniq % n).astype(np.int32)
        self.indptr = np.searchsorted(uniq // n, np.arange(n + 1)).astype(np.int32)
        DD = D * D
        self.scatter = (inverse[:, None] * DD + np.arange(DD)[None, :]).ravel()
        self.sign = bs
        self.edge = be
        self.gj = vj  # gradient scatter: +b_j at var j, −b_i at var i
        self.gi = vi

    def matrix(self, B: Array) -> sp.csc_matrix:
        D = self.D
        vals = (B[self.edge] * self.sign[:, None, None]).ravel()
        data = np.bincount(self.scatter, weights=vals, minlength=self.nnzb * D * D).reshape(-1, D, D)
        nv = self.n * D
        # H is symmetric, so the CSR form of its BSR is also its CSC form.
        return sp.bsr_matrix((data, self.indices, self.indptr), shape=(nv, nv)).tocsr().T.tocsc()

    def gradient(self, bj: Array) -> Array:
        D = self.D
        nv = self.n * D
        okj = self.gj >= 0
        idx = (self.gj[okj, None] * D + np.arange(D)).ravel()
        out = np.bincount(idx, weights=bj[okj].ravel(), minlength=nv)
        oki = self.gi >= 0
        idx = (self.gi[oki, None] * D + np.arange(D)).ravel()
        out -= np.bincount(idx, weights=bj[oki].ravel(), minlength=nv)
        return out


def _block_ordering(ii: NDArray[np.int64], jj: NDArray[np.int64], var: NDArray[np.int64]) -> NDArray[np.int64]:
    """Fill-reducing node ordering: SuperLU's minimum-degree ordering (MMD on AᵀA + A) of the block graph of
    H (one scalar per node, on a diagonally dominant stand-in with H's block pattern, so it is cheap).
    Returns the new position of every free node."""
    n = int(var.max()) + 1
    vi = np.where(ii >= 0, var[np.maximum(ii, 0)], -1)
    vj = var[jj]
    ok = (vi >= 0) & (vj >= 0)
    S = sp.coo_matrix((np.ones(int(ok.sum())), (vi[ok], vj[ok])), shape=(n, n)).tocsc()
    S = S + S.T
    S = S + sp.diags(np.asarray(abs(S).sum(axis=1)).ravel() + 1.0)
    lu = spla.splu(S.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.asarray(lu.perm_c, dtype=np.int64)


def _linear_system(P: Array, ii: NDArray[np.int64], jj: NDArray[np.int64], Z: Array, kappa: Array, tau: Array,
                   dim: int) -> tuple[Array, Array, float]:
    """Per-edge normal-equation block B (M, D, D), gradient b_j (M, D) and the total cost (the residuals are
    those of :func:`slam.graph.costs.chordal_residuals`, inlined to share the gathered poses)."""
    Pi = P[np.maximum(ii, 0)]
    if (ii < 0).any():
        Pi[ii < 0] = np.eye(4)
    Pj = P[jj]
    Ri, ti = Pi[:, :dim, :dim], Pi[:, :dim, 3]
    Rj, tj = Pj[:, :dim, :dim], Pj[:, :dim, 3]
    RiT = np.swapaxes(Ri, 1, 2)
    ER = RiT @ Rj - Z[:, :dim, :dim]
    et = np.einsum("mab,mb->ma", RiT, tj - ti) - Z[:, :dim, 3]
    cost = float(np.sum(kappa * np.einsum("mab,mab->m", ER, ER)) + np.sum(tau * np.einsum("ma,ma->m", et, et)))
    w = np.einsum("mab,mb->ma", Ri, et)  # R_i e_t
    A = -(Ri @ Z[:, :dim, :dim] @ np.swapaxes(Rj, 1, 2))  # I − R_i R̃ R_jᵀ (identity added below)
    m = len(jj)
    if dim == 2:
        st = np.stack([-tj[:, 1], tj[:, 0]], -1)  # S t_j
        B = np.zeros((m, 3, 3))
        B[:, 0, 0] = B[:, 1, 1] = tau
        B[:, :2, 2] = B[:, 2, :2] = tau[:, None] * st
        B[:, 2, 2] = 2.0 * kappa + tau * np.einsum("ma,ma->m", tj, tj)
        g = A[:, 1, 0] - A[:, 0, 1]
        b = np.empty((m, 3))
        b[:, :2] = tau[:, None] * w
        b[:, 2] = tau * np.einsum("ma,ma->m", st, w) + kappa * g
    else:
        K = geo.so3_hat(tj)
        B = np.zeros((m, 6, 6))
        eye = np.eye(3)
        B[:, :3, :3] = tau[:, None, None] * eye
        B[:, :3, 3:] = -tau[:, None, None] * K
        B[:, 3:, :3] = tau[:, None, None] * K
        B[:, 3:, 3:] = 2.0 * kappa[:, None, None] * eye - tau[:, None, None] * (K @ K)
        g = np.stack([A[:, 2, 1] - A[:, 1, 2], A[:, 0, 2] - A[:, 2, 0], A[:, 1, 0] - A[:, 0, 1]], -1)
        b = np.empty((m, 6))
        b[:, :3] = tau[:, None] * w
        b[:, 3:] = tau[:, None] * np.einsum("mab,mb->ma", K, w) + kappa[:, None] * g
    return B, b, cost


def _pcg(H: sp.csc_matrix, rhs: Array, factor, rtol: float, maxiter: int) -> Array | None:  # type: ignore[no-untyped-def]
    """Preconditioned conjugate gradients on ``H x = rhs`` (preconditioner: an earlier factor of a nearby H),
    to relative residual *rtol*; None when *maxiter* iterations do not reach it. Inner products are plain
    numpy reductions (no BLAS call, whose thread start-up dominates for these vector sizes)."""
    x = factor.solve(rhs)
    r = rhs - H @ x
    target2 = rtol * rtol * float((rhs * rhs).sum())
    z = factor.solve(r)
    p = z.copy()
    rz = float((r * z).sum())
    for _ in range(maxiter):
        if float((r * r).sum()) <= target2:
            return x
        Hp = H @ p
        alpha = rz / float((p * Hp).sum())
        x += alpha * p
        r -= alpha * Hp
        z = factor.solve(r)
        rz_new = float((r * z).sum())
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x if float((r * r).sum()) <= target2 else None


def _apply(P: Array, var: NDArray[np.int64], dx: Array, dim: int) -> Array:
    """X_k ← v2t(Δx_k) · X_k for every free node (left, world-frame perturbation)."""
    D = 3 if dim == 2 else 6
    free = var >= 0
    d = dx.reshape(-1, D)[var[free]]
    out = P.copy()
    R = P[free, :dim, :dim]
    t = P[free, :dim, 3]
    if dim == 2:
        dR = geo.rot2(d[:, 2])
        Rn = dR @ R
        tn = np.einsum("mab,mb->ma", dR, t) + d[:, :2]
        out[free] = geo.xytheta_to_matrix(tn[:, 0], tn[:, 1], np.arctan2(Rn[:, 1, 0], Rn[:, 0, 0]))
    else:
        dR = geo.so3_exp(d[:, 3:])
        out[free, :3, :3] = dR @ R
        out[free, :3, 3] = np.einsum("mab,mb->ma", dR, t) + d[:, :3]
    return out


def solve_chordal(
    graph: PoseGraph,
    initial: ArrayLike | None = None,
    *,
    max_iterations: int = 100,
    rel_tol: float = 1e-6,
    damping: float = 0.0,
    linear_solver: str = "splu_mmd",
    block_ordering: bool = True,
    forcing: float = 1e-3,
    max_pcg: int = 10,
    edge_weights: ArrayLike | None = None,
) -> ChordalResult:
    """Minimise the SE-Sync objective by chordal Gauss-Newton from *initial* poses ``(N, 4, 4)``.

    Stops when the relative cost decrease ``(f_k − f_{k+1}) / f_k`` drops below *rel_tol*. *damping* is the
    initial Levenberg λ (0 = pure Gauss-Newton); a step that increases the cost is halved up to six times
    (backtracking line search: −H⁻¹g is a descent direction) and only then damped. After each accepted step the next decrease is predicted from
    the Newton decrement ``½ gᵀH⁻¹g`` with the factor just computed (one triangular solve, no new
    factorisation); the solver also stops when that predicted relative decrease is below *rel_tol*.
    *block_ordering*: a fill-reducing ordering is computed once on the block (node) graph and H is assembled
    directly in that order (the sparsity pattern never changes), so no factorisation recomputes one.
    *forcing* > 0 makes it an inexact Newton method (Dembo, Eisenstat, Steihaug, SIAM J. Numer. Anal. 1982):
    after the first factorisation, a system is solved by conjugate gradients preconditioned with the last
    factor to relative residual *forcing* (at most *max_pcg* iterations; after one failure every later system
    is factorised). A
    preconditioned CG iteration costs two triangular solves, ~1/25-1/35 of a factorisation on city10000 and
    sphere2500, and 1e-3 keeps the Gauss-Newton step count of exact solves there.
    Robust kernels on edges are ignored (the SE-Sync objective
    has none); use the GTSAM back end for robust estimation.
    """
    t0 = time.perf_counter()
    dim = graph.dim
    D = graph.dof
    P = np.array(graph.poses if initial is None else initial, dtype=float)
    if P.shape != (graph.num_nodes, 4, 4) or not np.all(np.isfinite(P)):
        raise GraphError(f"initial poses must be a finite ({graph.num_nodes}, 4, 4) array")
    a = graph.edge_arrays()
    kappa, tau = chordal_weights(graph)
    n_indefinite = len(graph.indefinite_edges())
    if n_indefinite:
        warnings.warn(f"{n_indefinite} edge(s) have an information matrix that is not positive definite; the chordal "
                      "solver uses only their SE-Sync weights κ, τ (Rosen et al. 2019, eq. 14)", stacklevel=2)
    if edge_weights is not None:  # e.g. robust (IRLS / GNC) weights; the reported cost is then weighted too
        w = np.asarray(edge_weights, dtype=float)
        kappa, tau = kappa * w, tau * w
    n = graph.num_nodes
    fixed = np.zeros(n, dtype=bool)
    fixed[graph.anchor_indices()] = True
    var = np.full(n, -1, dtype=np.int64)
    var[~fixed] = np.arange(int((~fixed).sum()))
    ordered = False
    if block_ordering and linear_solver == "splu_mmd" and var.max() >= 0:
        # Order the free nodes once (fill-reducing, on the block graph) and number them in that order, so
        # every H is assembled already permuted and factorised without a new ordering.
        rank = _block_ordering(a.ii, a.jj, var)
        var = np.where(var >= 0, rank[np.maximum(var, 0)], -1)
        ordered = True
    pat = _Pattern(a.ii, a.jj, var, D)
    Z = a.measurements

    B, bj, cost = _linear_system(P, a.ii, a.jj, Z, kappa, tau, dim)
    initial_cost = cost
    history = [cost]
    lam = float(damping)
    converged = False
    factor = None
    use_pcg = True
    it = 0
    while it < max_iterations:
        it += 1
        H = pat.matrix(B)
        g = pat.gradient(bj)
        if lam > 0:
            H = H + sp.diags(lam * H.diagonal(), format="csc")
        dx = None
        if factor is not None and forcing > 0 and use_pcg:
            dx = _pcg(H, -g, factor, forcing, max_pcg)
            use_pcg = dx is not None  # H changes too fast for the old factor: factorise from now on
        if dx is None:
            factor = spd_factor(H, linear_solver, natural=ordered)
            dx = factor.solve(-g)
        Pn = _apply(P, var, dx, dim)
        Bn, bjn, cn = _linear_system(Pn, a.ii, a.jj, Z, kappa, tau, dim)
        step = 1.0
        while cn > cost and cost > 0 and step > 1.0 / 64:  # backtracking along the descent direction −H⁻¹g
            step *= 0.5
            Pn = _apply(P, var, step * dx, dim)
            Bn, bjn, cn = _linear_system(Pn, a.ii, a.jj, Z, kappa, tau, dim)
        if cn > cost and cost > 0:  # still no decrease: increase the damping (Levenberg) and retry
            lam = max(lam * 10.0, 1e-6)
            if lam > 1e8:
                break
            continue
        decrease = (cost - cn) / cost if cost > 0 else 0.0
        P, B, bj, cost = Pn, Bn, bjn, cn
        history.append(cost)
        if lam > 0:
            lam = lam / 10.0 if lam > 1e-12 else 0.0
        if decrease < rel_tol:
            converged = True
            break
        if lam == 0.0 and factor is not None and cost > 0:
            gn = pat.gradient(bj)
            predicted = 0.5 * float(gn @ factor.solve(gn))  # Newton decrement with the previous H
            if predicted / cost < rel_tol:
                converged = True
                break
    return ChordalResult(P, cost, initial_cost, it, time.perf_counter() - t0, converged, history)
