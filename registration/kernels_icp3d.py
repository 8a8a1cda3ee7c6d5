"""Compiled (numba) 3D point-to-plane ICP (Chen & Medioni 1992) on the cell grid of
:mod:`registration.kernels_grid3d`: the loop form of ``registration.point_to_plane.icp_point_to_plane`` in 3D,
which stays as its reference (tests check that both agree), with the cached gated nearest neighbour of
:mod:`registration.matching`.

It exists because a LiDAR scan-to-map step (~20k source points against a ~300k-point local map, 30–100
iterations) spent most of its time in per-call numpy/scipy work: building a k-d tree of the map for every
scan, k-neighbour queries and a batched ``eigh`` for the normals, and a dozen array passes per iteration.

Matching keeps the cached-candidate certificate of :mod:`registration.matching` and adds a per-point slack: a
point that moved less than it from where its candidates were last compared has the same match, so most points
of a converging iteration cost one squared distance.

Frames: every argument is in one frame (the target's); metres and radians.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

Array = NDArray[np.float64]

from .kernels import solve_linear
from .kernels_grid3d import cell_index, knn3, normal_at

__all__ = ["CACHED", "cell_order", "evaluate_match", "match_pass", "matcher_arrays", "plane_icp_3d", "regate", "unsort"]

#: neighbours cached per source point by the matcher (registration.matching._CACHED), and the search bound as a
#: multiple of the gate (registration.matching._BOUND_FACTOR), and the certificate margin (matching._TAU)
CACHED, _BOUND_FACTOR, _TAU = 8, 2.0, 1e-9


@njit(cache=True, inline="always")
def _search(p, mx, my, mz, gate, at, d1, radius, cand, cand_xyz, pts, cpts, origin, cell, dims, starts, order,
            bd, bi):  # pragma: no cover - compiled
    """Search source point *p* at (mx, my, mz) afresh: cache its K nearest within the bound (matching._search),
    their indices in *cand* and their coordinates in *cand_xyz* (read in sequence by the checks that follow)."""
    kc = cand.shape[1]
    bound = _BOUND_FACTOR * gate
    knn3(mx, my, mz, pts, cpts, origin, cell, dims, starts, order, kc, bound, bd, bi)
    n_tgt = pts.shape[0]
    at[p, 0], at[p, 1], at[p, 2] = mx, my, mz
    d1[p] = math.sqrt(bd[0])
    radius[p] = min(math.sqrt(bd[kc - 1]), bound)
    for s in range(kc):
        j = bi[s]
        cand[p, s] = j if j >= 0 else n_tgt
        if j >= 0:
            cand_xyz[p, s, 0], cand_xyz[p, s, 1], cand_xyz[p, s, 2] = pts[j, 0], pts[j, 1], pts[j, 2]


@njit(cache=True, inline="always")
def _slack2(gate, best, second, d1, radius, eps):  # pragma: no cover - compiled
    """Squared distance a source point may move, from where its candidates were compared, with the same answer
    (−1: none): the match stays the strictly nearest candidate (half the gap to the second) and on the same
    side of the gate, and the cache stays certain — min(gate, d1 + e) + e < radius − τ at a motion e ≤ eps + δ
    from the search position — each less the margin τ, so that rounding cannot decide."""
    if best < gate:
        keep = min(0.5 * (second - best), gate - best)
    else:
        keep = best - gate
    room = radius - _TAU - eps
    keep = min(keep, max(0.5 * (room - d1 - eps), room - gate)) - _TAU
    return keep * keep if keep > 0.0 else -1.0


@njit(cache=True)
def evaluate_match(p, mx, my, mz, gate, fresh, at, d1, radius, cand, cand_xyz, held, slack2, near, pts, cpts, origin, cell,
              dims, starts, order, bd, bi):  # pragma: no cover - compiled
    """Index of the target point nearest to (mx, my, mz) strictly within *gate*, else len(pts): from the cached
    candidates while the motion since the last search keeps them certain (registration.matching), else after a
    fresh search. Records where (*held*), how far the point may move from there with the same answer
    (*slack2*, :func:`_slack2`), and *near*: the nearest candidate, its distance, the second's and the motion
    since the search (a new gate's answer and slack follow from them)."""
    n_tgt = pts.shape[0]
    eps = 0.0
    if not fresh:
        ex, ey, ez = mx - at[p, 0], my - at[p, 1], mz - at[p, 2]
        eps = math.sqrt(ex * ex + ey * ey + ez * ez)
    if fresh or not min(gate, d1[p] + eps) + eps < radius[p] - _TAU:
        _search(p, mx, my, mz, gate, at, d1, radius, cand, cand_xyz, pts, cpts, origin, cell, dims, starts, order,
                bd, bi)
        eps = 0.0
    best2 = second2 = np.inf
    j_best = n_tgt
    for c in range(cand.shape[1]):
        j = cand[p, c]
        if j >= n_tgt:
            break
        ux, uy, uz = mx - cand_xyz[p, c, 0], my - cand_xyz[p, c, 1], mz - cand_xyz[p, c, 2]
        dist2 = ux * ux + uy * uy + uz * uz
        if dist2 < best2:
            second2 = best2
            best2 = dist2
            j_best = j
        elif dist2 < second2:
            second2 = dist2
    best, second = math.sqrt(best2), math.sqrt(second2)
    held[p, 0], held[p, 1], held[p, 2] = mx, my, mz
    near[p, 0], near[p, 1], near[p, 2], near[p, 3] = j_best, best, second, eps
    slack2[p] = _slack2(gate, best, second, d1[p], radius[p], eps)
    return j_best if best < gate else n_tgt


@njit(cache=True)
def _apply_se3_left(xi, R, t):  # pragma: no cover - compiled
    """``Exp(ξ) · (R, t)`` for ξ = (ρ, φ), as core.geometry.se3_exp (Rodrigues; left Jacobian for ρ)."""
    wx, wy, wz = xi[3], xi[4], xi[5]
    th2 = wx * wx + wy * wy + wz * wz
    th = math.sqrt(th2)
    if th < 1e-8:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    if th < 1e-6:
        ja, jb = 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        ja, jb = (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -wz, wy, wz, -wx, -wy, wx
    K2 = K @ K
    E = np.eye(3) + a * K + b * K2
    J = np.eye(3) + ja * K + jb * K2
    et = J @ xi[:3]
    return E @ R, E @ t + et


@njit(cache=True)
def matcher_arrays(n, kc):  # pragma: no cover - compiled
    """The cached matcher's state for *n* source points and *kc* cached candidates: the match ``idx``; where the
    candidates were searched (``at``), the nearest's distance ``d1`` and the cache's ``radius``; the candidates
    (``cand``, ``cand_xyz``) and the search's scratch (``bd``, ``bi``); where each match was last evaluated
    (``held``) and the squared distance the point may move from there keeping it (``slack2``, −1: none yet);
    ``near`` (nearest candidate there, its distance, the second's, motion since the search); ``moved``."""
    return (np.empty(n, np.int64), np.empty((n, 3)), np.empty(n), np.empty(n), np.empty((n, kc), np.int64),
            np.empty((n, kc, 3)), np.empty(kc), np.empty(kc, np.int64), np.zeros((n, 3)), np.full(n, -1.0),
            np.empty((n, 4)), np.empty((n, 3)))


@njit(cache=True, inline="always")
def match_pass(S, R, t, moved, idx, gate, fresh, at, d1, radius, cand, cand_xyz, held, slack2, near, pts, cpts, origin,
               cell, dims, starts, order, bd, bi, n_tgt):  # pragma: no cover - compiled
    """One matching pass of an iteration: every source point of *S* moved by (*R*, *t*) into *moved*, its match
    into *idx* — kept without comparing candidates while the point stays within its slack of where it was last
    evaluated, else :func:`evaluate_match` — and the number matched within the *gate* returned."""
    n_ok = 0
    for p in range(S.shape[0]):
        mx = R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + R[0, 2] * S[p, 2] + t[0]
        my = R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + R[1, 2] * S[p, 2] + t[1]
        mz = R[2, 0] * S[p, 0] + R[2, 1] * S[p, 1] + R[2, 2] * S[p, 2] + t[2]
        moved[p, 0], moved[p, 1], moved[p, 2] = mx, my, mz
        ex, ey, ez = mx - held[p, 0], my - held[p, 1], mz - held[p, 2]
        if ex * ex + ey * ey + ez * ez < slack2[p]:
            q = idx[p]  # certainly the same match as where it was last evaluated
        else:
            q = evaluate_match(p, mx, my, mz, gate, fresh, at, d1, radius, cand, cand_xyz, held, slack2, near, pts, cpts,
                               origin, cell, dims, starts, order, bd, bi)
        idx[p] = q
        if q < n_tgt:
            n_ok += 1
    return n_ok


@njit(cache=True)
def regate(gate, idx, slack2, near, d1, radius, n_tgt):  # pragma: no cover - compiled
    """A new gate: each point's answer where its candidates were last compared, and its slack, from *near*
    (the cache must stay certain there under the new gate, else the point is compared again)."""
    for p in range(idx.shape[0]):
        best, second, eps = near[p, 1], near[p, 2], near[p, 3]
        if min(gate, d1[p] + eps) + eps < radius[p] - _TAU:
            idx[p] = np.int64(near[p, 0]) if best < gate else n_tgt
            slack2[p] = _slack2(gate, best, second, d1[p], radius[p], eps)
        else:
            slack2[p] = -1.0


@njit(cache=True)
def cell_order(S, R, t, origin, cell, dims):  # pragma: no cover - compiled
    """The order of the source points ``S (N, 3)`` moved by (R, t) by grid cell (stable): iterating in it, consecutive
    points search the same cells (undo with :func:`unsort`)."""
    key = np.empty(S.shape[0], np.int64)
    for p in range(S.shape[0]):
        key[p] = cell_index(R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + R[0, 2] * S[p, 2] + t[0],
                            R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + R[1, 2] * S[p, 2] + t[1],
                            R[2, 0] * S[p, 0] + R[2, 1] * S[p, 1] + R[2, 2] * S[p, 2] + t[2], origin, cell, dims)
    return np.argsort(key, kind="mergesort")


@njit(cache=True)
def unsort(idx, perm):  # pragma: no cover - compiled
    out = np.empty_like(idx)
    for p in range(idx.shape[0]):
        out[perm[p]] = idx[p]
    return out


@njit(cache=True)
def plane_icp_3d(S, R, t, gates, max_iterations, tol_t, tol_r, robust, scale, min_inliers,
                 normals, have, k, pts, cpts, origin, cell, dims, starts, order):  # pragma: no cover - compiled
    """Point-to-plane ICP iterations of ``registration.point_to_plane.icp_point_to_plane`` in 3D (left
    increment, Jacobian rows [nᵀ, (m × n)ᵀ], Low 2004), source ``S (N, 3)`` from ``(R, t)``; *robust* 0 = none,
    1 = Huber, 2 = Cauchy on |e| with *scale*. Normals of the matched target points are filled into *normals*
    / *have* on demand. Returns (R, t, iterations, converged, status, stage, pairs, matches): status 0 = done,
    *matches* the nearest target point strictly within the last gate of each source point at the final pose
    (len(pts): none); 1 = fewer than *min_inliers* pairs (*pairs*) within ``gates[stage]`` at iteration
    *iterations*; 2 = singular normal equations."""
    n_tgt = pts.shape[0]
    # The source in the grid's cell order: consecutive points search, and read the normals of, the same cells.
    perm = cell_order(S, R, t, origin, cell, dims)
    S = S[perm]
    n = S.shape[0]
    kc = max(2, min(CACHED, n_tgt))
    R = R.copy()
    t = t.copy()
    idx, at, d1, radius, cand, cand_xyz, bd, bi, held, slack2, near, moved = matcher_arrays(n, kc)
    bdk = np.empty(k)
    bik = np.empty(k, np.int64)
    # each source point's current match, its coordinates and normal, read in sequence while the match holds
    pair = np.full(n, -1, np.int64)
    pair_xyz = np.empty((n, 3))
    pair_n = np.empty((n, 3))
    fresh = True
    it = 0
    converged = False
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
            if n_ok < min_inliers:
                return R, t, it, False, 1, stage, n_ok, unsort(idx, perm)
            H = np.zeros((6, 6))
            g = np.zeros(6)
            J = np.empty(6)
            for p in range(n):
                q = idx[p]
                if q >= n_tgt:
                    continue
                if q != pair[p]:
                    if not have[q]:
                        normal_at(q, normals, pts, cpts, origin, cell, dims, starts, order, k, bdk, bik)
                        have[q] = True
                    pair[p] = q
                    for a in range(3):
                        pair_xyz[p, a] = pts[q, a]
                        pair_n[p, a] = normals[q, a]
                mx, my, mz = moved[p, 0], moved[p, 1], moved[p, 2]
                nx_, ny_, nz_ = pair_n[p, 0], pair_n[p, 1], pair_n[p, 2]
                e = (mx - pair_xyz[p, 0]) * nx_ + (my - pair_xyz[p, 1]) * ny_ + (mz - pair_xyz[p, 2]) * nz_
                w = 1.0
                if robust == 1:
                    w = min(1.0, scale / max(abs(e), 1e-300))
                elif robust == 2:
                    w = 1.0 / (1.0 + (abs(e) / scale) ** 2)
                J[0], J[1], J[2] = nx_, ny_, nz_
                J[3] = my * nz_ - mz * ny_
                J[4] = mz * nx_ - mx * nz_
                J[5] = mx * ny_ - my * nx_
                for a in range(6):
                    wa = J[a] * w
                    for b in range(a, 6):
                        H[a, b] += J[b] * wa
                    g[a] += wa * e
            for a in range(6):
                for b in range(a):
                    H[a, b] = H[b, a]
            xi = solve_linear(H, -g)
            if xi[0] != xi[0]:  # NaN: singular
                return R, t, it, False, 2, stage, n_ok, unsort(idx, perm)
            R, t = _apply_se3_left(xi, R, t)
            if (math.sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2]) < tol_t
                    and math.sqrt(xi[3] * xi[3] + xi[4] * xi[4] + xi[5] * xi[5]) < tol_r):
                converged = True
                break
    # The matches at the final pose and the last gate (the evaluation's), with their normals.
    if gate != gates[gates.shape[0] - 1]:  # the iteration cap ended an earlier stage
        gate = gates[gates.shape[0] - 1]
        regate(gate, idx, slack2, near, d1, radius, n_tgt)
    for p in range(n):
        mx = R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + R[0, 2] * S[p, 2] + t[0]
        my = R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + R[1, 2] * S[p, 2] + t[1]
        mz = R[2, 0] * S[p, 0] + R[2, 1] * S[p, 1] + R[2, 2] * S[p, 2] + t[2]
        ex, ey, ez = mx - held[p, 0], my - held[p, 1], mz - held[p, 2]
        if ex * ex + ey * ey + ez * ez < slack2[p]:
            q = idx[p]
        else:
            q = evaluate_match(p, mx, my, mz, gate, fresh, at, d1, radius, cand, cand_xyz, held, slack2, near, pts, cpts, origin,
                          cell, dims, starts, order, bd, bi)
        idx[p] = q
        if q < n_tgt and not have[q]:
            normal_at(q, normals, pts, cpts, origin, cell, dims, starts, order, k, bdk, bik)
            have[q] = True
    return R, t, it, converged, 0, gates.shape[0] - 1, n, unsort(idx, perm)
