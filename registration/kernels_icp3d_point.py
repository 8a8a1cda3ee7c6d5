"""Compiled (numba) 3D point-to-point SVD-ICP (Besl & McKay 1992; the closed-form step of Arun et al. 1987 /
Umeyama 1991) on the cell grid of :mod:`registration.kernels_grid3d`, with the cached matching of
:mod:`registration.kernels_icp3d`: the loop form of ``registration.icp.icp`` in 3D, which stays as its reference
(tests check that both agree).

It exists because the numpy loop spends most of a LiDAR pair's time (~20k source points, 30–100 iterations to the
fixed point) in per-iteration array passes and k-d tree calls; here a converging iteration costs about one
squared distance per point (the match slack of kernels_icp3d) plus the two passes of the centroids and the
cross-covariance.

Frames: every argument is in one frame (the target's); metres and radians.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .kernels import same_matches
from .kernels_icp3d import CACHED, cell_order, match_pass, matcher_arrays, regate, unsort

__all__ = ["point_icp_3d"]


@njit(cache=True)
def _rotation(H):  # pragma: no cover - compiled
    """The rotation R maximising tr(R H) (Arun et al. 1987, with Umeyama's reflection fix), as
    registration.icp._svd_step: V Uᵀ from H = U Σ Vᵀ, the last column of V negated when det(V Uᵀ) < 0."""
    U, _, Vt = np.linalg.svd(H)
    R = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            R[i, j] = Vt[0, i] * U[j, 0] + Vt[1, i] * U[j, 1] + Vt[2, i] * U[j, 2]
    det = (R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]) - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
           + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]))
    if det < 0.0:
        for i in range(3):
            for j in range(3):
                R[i, j] = Vt[0, i] * U[j, 0] + Vt[1, i] * U[j, 1] - Vt[2, i] * U[j, 2]
    return R


@njit(cache=True)
def point_icp_3d(S, R, t, gates, max_iterations, tol_t, tol_r, robust, scale, min_inliers, repeat_is_fixed_point,
                 pts, cpts, origin, cell, dims, starts, order):  # pragma: no cover - compiled
    """Point-to-point SVD-ICP iterations of ``registration.icp.icp`` in 3D, source ``S (N, 3)`` from ``(R, t)``;
    *robust* 0 = none, 1 = Huber, 2 = Cauchy on the pair distance with *scale*. With *repeat_is_fixed_point* an
    iteration whose matches repeat those the pose was solved from ends the stage (the step would be exactly 0).
    Returns (R, t, iterations, converged, status, stage, pairs, matches): status 0 = done, *matches* the nearest
    target point strictly within the last gate of each source point at the final pose (len(pts): none); 1 = fewer
    than *min_inliers* pairs (*pairs*) within ``gates[stage]`` at iteration *iterations*; 3 = every
    correspondence weight zero."""
    n_tgt = pts.shape[0]
    perm = cell_order(S, R, t, origin, cell, dims)  # consecutive points search the same cells
    S = S[perm]
    n = S.shape[0]
    kc = max(2, min(CACHED, n_tgt))
    R = R.copy()
    t = t.copy()
    idx, at, d1, radius, cand, cand_xyz, bd, bi, held, slack2, near, moved = matcher_arrays(n, kc)
    solved = np.empty(n, np.int64)  # the matches the current pose was solved from
    weights = np.empty(n)
    fresh, have_solved, converged = True, False, False
    it = 0
    gate = gates[0]
    for stage in range(gates.shape[0]):
        gate = gates[stage]
        if not fresh:
            regate(gate, idx, slack2, near, d1, radius, n_tgt)
        converged = False
        while it < max_iterations:
            it += 1
            n_ok = match_pass(S, R, t, moved, idx, gate, fresh, at, d1, radius, cand, cand_xyz, held, slack2, near,
                              pts, cpts, origin, cell, dims, starts, order, bd, bi, n_tgt)
            fresh = False
            if repeat_is_fixed_point and have_solved and same_matches(idx, solved):
                converged = True
                break
            if n_ok < n and n_ok < min_inliers:  # as the numpy loop: checked when a pair is missing
                return R, t, it, False, 1, stage, n_ok, unsort(idx, perm)
            sw = px = py = pz = qx = qy = qz = 0.0  # weighted centroids of the matched source and target points
            for p in range(n):
                q = idx[p]
                if q >= n_tgt:
                    continue
                w = 1.0
                if robust != 0:
                    ux, uy, uz = moved[p, 0] - pts[q, 0], moved[p, 1] - pts[q, 1], moved[p, 2] - pts[q, 2]
                    dist = math.sqrt(ux * ux + uy * uy + uz * uz)
                    w = min(1.0, scale / max(dist, 1e-300)) if robust == 1 else 1.0 / (1.0 + (dist / scale) ** 2)
                weights[p] = w
                sw += w
                px += w * S[p, 0]
                py += w * S[p, 1]
                pz += w * S[p, 2]
                qx += w * pts[q, 0]
                qy += w * pts[q, 1]
                qz += w * pts[q, 2]
            if sw <= 0.0:
                return R, t, it, False, 3, stage, n_ok, unsort(idx, perm)
            px, py, pz, qx, qy, qz = px / sw, py / sw, pz / sw, qx / sw, qy / sw, qz / sw
            H = np.zeros((3, 3))
            for p in range(n):
                q = idx[p]
                if q >= n_tgt:
                    continue
                w = weights[p]
                a0, a1, a2 = S[p, 0] - px, S[p, 1] - py, S[p, 2] - pz
                b0, b1, b2 = (pts[q, 0] - qx) * w, (pts[q, 1] - qy) * w, (pts[q, 2] - qz) * w
                H[0, 0] += a0 * b0
                H[0, 1] += a0 * b1
                H[0, 2] += a0 * b2
                H[1, 0] += a1 * b0
                H[1, 1] += a1 * b1
                H[1, 2] += a1 * b2
                H[2, 0] += a2 * b0
                H[2, 1] += a2 * b1
                H[2, 2] += a2 * b2
            R_new = _rotation(H)
            tx = qx - (R_new[0, 0] * px + R_new[0, 1] * py + R_new[0, 2] * pz)
            ty = qy - (R_new[1, 0] * px + R_new[1, 1] * py + R_new[1, 2] * pz)
            tz = qz - (R_new[2, 0] * px + R_new[2, 1] * py + R_new[2, 2] * pz)
            dt = math.sqrt((tx - t[0]) ** 2 + (ty - t[1]) ** 2 + (tz - t[2]) ** 2)
            dr2 = 0.0
            for i in range(3):
                for j in range(3):
                    dr2 += (R_new[i, j] - R[i, j]) ** 2
            dr = math.sqrt(dr2) / math.sqrt(2.0)  # = 2 sin(α/2) ≈ α, no √ε floor
            R = R_new
            t[0], t[1], t[2] = tx, ty, tz
            solved[:] = idx
            have_solved = True
            if dt < tol_t and dr < tol_r:
                converged = True
                break
    # The matches at the final pose and the last gate (the evaluation's).
    match_pass(S, R, t, moved, idx, gate, fresh, at, d1, radius, cand, cand_xyz, held, slack2, near, pts, cpts, origin,
               cell, dims, starts, order, bd, bi, n_tgt)
    return R, t, it, converged, 0, gates.shape[0] - 1, n, unsort(idx, perm)
