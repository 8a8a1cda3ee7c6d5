"""SVD-ICP in 2D and 3D (Besl & McKay 1992), with covariance and the residual χ² test.

Each iteration matches every (subsampled) source point to its nearest target point with a
kd-tree built once on the target (scipy ``cKDTree``), drops pairs beyond the correspondence gate,
weights the rest (trimmed or robust), and solves the closed-form alignment of
:func:`registration.align.align_svd` (Arun 1987 / Umeyama 1991) from the *original* source
points, so the result is ``target_T_source`` directly. A stage ends when the pose increment is
below ``tol_translation`` / ``tol_rotation``; gates run coarse to fine; ``max_iterations`` caps
the total. At the fixed point the covariance ``σ² (∂²f/∂δ²)⁻¹`` and the χ² verdict are computed
(:mod:`registration.covariance`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from .config import IcpConfig
from .covariance import (Chi2Verdict, chi2_test, covariance_from_information, fisher_information,
                         jacobian_plane, jacobian_point)
from .errors import DegenerateInputError, GeometryError
from .matching import INCREMENTAL_MIN_POINTS, IncrementalMatcher, pair_distances
from .voxel import voxel_downsample

Array = NDArray[np.float64]

__all__ = ["IcpTarget", "IcpResult", "icp", "evaluate_alignment", "robust_weights", "pose_increment"]


class IcpTarget:
    """A target point set prepared once for many alignments: subsampled points, kd-tree and
    (lazily) PCA normals. Points ``(N, d)`` in the target frame, metres."""

    def __init__(self, points: ArrayLike, voxel_size: float | None = None, normal_neighbors: int = 10,
                 workers: int = -1) -> None:
        P = np.asarray(points, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] not in (2, 3):
            raise GeometryError(f"target points must be (N, 2) or (N, 3), got shape {P.shape}")
        self.points = voxel_downsample(P, voxel_size, mode="centroid") if voxel_size else P
        if len(self.points) < 3:
            raise DegenerateInputError(f"target has {len(self.points)} points; ICP needs at least 3")
        self.dim = self.points.shape[1]
        self._tree: cKDTree | None = None
        self._grid = None
        self.normal_neighbors = normal_neighbors
        self.workers = workers
        # Normals are computed on demand, point by point, and kept: an alignment needs them only at
        # the target points it matches (a scan against a ten-scan local map: about a tenth). The
        # compiled 2D ICP (point_to_plane._icp_plane_2d_compiled) fills these two arrays in place.
        self._normals = np.empty((len(self.points), self.dim))  # C order: the compiled kernels' layout
        self._have = np.zeros(len(self.points), dtype=bool)
        self._have_all = False

    @property
    def tree(self) -> cKDTree:
        """k-d tree of the points (built on first use: compiled 2D alignments search :attr:`grid`)."""
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    @property
    def grid(self):
        """2D only: the uniform-grid index of the compiled kernels (:class:`registration.kernels.PointGrid`)."""
        if self._grid is None:
            from .kernels import PointGrid

            self._grid = PointGrid(self.points)
        return self._grid

    def normals(self, index: NDArray[np.intp] | None = None) -> Array:
        """Unit PCA normals (smallest-eigenvalue eigenvector of the k-neighbour scatter) of the
        target points *index* (all when None), computed once per point."""
        from .point_to_plane import estimate_normals

        if self.dim == 2:  # compiled grid search, one point at a time (same estimator)
            from .kernels import normals_2d

            g = self.grid
            want = np.arange(len(self.points)) if index is None else np.asarray(index, dtype=np.int64)
            normals_2d(want, self._normals, self._have, g.points, *g.args(), min(self.normal_neighbors, len(self.points)))
            return self._normals if index is None else self._normals.take(index, axis=0)
        if index is None:
            if not self._have_all:
                missing = np.flatnonzero(~self._have)
                self._normals[missing] = estimate_normals(self.points[missing], self.tree, self.normal_neighbors, self.workers)
                self._have[:] = self._have_all = True
            return self._normals
        if not self._have_all:
            missing = index[~self._have[index]]
            if len(missing):
                missing = np.unique(missing)
                self._normals[missing] = estimate_normals(self.points[missing], self.tree, self.normal_neighbors, self.workers)
                self._have[missing] = True
        return self._normals.take(index, axis=0)


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
    k = config.robust_scale
    if config.robust == "huber":
        return np.minimum(1.0, k / np.maximum(dist, 1e-300))
    return 1.0 / (1.0 + (dist / k) ** 2)


def pose_increment(A: Array, B: Array) -> tuple[float, float]:
    """(translation m, rotation rad) of ``A⁻¹ B``."""
    D = np.linalg.solve(A, B)
    c = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(D[:3, 3])), float(np.arccos(c))


# Below this many queries scipy's thread start/join costs more than the parallel search saves.
_PARALLEL_MIN_QUERIES = 20000


def _workers(n: int, workers: int) -> int:
    """cKDTree ``workers`` for *n* queries: one thread for small batches."""
    return workers if n >= _PARALLEL_MIN_QUERIES else 1


def _svd_step(P: Array, Q: Array, w: Array | None, Pc: Array | None = None,
              pm: Array | None = None) -> tuple[Array, Array]:
    """Inner-loop form of :func:`registration.align.align_svd` (same equations, no input checks;
    degenerate pairs are caught by the checks of the final evaluation): ``(R, t)``.

    Unweighted, the centred source ``Pc = P − pm`` may be passed in: ICP matches the same source
    points every iteration, so only the target side changes (Arun 1987).
    In 2D the maximiser of tr(R H) is closed form, θ = atan2(H01 − H10, H00 + H11)."""
    n = len(P)
    if w is None:
        if Pc is None:
            pm = P.sum(axis=0) / n  # bit-identical to P.mean(axis=0), with less overhead
            Pc = P - pm
        qm = Q.sum(axis=0) / n
        H = Pc.T @ (Q - qm)
    else:
        sw = w.sum()
        if sw <= 0:
            raise DegenerateInputError("all correspondence weights are zero")
        pm, qm = (w @ P) / sw, (w @ Q) / sw
        H = (P - pm).T @ ((Q - qm) * w[:, None])
    if P.shape[1] == 2:
        (h00, h01), (h10, h11) = H.tolist()
        th = math.atan2(h01 - h10, h00 + h11)
        c, s = math.cos(th), math.sin(th)
        (p0, p1), (q0, q1) = pm.tolist(), qm.tolist()
        return np.array(((c, -s), (s, c))), np.array((q0 - (c * p0 - s * p1), q1 - (s * p0 + c * p1)))
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T
    if np.linalg.det(V @ U.T) < 0:
        V[:, -1] = -V[:, -1]
    R = V @ U.T
    return R, qm - R @ pm


def _as_target(target: ArrayLike | IcpTarget, config: IcpConfig) -> IcpTarget:
    if isinstance(target, IcpTarget):
        return target
    return IcpTarget(target, config.target_voxel_size, config.normal_neighbors, config.workers)


def _prepare(source: ArrayLike, tgt: IcpTarget, init: ArrayLike | None, config: IcpConfig) -> tuple[Array, Array]:
    S = np.asarray(source, dtype=np.float64)
    if S.ndim != 2 or S.shape[1] != tgt.dim:
        raise GeometryError(f"source must be (N, {tgt.dim}) like the target, got shape {S.shape}")
    if config.voxel_size:
        S = voxel_downsample(S, config.voxel_size)
    if len(S) < 3:
        raise DegenerateInputError(f"source has {len(S)} points; ICP needs at least 3")
    T = np.eye(4) if init is None else np.array(init, dtype=np.float64)
    if T.shape != (4, 4):
        raise GeometryError(f"initial guess must be a 4×4 pose, got shape {T.shape}")
    return S, T


def gated_nearest(tgt: IcpTarget, points: Array, gate: float, workers: int = 1) -> NDArray[np.intp]:
    """Index of the target point nearest to each row of *points*, strictly within *gate* (m), else
    ``len(tgt.points)`` (as cKDTree reports a miss): the compiled grid search in 2D, the k-d tree in 3D."""
    if tgt.dim == 2:
        from .kernels import nearest_within

        g = tgt.grid
        idx = nearest_within(np.ascontiguousarray(points, dtype=np.float64), g.points, *g.args(), float(gate))
        idx[idx < 0] = len(tgt.points)
        return idx
    return tgt.tree.query(points, k=1, distance_upper_bound=gate, workers=_workers(len(points), workers))[1]


def evaluate_alignment(S: Array, tgt: IcpTarget, T: Array, gate: float, config: IcpConfig, iterations: int = 0,
                       converged: bool = True) -> IcpResult:
    """Correspondences at *gate*, RMSE, covariance and χ² test of a given pose ``T = target_T_source``.

    Used at the end of every ICP, and to attach a covariance to poses found by another
    registration (KISS-ICP). *S* is ``(N, d)`` in the source frame (m)."""
    d = tgt.dim
    moved = S @ T[:d, :d].T + T[:d, 3]
    idx = gated_nearest(tgt, moved, gate, config.workers)
    return _evaluate(S, tgt, T, moved, idx, gate, config, iterations, converged)


def _evaluate(S: Array, tgt: IcpTarget, T: Array, moved: Array, idx: NDArray[np.intp], gate: float,
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
    verdict = chi2_test(res, n_res, dof, None if config.sigma is None else config.sigma**2,
                        config.chi2_factor, config.false_rejection_rate)
    cov, degenerate = covariance_from_information(fisher_information(J, w), verdict.sigma2)
    rmse = math.sqrt(float(np.vdot(diff, diff)) / len(diff))
    return IcpResult(T, rmse, int(len(src)), len(src) / len(S), iterations, converged, res, n_res, dof,
                     cov, degenerate, verdict)


def icp(source: ArrayLike, target: ArrayLike | IcpTarget, init: ArrayLike | None = None,
        config: IcpConfig | None = None) -> IcpResult:
    """Point-to-point SVD-ICP of *source* onto *target* (Besl & McKay 1992).

    Args:
        source: ``(N, d)`` points in the source frame (m).
        target: ``(M, d)`` points in the target frame, or a prepared :class:`IcpTarget`.
        init: initial guess of ``target_T_source`` (4×4); identity when None.
        config: :class:`IcpConfig` (gates, subsampling, robust weights, tolerances, σ).

    Returns:
        :class:`IcpResult` with ``transform = target_T_source``.

    Raises:
        DegenerateInputError: too few points or too few pairs within the gate.
    """
    config = config or IcpConfig()
    tgt = _as_target(target, config)
    S, T = _prepare(source, tgt, init, config)
    d, n = tgt.dim, len(S)
    from . import point_to_plane as p2l  # the switch of both compiled 2D loops

    if d == 2 and p2l.COMPILED_2D and config.robust in p2l._ROBUST_CODES:
        return _icp_2d_compiled(S, tgt, T, config)
    tpts = tgt.points
    n_tgt = len(tpts)
    # The matches are searched again only where the motion since the last search could change them.
    matcher = IncrementalMatcher(tgt.tree, config.workers, incremental=n >= INCREMENTAL_MIN_POINTS)
    robust = config.robust != "none"
    tol_t, tol_r = config.tol_translation, config.tol_rotation
    # Unweighted, the closed-form step from the same correspondences returns the same pose: matches
    # that repeat those the current pose was solved from are the fixed point (the increment would be
    # exactly 0), and they are also the final evaluation's.
    repeat_is_fixed_point = not robust and tol_t > 0 and tol_r > 0
    pm_all = S.sum(axis=0) / n
    Sc_all = S - pm_all
    R, t = T[:d, :d].copy(), T[:d, 3].copy()
    th = math.atan2(R[1, 0], R[0, 0]) if d == 2 else 0.0
    solved_from = None  # correspondences (idx, unmatched = n_tgt) the current pose was solved from
    moved = None  # the source moved by the current pose, when already computed
    it = 0
    converged = False
    for gate in config.gates:
        converged = False
        while it < config.max_iterations:
            it += 1
            moved = S @ R.T + t
            idx = matcher.match(moved, gate)
            if repeat_is_fixed_point and solved_from is not None and np.array_equal(idx, solved_from):
                converged = True
                break
            if idx[-1] < n_tgt and idx.max() < n_tgt:  # every point matched: no mask copies
                P, Pc, pm, mv, Q = S, Sc_all, pm_all, moved, tpts.take(idx, axis=0)
            else:
                ok = idx < n_tgt
                n_ok = int(np.count_nonzero(ok))
                if n_ok < config.min_inliers:
                    raise DegenerateInputError(
                        f"ICP iteration {it}: {n_ok} pairs within {gate} m (need {config.min_inliers})")
                P, Pc, pm, mv, Q = S[ok], None, None, moved[ok], tpts.take(idx[ok], axis=0)
            R_new, t_new = _svd_step(P, Q, robust_weights(pair_distances(mv, Q), config) if robust else None, Pc, pm)
            if d == 2:
                th_new = math.atan2(R_new[1, 0], R_new[0, 0])
                dt = math.hypot(*(t_new - t).tolist())
                dr = abs(th_new - th)
                dr = min(dr, 2.0 * math.pi - dr)
                th = th_new
            else:
                dt = float(np.linalg.norm(t_new - t))
                dr = float(np.linalg.norm(R_new - R)) / math.sqrt(2.0)  # = 2 sin(α/2) ≈ α, no √ε floor
            R, t = R_new, t_new
            solved_from, moved = idx, None
            if dt < tol_t and dr < tol_r:
                converged = True
                break
    T = np.eye(4)
    T[:d, :d], T[:d, 3] = R, t
    if moved is None:
        moved = S @ R.T + t
    gate = config.gates[-1]
    return _evaluate(S, tgt, T, moved, matcher.match(moved, gate), gate, config, it, converged)


def _icp_2d_compiled(S: Array, tgt: IcpTarget, T: Array, config: IcpConfig) -> IcpResult:
    """The 2D iterations of :func:`icp`, compiled (:func:`registration.kernels.point_icp_2d`) on the target's
    grid index, then the same evaluation."""
    from . import kernels
    from .point_to_plane import _ROBUST_CODES

    g = tgt.grid
    repeat_is_fixed_point = config.robust == "none" and config.tol_translation > 0 and config.tol_rotation > 0
    R, t, it, converged, status, stage, matches, pairs = kernels.point_icp_2d(
        np.ascontiguousarray(S), T[:2, :2].copy(), T[:2, 3].copy(), np.asarray(config.gates, dtype=np.float64),
        config.max_iterations, config.tol_translation, config.tol_rotation, _ROBUST_CODES[config.robust],
        config.robust_scale, config.min_inliers, repeat_is_fixed_point, g.points, *g.args())
    if status == 1:
        raise DegenerateInputError(f"ICP iteration {it}: {pairs} pairs within {config.gates[stage]} m "
                                   f"(need {config.min_inliers})")
    if status == 3:
        raise DegenerateInputError("all correspondence weights are zero")
    T = np.eye(4)
    T[:2, :2], T[:2, 3] = R, t
    matches[matches < 0] = len(tgt.points)  # unmatched, as cKDTree reports it
    gate = config.gates[-1]
    return _evaluate(S, tgt, T, S @ R.T + t, matches, gate, config, it, converged)
