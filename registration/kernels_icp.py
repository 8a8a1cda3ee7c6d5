"""Compiled (numba) 2D ICP iterations: point-to-point (SVD, Arun et al. 1987) and point-to-line (Chen & Medioni
1992) on the uniform-grid index of :mod:`registration.kernels`; the loop forms of ``registration.icp`` and
``registration.point_to_plane``, which stay as their references (tests check both agree to 1e-9)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .kernels import knn_normal, nearest_point, same_matches, solve_linear

__all__ = ["point_icp_2d", "plane_icp_2d"]


@njit(cache=True)
def _match_all(S, R, t, idx, pts, ox, oy, cell, nx, ny, order, starts, gate):  # pragma: no cover - compiled
    """``idx[p]``: the grid point nearest to source point p moved by (R, t), strictly within *gate* (−1: none);
    returns how many matched."""
    n_ok = 0
    for p in range(S.shape[0]):
        mx = R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + t[0]
        my = R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + t[1]
        idx[p] = nearest_point(mx, my, pts, ox, oy, cell, nx, ny, order, starts, gate)[0]
        if idx[p] >= 0:
            n_ok += 1
    return n_ok


@njit(cache=True)
def _pair_weight(S, R, t, p, pts, q, robust, scale):  # pragma: no cover - compiled
    """Robust weight of the pair (source p moved by (R, t), grid point q) from its distance, as
    registration.alignment.robust_weights: 1, Huber min(1, k/d) or Cauchy 1/(1 + (d/k)²)."""
    if robust == 0:
        return 1.0
    dx = R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + t[0] - pts[q, 0]
    dy = R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + t[1] - pts[q, 1]
    d = math.sqrt(dx * dx + dy * dy)
    return min(1.0, scale / max(d, 1e-300)) if robust == 1 else 1.0 / (1.0 + (d / scale) ** 2)


@njit(cache=True)
def plane_icp_2d(S, R, t, gates, max_iterations, tol_t, tol_r, robust, scale, min_inliers,
                 normals, have, k, pts, ox, oy, cell, nx, ny, order, starts):  # pragma: no cover - compiled
    """Point-to-line ICP iterations of ``registration.point_to_plane.icp_point_to_plane`` in 2D
    (Chen & Medioni 1992; left increment, Jacobian rows [nᵀ, m × n], Low 2004), source ``S (N, 2)``
    from ``(R, t)``; *robust* 0 = none, 1 = Huber, 2 = Cauchy with *scale* (IcpConfig.robust). Returns (R, t, iterations, converged, status, stage, pairs): status 0 = done,
    1 = fewer than *min_inliers* pairs (*pairs* of them) within ``gates[stage]`` at iteration
    *iterations*, 2 = singular normal equations."""
    n = S.shape[0]
    R = R.copy()
    t = t.copy()
    idx = np.empty(n, np.int64)
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    it = 0
    converged = False
    for stage in range(gates.shape[0]):
        gate = gates[stage]
        converged = False
        while it < max_iterations:
            it += 1
            n_ok = _match_all(S, R, t, idx, pts, ox, oy, cell, nx, ny, order, starts, gate)
            if n_ok < min_inliers:
                return R, t, it, False, 1, stage, n_ok
            H = np.zeros((3, 3))
            g = np.zeros(3)
            for p in range(n):
                q = idx[p]
                if q < 0:
                    continue
                if not have[q]:
                    normals[q, 0], normals[q, 1] = knn_normal(q, pts, ox, oy, cell, nx, ny, order, starts, k, bd, bi)
                    have[q] = True
                mx = R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + t[0]
                my = R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + t[1]
                nx_, ny_ = normals[q, 0], normals[q, 1]
                e = (mx - pts[q, 0]) * nx_ + (my - pts[q, 1]) * ny_
                w = 1.0
                if robust == 1:
                    w = min(1.0, scale / max(abs(e), 1e-300))
                elif robust == 2:
                    w = 1.0 / (1.0 + (e / scale) ** 2)
                j0, j1, j2 = nx_, ny_, mx * ny_ - my * nx_
                H[0, 0] += j0 * j0 * w
                H[0, 1] += j0 * j1 * w
                H[0, 2] += j0 * j2 * w
                H[1, 1] += j1 * j1 * w
                H[1, 2] += j1 * j2 * w
                H[2, 2] += j2 * j2 * w
                g[0] += j0 * w * e
                g[1] += j1 * w * e
                g[2] += j2 * w * e
            H[1, 0], H[2, 0], H[2, 1] = H[0, 1], H[0, 2], H[1, 2]
            xi = solve_linear(H, -g)
            if xi[0] != xi[0]:  # NaN: singular
                return R, t, it, False, 2, stage, n_ok
            R, t = _apply_se2_left(xi, R, t)
            if math.hypot(xi[0], xi[1]) < tol_t and abs(xi[2]) < tol_r:
                converged = True
                break
    return R, t, it, converged, 0, gates.shape[0] - 1, n


@njit(cache=True)
def point_icp_2d(S, R, t, gates, max_iterations, tol_t, tol_r, robust, scale, min_inliers, repeat_is_fixed_point,
                 pts, ox, oy, cell, nx, ny, order, starts):  # pragma: no cover - compiled
    """Point-to-point SVD-ICP iterations of ``registration.icp.icp`` in 2D (Besl & McKay 1992; the
    closed-form step of Arun et al. 1987, in 2D θ = atan2(H01 − H10, H00 + H11)), source ``S (N, 2)``
    from ``(R, t)``; *robust* 0 = none, 1 = Huber, 2 = Cauchy on the pair distance with *scale*. With
    *repeat_is_fixed_point* an iteration whose matches repeat those the pose was solved from ends the
    stage (the step would be exactly 0). Returns (R, t, iterations, converged, status, stage, matches,
    pairs): status 0 = done, *matches* the nearest target point within the last gate of each source point
    at the final pose (−1: none); 1 = fewer than *min_inliers* pairs (*pairs*) within ``gates[stage]`` at
    iteration *iterations*; 3 = every correspondence weight zero."""
    n = S.shape[0]
    idx, solved = np.empty(n, np.int64), np.empty(n, np.int64)  # matches now, and those the pose was solved from
    weights = np.empty(n)
    have_solved = converged = False
    R, t, th, it = R.copy(), t.copy(), math.atan2(R[1, 0], R[0, 0]), 0
    for stage in range(gates.shape[0]):
        converged = False
        while it < max_iterations:
            it += 1
            n_ok = _match_all(S, R, t, idx, pts, ox, oy, cell, nx, ny, order, starts, gates[stage])
            if repeat_is_fixed_point and have_solved and same_matches(idx, solved):
                converged = True
                break
            if n_ok < min_inliers:
                return R, t, it, False, 1, stage, idx, n_ok
            sw = px = py = qx = qy = 0.0  # weighted centroids of the matched source and target points
            for p in range(n):
                q = idx[p]
                weights[p] = 0.0 if q < 0 else _pair_weight(S, R, t, p, pts, q, robust, scale)
                if q >= 0:
                    w = weights[p]
                    sw += w
                    px += w * S[p, 0]
                    py += w * S[p, 1]
                    qx += w * pts[q, 0]
                    qy += w * pts[q, 1]
            if sw <= 0.0:
                return R, t, it, False, 3, stage, idx, n_ok
            px, py, qx, qy = px / sw, py / sw, qx / sw, qy / sw
            h00 = h01 = h10 = h11 = 0.0
            for p in range(n):
                q = idx[p]
                if q < 0:
                    continue
                ax, ay = S[p, 0] - px, S[p, 1] - py
                bx, by = (pts[q, 0] - qx) * weights[p], (pts[q, 1] - qy) * weights[p]
                h00 += ax * bx
                h01 += ax * by
                h10 += ay * bx
                h11 += ay * by
            th_new = math.atan2(h01 - h10, h00 + h11)
            c, s = math.cos(th_new), math.sin(th_new)
            tx, ty = qx - (c * px - s * py), qy - (s * px + c * py)
            dt = math.hypot(tx - t[0], ty - t[1])
            dr = abs(th_new - th)
            dr = min(dr, 2.0 * math.pi - dr)
            th = th_new
            R[0, 0], R[0, 1], R[1, 0], R[1, 1] = c, -s, s, c
            t[0], t[1] = tx, ty
            solved[:] = idx
            have_solved = True
            if dt < tol_t and dr < tol_r:
                converged = True
                break
    # The matches at the final pose and the last gate (the evaluation's), −1 where none.
    _match_all(S, R, t, idx, pts, ox, oy, cell, nx, ny, order, starts, gates[gates.shape[0] - 1])
    return R, t, it, converged, 0, gates.shape[0] - 1, idx, n


@njit(cache=True)
def _apply_se2_left(xi, R, t):  # pragma: no cover - compiled
    """``Exp(ξ) · (R, t)`` for ξ = (ρx, ρy, θ), as registration.point_to_plane._apply_se2_left."""
    rx, ry, th = xi[0], xi[1], xi[2]
    c, s = math.cos(th), math.sin(th)
    if abs(th) < 1e-9:
        a, b = 1.0 - th * th / 6.0, th / 2.0
    else:
        a, b = s / th, (1.0 - c) / th
    ex, ey = a * rx - b * ry, b * rx + a * ry
    R2 = np.empty((2, 2))
    t2 = np.empty(2)
    for i in range(2):
        R2[0, i] = c * R[0, i] - s * R[1, i]
        R2[1, i] = s * R[0, i] + c * R[1, i]
    t2[0] = c * t[0] - s * t[1] + ex
    t2[1] = s * t[0] + c * t[1] + ey
    return R2, t2
