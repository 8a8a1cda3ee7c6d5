"""SVD-ICP in 2D and 3D (Besl & McKay 1992), with covariance and the residual χ² test.

Each iteration matches every (subsampled) source point to its nearest target point with a
kd-tree built once on the target (scipy ``cKDTree``), drops pairs beyond the correspondence gate,
weights the rest (trimmed or robust), and solves the closed-form alignment of
:func:`registration.align.align_svd` (Arun 1987 / Umeyama 1991) from the *original* source
points, so the result is ``target_T_source`` directly. A stage ends when the pose increment is
below ``tol_translation`` / ``tol_rotation``; gates run coarse to fine; ``max_iterations`` caps
the total. At the fixed point the covariance ``σ² (∂²f/∂δ²)⁻¹`` and the χ² verdict are computed
(:mod:`registration.covariance`).

With ``alignment.COMPILED_2D`` / ``COMPILED_3D`` (robust none / Huber / Cauchy) the same iterations run compiled on
a grid of the target (:mod:`registration.kernels_icp`, :mod:`registration.kernels_icp3d_point`); the numpy loop
below stays as the reference the tests compare them with (trimming runs it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.errors import DegenerateInputError

from . import alignment
from .alignment import IcpResult, as_target, evaluate_matches, prepare, robust_weights
from .config import IcpConfig
from .matching import INCREMENTAL_MIN_POINTS, IncrementalMatcher, pair_distances
from .target import IcpTarget

Array = NDArray[np.float64]

__all__ = ["icp", "pose_increment"]


def pose_increment(A: Array, B: Array) -> tuple[float, float]:
    """(translation m, rotation rad) of ``A⁻¹ B``."""
    D = np.linalg.solve(A, B)
    c = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(D[:3, 3])), float(np.arccos(c))


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
    tgt = as_target(target, config)
    S, T = prepare(source, tgt, init, config)
    d, n = tgt.dim, len(S)
    if d == 2 and alignment.COMPILED_2D and config.robust in alignment.ROBUST_CODES:
        return _icp_2d_compiled(S, tgt, T, config)
    if d == 3 and alignment.COMPILED_3D and config.robust in alignment.ROBUST_CODES:
        return _icp_3d_compiled(S, tgt, T, config)
    tpts = tgt.points
    n_tgt = len(tpts)
    # The matches are searched again only where the motion since the last search could change them.
    matcher = IncrementalMatcher(tgt.tree, config.workers, incremental=n >= INCREMENTAL_MIN_POINTS)
    robust = config.robust != "none"
    tol_t, tol_r = config.tol_translation_m, config.tol_rotation_rad
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
    for gate in config.gates_m:
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
    gate = config.gates_m[-1]
    return evaluate_matches(S, tgt, T, moved, matcher.match(moved, gate), gate, config, it, converged)


def _repeat_is_fixed_point(config: IcpConfig) -> bool:
    """Unweighted steps to a positive tolerance: the same matches twice mean the same pose (the fixed-point test)."""
    return config.robust == "none" and config.tol_translation_m > 0 and config.tol_rotation_rad > 0


def _icp_2d_compiled(S: Array, tgt: IcpTarget, T: Array, config: IcpConfig) -> IcpResult:
    """The 2D iterations of :func:`icp`, compiled (:func:`registration.kernels_icp.point_icp_2d`) on the target's
    grid index, then the same evaluation."""
    from . import kernels_icp

    g = tgt.grid
    R, t, it, converged, status, stage, matches, pairs = kernels_icp.point_icp_2d(
        *alignment.compiled_loop_args(S, T, config, 2), _repeat_is_fixed_point(config), g.points, *g.args())
    _refuse(status, it, pairs, stage, config)
    matches[matches < 0] = len(tgt.points)  # unmatched, as cKDTree reports it
    return _evaluated(S, tgt, R, t, matches, config, it, converged)


def _icp_3d_compiled(S: Array, tgt: IcpTarget, T: Array, config: IcpConfig) -> IcpResult:
    """The 3D iterations of :func:`icp`, compiled (:func:`registration.kernels_icp3d_point.point_icp_3d`: the same
    nearest neighbours on the target's cell grid instead of its k-d tree), then the same evaluation."""
    from . import kernels_icp3d_point

    g = tgt.grid3
    R, t, it, converged, status, stage, pairs, matches = kernels_icp3d_point.point_icp_3d(
        *alignment.compiled_loop_args(S, T, config, 3), _repeat_is_fixed_point(config), g.points, *g.args())
    _refuse(status, it, pairs, stage, config)
    if config.covariance_model == "plane":  # the evaluation's normals, from the same grid (no k-d tree to build)
        from .kernels_grid3d import normals_3d

        normals_3d(matches[matches < len(g.points)], tgt._normals, tgt._have, g.points, *g.args(),
                   min(tgt.normal_neighbors, len(g.points)))
    return _evaluated(S, tgt, R, t, matches, config, it, converged)


def _refuse(status: int, it: int, pairs: int, stage: int, config: IcpConfig) -> None:
    """The numpy loop's errors for a compiled loop's *status* (1: too few pairs, 3: every weight zero)."""
    if status == 1:
        raise DegenerateInputError(f"ICP iteration {it}: {pairs} pairs within {config.gates_m[stage]} m "
                                   f"(need {config.min_inliers})")
    if status == 3:
        raise DegenerateInputError("all correspondence weights are zero")


def _evaluated(S: Array, tgt: IcpTarget, R: Array, t: Array, matches: NDArray[np.intp], config: IcpConfig, it: int,
               converged: bool) -> IcpResult:
    """A compiled loop's pose (*R*, *t*) and final *matches* through the numpy loop's evaluation."""
    d = len(t)
    T = np.eye(4)
    T[:d, :d], T[:d, 3] = R, t
    return evaluate_matches(S, tgt, T, S @ R.T + t, matches, config.gates_m[-1], config, it, converged)
