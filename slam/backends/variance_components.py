"""How sure each kind of edge really is, read from the pose graph's own redundancy (variance components).

A pose graph weighs its edges by covariances that come from models: the registration's Fisher information
plus floors, the wheels' noise model, the loop verifier's ICP covariance plus its floor. The floors are
set so that no log of the development set is made overconfident, so on most logs they are too wide, and by
how much differs by sensor: on a sharp laser the registration's heading variance is several times smaller than
its floor says, and the wheels beside it then hold the heading where they should not (docs/LOOP_CLOSURE.md,
"How sure the edges are").

Once loops are closed the graph holds more measurements than unknowns, and the residuals of the solution
say how large each group's errors are. That is variance-component estimation (Helmert 1907; the iterative
estimator of Förstner, "Ein Verfahren zur Schätzung von Varianz- und Kovarianzkomponenten", AVN 86, 1979;
Koch, *Parameter Estimation and Hypothesis Testing in Linear Models*, 1999, §3.6; as least squares,
Teunissen & Amiri-Simkooei, J. Geodesy 82, 2008). Each edge of group g has the covariance
``Σ_e = s_{g,t} Q⁰_{t,e} + s_{g,r} Q⁰_{r,e}``, its translation and rotation components (below) scaled by the
group's factors; at the least-squares solution with residuals v_e, each component k = (g, block) is updated as

    s_k ← s_k · q_k / r_k,   q_k = Σ_e v_eᵀ M_{k,e} v_e,   r_k = Σ_e dim_k − tr(Σ_x B_k),

with M_{k,e} = Λ_e Q_{k,e} Λ_e (Q_{k,e} the block's component of Σ_e, Λ_e = Σ_e⁻¹), B_k = Σ_e J_eᵀ M_{k,e} J_e,
Σ_x the solution's covariance and J_e the edge's Jacobian: q_k is the block's share of the residuals' χ² and
r_k its share of the redundancy (Σ_k q_k and Σ_k r_k are the χ² and the redundancy of the whole graph).
The blocks of a covariance are correlated (a heading error moves the far end by its lever arm), so the
components are its rotation block with the translation that rotation carries, and the translation left
(``Σ_e = L diag(A, B) Lᵀ``, :func:`covariance_components`): each is positive semi-definite, and scaling one
leaves the other. In the rows that whiten them, q_k is the sum of the rows' squared residuals and r_k the
sum of one minus each row's leverage (the diagonal of the hat matrix ``J_w H⁻¹ J_wᵀ``). The leverages are
estimated with Rademacher probes over the rows (Hutchinson, Commun. Stat. Simul. Comput. 19, 1990; the
diagonal estimator of Bekas, Kokiopoulou & Saad, Appl. Numer. Math. 57, 2007) from one factorisation of the
normal matrix H per iteration; probes over the poses would be far noisier, as the poses' own covariance grows
along a chain while the hat matrix is a projection. The same factorisation gives the Gauss-Newton step of
that iteration, so the solution follows the scales.

Every edge counts as Gaussian here, robust kernels or not: under a redescending kernel (the closures'
Cauchy at one σ) a component's weighted χ² is bounded whatever its scale, and the estimate runs to zero.
It is meant for the closures the final solve kept (the pruning drops those the solution violates). A
component whose redundancy is below ``MIN_REDUNDANCY`` keeps its scale: the estimate's relative standard
deviation is √(2 / r), and a graph with a handful of closures says too little about its edges. Planar
(x, y, θ) and 3D (ρ, φ) graphs; the tangent order is translation first, right perturbations
(docs/ARCHITECTURE.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from core import geometry as G
from slam.graph.posegraph import PRIOR_NODE, PoseGraph

from .linsolve import spd_factor

Array = NDArray[np.float64]

__all__ = ["VarianceComponents", "estimate_variance_components", "scaled_graph", "MIN_REDUNDANCY"]

#: Fewest redundant observations a component is estimated from (relative σ of the estimate √(2/20) ≈ 32 %).
MIN_REDUNDANCY = 20.0
#: Scales are kept within these bounds (numerical safety: a component whose residuals vanish would run to 0).
SCALE_BOUNDS = (1e-3, 1e3)
BLOCKS = ("translation", "rotation")


@dataclass(frozen=True)
class VarianceComponents:
    """The estimated scales of each (group, block)'s variance, and what they were estimated from.

    Attributes:
        scales: ``{(group, "translation" | "rotation"): factor}`` on that block's variance (1: as modelled).
        redundancy: the component's redundancy at the last iteration (its share of observations − unknowns).
        chi2: the component's share of the residuals' χ² at the last iteration.
        iterations: iterations run; converged: the largest change of a scale in the last one was below the tolerance.
        poses: ``(N, 4, 4)`` the Gauss-Newton solution under the final scales.
    """

    scales: dict[tuple[str, str], float]
    redundancy: dict[tuple[str, str], float]
    chi2: dict[tuple[str, str], float]
    iterations: int
    converged: bool
    poses: Array

    def as_dict(self) -> dict:
        """``{group: {block: {"scale", "redundancy", "chi2"}}, "iterations", "converged"}`` for summary.json."""
        out: dict = {}
        for (g, b), s in self.scales.items():
            out.setdefault(g, {})[b] = {"scale": float(s), "redundancy": float(self.redundancy[(g, b)]),
                                        "chi2": float(self.chi2[(g, b)])}
        return {"groups": out, "iterations": self.iterations, "converged": self.converged}


def _adjoints(T: Array, planar: bool) -> Array:
    """``(M, d, d)`` adjoints of the poses *T* ``(M, 4, 4)`` (:func:`core.geometry.adjoint`, stacked)."""
    M = len(T)
    R, t = T[:, :3, :3], T[:, :3, 3]
    if planar:
        A = np.zeros((M, 3, 3))
        A[:, :2, :2] = R[:, :2, :2]
        A[:, 0, 2], A[:, 1, 2], A[:, 2, 2] = t[:, 1], -t[:, 0], 1.0
        return A
    A = np.zeros((M, 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    hat = np.zeros((M, 3, 3))
    hat[:, 0, 1], hat[:, 0, 2], hat[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    hat[:, 1, 0], hat[:, 2, 0], hat[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    A[:, :3, 3:] = hat @ R
    return A


def _log(T: Array, planar: bool) -> Array:
    return G.se2_log(T) if planar else G.se3_log(T)


def _exp(xi: Array, planar: bool) -> Array:
    return G.se2_exp(xi) if planar else G.se3_exp(xi)


def covariance_components(information: Array, nt: int) -> tuple[Array, Array, Array]:
    """Each covariance Σ = inv(information) as ``L diag(A, B) Lᵀ``, ``L = [[I, C], [0, I]]``: B the rotation
    block, C = Σ_tr B⁻¹ the translation a heading error carries (the lever arm), A = Σ_tt − C Σ_rt the
    translation that is the translation's own. Returns ``(C, A⁻¹, B⁻¹)``; the two components ``L diag(A, 0) Lᵀ``
    and ``L diag(0, B) Lᵀ`` are each positive semi-definite and sum to Σ."""
    S = np.linalg.inv(information)
    Stt, Str, Srr = S[:, :nt, :nt], S[:, :nt, nt:], S[:, nt:, nt:]
    C = Str @ np.linalg.inv(Srr)
    A = Stt - C @ np.swapaxes(Str, 1, 2)
    return C, np.linalg.inv(A), np.linalg.inv(Srr)


def _whitening(C: Array, A_inv: Array, B_inv: Array) -> Array:
    """``(M, d, d)`` square roots S of the information, ``SᵀS = (L diag(A, B) Lᵀ)⁻¹``
    (:func:`covariance_components`): ``S = diag(chol(A⁻¹)ᵀ, chol(B⁻¹)ᵀ) L⁻¹``, so that the first rows of S v
    whiten the translation's own part and the last the rotation's."""
    M, nt, nr = C.shape
    Linv = np.tile(np.eye(nt + nr), (M, 1, 1))
    Linv[:, :nt, nt:] = -C
    D = np.zeros((M, nt + nr, nt + nr))
    D[:, :nt, :nt] = np.swapaxes(np.linalg.cholesky(A_inv), 1, 2)
    D[:, nt:, nt:] = np.swapaxes(np.linalg.cholesky(B_inv), 1, 2)
    return D @ Linv


def _jacobian(j_T_i: Array, ii: NDArray[np.int64], jj: NDArray[np.int64], prior: NDArray[np.bool_], planar: bool,
              n_var: int) -> sp.csr_matrix:
    """Sparse ``(M·d, n_var)`` Jacobian of the edges' residuals, first order: ∂v/∂δ_j = I, ∂v/∂δ_i = −Ad(T_j⁻¹ T_i)
    (none for a prior); node 0 is the gauge and has no columns."""
    M = len(jj)
    Ji = -_adjoints(j_T_i, planar)
    d = Ji.shape[1]
    rows = np.arange(M * d).reshape(M, d)
    r, c, val = [], [], []
    for nodes, Jn, use in ((jj, np.broadcast_to(np.eye(d), (M, d, d)), np.ones(M, bool)), (ii, Ji, ~prior)):
        keep = use & (nodes > 0)
        cols = (nodes[keep] - 1)[:, None] * d + np.arange(d)[None, :]
        r.append(np.repeat(rows[keep][:, :, None], d, axis=2).ravel())
        c.append(np.repeat(cols[:, None, :], d, axis=1).ravel())
        val.append(Jn[keep].ravel())
    return sp.csr_matrix((np.concatenate(val), (np.concatenate(r), np.concatenate(c))), shape=(M * d, n_var))


def estimate_variance_components(graph: PoseGraph, poses: Array, groups: Sequence[str], *, max_iterations: int = 30,
                                 tolerance: float = 0.01, probes: int = 32, seed: int = 0) -> VarianceComponents:
    """Scales of each edge group's translation and rotation variance that make the residuals of the graph's
    solution match their redundancy (module docstring), starting at the solution *poses* ``(N, 4, 4)``.

    *groups*: a label per edge of *graph* (e.g. ``"registration"``, ``"wheel"``, ``"loop"``). Edges to
    :data:`~slam.graph.posegraph.PRIOR_NODE` count as measured against the world. The first node is held
    fixed (the gauge), as the batch solve holds it. Raises ``numpy.linalg.LinAlgError`` for an information
    matrix that is not positive definite.
    """
    a = graph.edge_arrays()
    planar = graph.dim == 2
    d = graph.dof
    nt = 2 if planar else 3
    M, N = len(a.ii), graph.num_nodes
    if len(groups) != M:
        raise ValueError(f"{len(groups)} group labels for {M} edges")
    names = sorted(set(groups))
    comps = [(g, b) for g in names for b in BLOCKS]
    gid = np.array([names.index(g) for g in groups], dtype=np.int64)
    comp_t, comp_r = 2 * gid, 2 * gid + 1
    C, A_inv, B_inv = covariance_components(a.information, nt)
    scale = np.ones(len(comps))
    P = np.array(poses, dtype=float)
    prior = a.ii == PRIOR_NODE
    ii = np.where(prior, 0, a.ii)
    rng = np.random.default_rng(seed)
    n_var = (N - 1) * d
    comp_rows = np.concatenate([np.repeat(comp_t[:, None], nt, 1), np.repeat(comp_r[:, None], d - nt, 1)], 1).ravel()
    q = r = np.zeros(len(comps))
    converged, it = False, 0
    for it in range(1, max_iterations + 1):
        S = _whitening(C, A_inv / scale[comp_t][:, None, None], B_inv / scale[comp_r][:, None, None])
        Ti = np.where(prior[:, None, None], np.eye(4), P[ii])
        Tj = P[a.jj]
        v = _log(G.inverse(a.measurements) @ G.inverse(Ti) @ Tj, planar)  # (M, d)
        Jw = sp.block_diag(list(S), format="csr") @ _jacobian(G.inverse(Tj) @ Ti, ii, a.jj, prior, planar, n_var)
        factor = spd_factor((Jw.T @ Jw).tocsc())
        # Gauss-Newton step under these scales; the whitened residuals of the linearised solution.
        vw = np.einsum("mij,mj->mi", S, v).ravel()
        dx = -factor.solve(Jw.T @ vw)
        vw = vw + Jw @ dx
        P = P @ _exp(np.vstack([np.zeros((1, d)), dx.reshape(N - 1, d)]), planar)
        # Each component's share of the χ² (its whitened rows' squares) and of the redundancy (one minus each
        # row's leverage, the diagonal of Jw H⁻¹ Jwᵀ, from the probes; module docstring).
        Z = rng.choice([-1.0, 1.0], size=(M * d, probes))
        lev = np.mean(Z * (Jw @ factor.solve(Jw.T @ Z)), axis=1)
        q = np.bincount(comp_rows, vw**2, minlength=len(comps))
        r = np.bincount(comp_rows, 1.0 - lev, minlength=len(comps))
        new = np.where(r >= MIN_REDUNDANCY, scale * q / np.maximum(r, 1e-12), scale)
        new = np.clip(new, *SCALE_BOUNDS)
        change = float(np.max(np.abs(np.log(new / scale))))
        scale = new
        if change < tolerance:
            converged = True
            break
    return VarianceComponents({c: float(x) for c, x in zip(comps, scale)},
                              {c: float(x) for c, x in zip(comps, r)}, {c: float(x) for c, x in zip(comps, q)},
                              it, converged, P)


def scaled_graph(graph: PoseGraph, groups: Sequence[str], scales: dict[tuple[str, str], float]) -> PoseGraph:
    """A copy of *graph* whose edges carry their group's scales: each covariance's own translation part and its
    rotation part (with the translation that part carries, :func:`covariance_components`) multiplied by the
    group's factors (a missing one is 1); nodes, poses, kernels and everything else as they were."""
    nt = 2 if graph.dim == 2 else 3
    a = graph.edge_arrays()
    C, A_inv, B_inv = covariance_components(a.information, nt) if len(a.ii) else (None, None, None)
    out = PoseGraph(graph.dim)
    for nid, T in zip(graph.node_ids, graph.poses):
        out.add_node(int(nid), T)
    for e, (g, edge) in enumerate(zip(groups, graph.edges())):
        st, sr = scales.get((g, "translation"), 1.0), scales.get((g, "rotation"), 1.0)
        S = _whitening(C[e:e + 1], A_inv[e:e + 1] / st, B_inv[e:e + 1] / sr)[0]
        info = S.T @ S
        out.add_edge(edge.i, edge.j, edge.measurement, info, edge.kind, edge.kernel)
    out.fixed_ids = list(graph.fixed_ids)
    return out
