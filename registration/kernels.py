"""Compiled (numba) inner loops of planar registration: a uniform-grid point index, its gated nearest
neighbour and k-nearest-neighbour searches, PCA normals, the point-to-line ICP iterations and the
correlative scorer.

Each kernel is the loop form of a numpy implementation that stays in the package as its reference
and for 3D (``registration.point_to_plane``, ``registration.correlative``); tests check that both
agree. They exist because a 2D laser scan has ~200 points, where numpy's per-call overhead, not
arithmetic, set the cost (measurements in ``benchmarks/registration.py``).

Grid index: points bucketed into square cells of side ``cell`` (m) by a counting sort; cell (i, j)
holds ``order[starts[i·ny + j] : starts[i·ny + j + 1]]``. A search visits square rings of cells
around the query's cell; after ring r every unvisited point is at least r·cell away (the query lies
inside the centre cell), which ends the search exactly.

Frames: every argument is in one frame (the target's); metres and radians. Callers import this
module only when they use it: importing numba adds ~120 MB to a process.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["PointGrid", "plane_icp_2d", "point_icp_2d", "nearest_within", "normals_2d", "score_candidates", "compile_all"]

# Grids larger than this many cells get coarser cells (a far target of a long-range laser spans ~160 m).
_MAX_CELLS = 4_000_000


class PointGrid:
    """Uniform-grid index of 2D points ``(N, 2)`` (m) with cell side *cell* (m; grown when the bounding
    box would need more than 4 million cells)."""

    def __init__(self, points: Array, cell: float = 0.25) -> None:
        pts = np.ascontiguousarray(points[:, :2], dtype=np.float64)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        span = float(max(hi[0] - lo[0], hi[1] - lo[1]))
        cell = max(cell, span / math.sqrt(_MAX_CELLS))
        self.points = pts
        self.cell = float(cell)
        self.origin = lo
        self.nx = int((hi[0] - lo[0]) / cell) + 1
        self.ny = int((hi[1] - lo[1]) / cell) + 1
        self.order, self.starts = _bucket(pts, lo[0], lo[1], self.cell, self.nx, self.ny)

    def args(self) -> tuple:
        """The grid as the positional arguments every kernel takes after the points."""
        return (self.origin[0], self.origin[1], self.cell, self.nx, self.ny, self.order, self.starts)


@njit(cache=True)
def _bucket(pts, ox, oy, cell, nx, ny):  # pragma: no cover - compiled
    n = pts.shape[0]
    key = np.empty(n, np.int64)
    starts = np.zeros(nx * ny + 1, np.int64)
    for p in range(n):
        i = min(max(int((pts[p, 0] - ox) / cell), 0), nx - 1)
        j = min(max(int((pts[p, 1] - oy) / cell), 0), ny - 1)
        key[p] = i * ny + j
        starts[key[p] + 1] += 1
    for c in range(nx * ny):
        starts[c + 1] += starts[c]
    fill = starts[:-1].copy()
    order = np.empty(n, np.int64)
    for p in range(n):
        order[fill[key[p]]] = p
        fill[key[p]] += 1
    return order, starts


@njit(cache=True, inline="always")
def _cell_of(x, y, ox, oy, cell):  # pragma: no cover - compiled
    return int(math.floor((x - ox) / cell)), int(math.floor((y - oy) / cell))


@njit(cache=True, inline="always")
def _covered(x, y, ci, cj, r, ox, oy, cell):  # pragma: no cover - compiled
    """Radius around (x, y) that the cells of rings 0 … *r* about its cell (ci, cj) cover: every point
    closer than this lies in them (at least r·cell, up to (r + 1)·cell by where it sits in its cell)."""
    lo_x = ox + (ci - r) * cell
    lo_y = oy + (cj - r) * cell
    span = (2 * r + 1) * cell
    return min(x - lo_x, lo_x + span - x, y - lo_y, lo_y + span - y)


@njit(cache=True)
def _nearest(x, y, pts, ox, oy, cell, nx, ny, order, starts, gate):  # pragma: no cover - compiled
    """Index of the point nearest to (x, y) strictly closer than *gate*, else −1; and its squared distance."""
    ci, cj = _cell_of(x, y, ox, oy, cell)
    best_d2 = gate * gate
    best = -1
    r = 0
    while True:
        for i in range(max(ci - r, 0), min(ci + r, nx - 1) + 1):
            edge_i = i == ci - r or i == ci + r  # a full column of ring r, else only its two ends
            j = cj - r
            while j <= cj + r:
                if 0 <= j < ny:
                    c = i * ny + j
                    for q in range(starts[c], starts[c + 1]):
                        p = order[q]
                        dx = pts[p, 0] - x
                        dy = pts[p, 1] - y
                        d2 = dx * dx + dy * dy
                        if d2 < best_d2:
                            best_d2, best = d2, p
                j += 1 if edge_i else 2 * r
        reach = _covered(x, y, ci, cj, r, ox, oy, cell)
        if reach >= gate or (best >= 0 and best_d2 <= reach * reach):
            break
        if ci - r <= 0 and ci + r >= nx - 1 and cj - r <= 0 and cj + r >= ny - 1:
            break
        r += 1
    return best, best_d2


@njit(cache=True)
def nearest_within(queries, pts, ox, oy, cell, nx, ny, order, starts, gate):  # pragma: no cover - compiled
    """Nearest grid point strictly within *gate* of each query ``(M, 2)``: indices, −1 where none."""
    out = np.empty(queries.shape[0], np.int64)
    for m in range(queries.shape[0]):
        out[m] = _nearest(queries[m, 0], queries[m, 1], pts, ox, oy, cell, nx, ny, order, starts, gate)[0]
    return out


@njit(cache=True)
def _normal(p, pts, ox, oy, cell, nx, ny, order, starts, k, bd, bi):  # pragma: no cover - compiled
    """PCA normal at point *p* from its *k* nearest points (itself included), as estimate_normals; *bd*, *bi*
    are work arrays of length k."""
    x, y = pts[p, 0], pts[p, 1]
    ci, cj = _cell_of(x, y, ox, oy, cell)
    bd[:] = np.inf
    bi[:] = -1
    r = 0
    while True:
        for i in range(max(ci - r, 0), min(ci + r, nx - 1) + 1):
            edge_i = i == ci - r or i == ci + r
            j = cj - r
            while j <= cj + r:
                if 0 <= j < ny:
                    c = i * ny + j
                    for q in range(starts[c], starts[c + 1]):
                        o = order[q]
                        dx = pts[o, 0] - x
                        dy = pts[o, 1] - y
                        d2 = dx * dx + dy * dy
                        if d2 < bd[k - 1]:  # insert into the sorted k best
                            s = k - 1
                            while s > 0 and bd[s - 1] > d2:
                                bd[s] = bd[s - 1]
                                bi[s] = bi[s - 1]
                                s -= 1
                            bd[s] = d2
                            bi[s] = o
                j += 1 if edge_i else 2 * r
        reach = _covered(x, y, ci, cj, r, ox, oy, cell)
        if bi[k - 1] >= 0 and bd[k - 1] <= reach * reach:
            break
        if ci - r <= 0 and ci + r >= nx - 1 and cj - r <= 0 and cj + r >= ny - 1:
            break
        r += 1
    mx = 0.0
    my = 0.0
    for s in range(k):
        mx += pts[bi[s], 0]
        my += pts[bi[s], 1]
    mx /= k
    my /= k
    a = 0.0
    b = 0.0
    cc = 0.0
    for s in range(k):
        ux = pts[bi[s], 0] - mx
        uy = pts[bi[s], 1] - my
        a += ux * ux
        b += ux * uy
        cc += uy * uy
    phi = 0.5 * math.atan2(2.0 * b, a - cc)
    return -math.sin(phi), math.cos(phi)


@njit(cache=True)
def normals_2d(index, normals, have, pts, ox, oy, cell, nx, ny, order, starts, k):  # pragma: no cover - compiled
    """Fill ``normals[p]`` for each p in *index* not yet *have* (k-neighbour PCA, k ≤ number of points)."""
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    for m in range(index.shape[0]):
        p = index[m]
        if not have[p]:
            normals[p, 0], normals[p, 1] = _normal(p, pts, ox, oy, cell, nx, ny, order, starts, k, bd, bi)
            have[p] = True


@njit(cache=True)
def _match_all(S, R, t, idx, pts, ox, oy, cell, nx, ny, order, starts, gate):  # pragma: no cover - compiled
    """``idx[p]``: the grid point nearest to source point p moved by (R, t), strictly within *gate* (−1: none);
    returns how many matched."""
    n_ok = 0
    for p in range(S.shape[0]):
        mx = R[0, 0] * S[p, 0] + R[0, 1] * S[p, 1] + t[0]
        my = R[1, 0] * S[p, 0] + R[1, 1] * S[p, 1] + t[1]
        idx[p] = _nearest(mx, my, pts, ox, oy, cell, nx, ny, order, starts, gate)[0]
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
                    normals[q, 0], normals[q, 1] = _normal(q, pts, ox, oy, cell, nx, ny, order, starts, k, bd, bi)
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
            xi = _solve3(H, -g)
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
            if repeat_is_fixed_point and have_solved:
                same = True
                for p in range(n):
                    if idx[p] != solved[p]:
                        same = False
                        break
                if same:
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
def _solve3(A, b):  # pragma: no cover - compiled
    """Gaussian elimination with partial pivoting of a 3×3 system; NaNs when a pivot is exactly 0."""
    M = np.empty((3, 4))
    M[:, :3] = A
    M[:, 3] = b
    for c in range(3):
        piv = c
        for r in range(c + 1, 3):
            if abs(M[r, c]) > abs(M[piv, c]):
                piv = r
        if M[piv, c] == 0.0:
            return np.full(3, np.nan)
        if piv != c:
            for q in range(4):
                M[c, q], M[piv, q] = M[piv, q], M[c, q]
        for r in range(c + 1, 3):
            f = M[r, c] / M[c, c]
            for q in range(c, 4):
                M[r, q] -= f * M[c, q]
    x = np.empty(3)
    for c in range(2, -1, -1):
        s = M[c, 3]
        for q in range(c + 1, 3):
            s -= M[c, q] * x[q]
        x[c] = s / M[c, c]
    return x


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


@njit(cache=True, inline="always")
def _score_at(grid, cells, r, ox, oy):  # pragma: no cover - compiled
    """One candidate of :func:`score_candidates`: rotation index *r*, cell offset (*ox*, *oy*)."""
    H, W = grid.shape
    n = cells.shape[1]
    acc = 0
    for p in range(n):
        i = min(max(cells[r, p, 0] + ox, 0), H - 1)
        j = min(max(cells[r, p, 1] + oy, 0), W - 1)
        acc += grid[i, j]
    return float(acc) / n / 255.0


@njit(cache=True)
def score_candidates(grid, cells, rot, offsets):  # pragma: no cover - compiled
    """Correlative scores of ``registration.correlative.LikelihoodPyramid.score_candidates``: for each
    candidate c the mean over the scan's points of the uint8 *grid* at ``cells[rot[c]] + offsets[c]``
    (indices clipped to the grid) divided by 255, summed exactly in integers."""
    out = np.empty(rot.shape[0])
    for c in range(rot.shape[0]):
        out[c] = _score_at(grid, cells, rot[c], offsets[c, 0], offsets[c, 1])
    return out


@njit(cache=True)
def branch_and_bound(grids, cells, top, w, best, best_rot, best_ox, best_oy,
                     ex_r, ex_x, ex_y, ex_dr, ex_dxy):  # pragma: no cover - compiled
    """Depth-first branch and bound of ``registration.correlative.match`` (Hess et al. 2016, Algorithm 3).

    *grids* ``(L, H, W)`` uint8: the pyramid's max-pooled levels; *cells* ``(R, N, 2)``: the scan's
    cells at each of R rotations. Candidates are (rotation, offset) with offsets in [−w, w]² cells:
    level-*top* blocks of 2^top × 2^top offsets from −w, each split into its four children down to
    level 0 (single offsets). Children are visited best first, so the first leaves reached are good
    and the bound prunes the rest; a block is expanded only when its bound (the max-pooled score)
    exceeds *best*. Returns the best (score, rotation, ox, oy) strictly above the starting *best*,
    or the starting values when nothing in the window beats it. With *ex_dxy* ≥ 0 the candidates within
    *ex_dr* rotations and *ex_dxy* cells (in x and in y) of (*ex_r*, *ex_x*, *ex_y*) are excluded: the
    best pose elsewhere, for the uniqueness test of a match (blocks wholly inside are skipped)."""
    R = cells.shape[0]
    h = 1 << top
    ng = (2 * w) // h + 1
    m = R * ng * ng
    cap = m + 4 * (top + 1)
    s_lv = np.empty(cap, np.int64)
    s_r = np.empty(cap, np.int64)
    s_x = np.empty(cap, np.int64)
    s_y = np.empty(cap, np.int64)
    s_b = np.empty(cap)
    top_b = np.empty(m)
    for r in range(R):
        for a in range(ng):
            for b in range(ng):
                top_b[(r * ng + a) * ng + b] = _score_at(grids[top], cells, r, -w + a * h, -w + b * h)
    sp = 0
    for c in np.argsort(top_b, kind="mergesort"):  # ascending: the best block is popped first
        if top_b[c] > best:
            r, rest = c // (ng * ng), c % (ng * ng)
            s_lv[sp], s_r[sp], s_x[sp], s_y[sp], s_b[sp] = top, r, -w + (rest // ng) * h, -w + (rest % ng) * h, top_b[c]
            sp += 1
    cb = np.empty(4)
    cx = np.empty(4, np.int64)
    cy = np.empty(4, np.int64)
    while sp > 0:
        sp -= 1
        lv, r, x, y, bound = s_lv[sp], s_r[sp], s_x[sp], s_y[sp], s_b[sp]
        if bound <= best:
            continue
        if ex_dxy >= 0 and abs(r - ex_r) <= ex_dr:
            span = (1 << lv) - 1
            if x >= ex_x - ex_dxy and x + span <= ex_x + ex_dxy and y >= ex_y - ex_dxy and y + span <= ex_y + ex_dxy:
                continue  # every candidate of the block is excluded
        if lv == 0:
            best, best_rot, best_ox, best_oy = bound, r, x, y
            continue
        half = 1 << (lv - 1)
        k = 0
        for dx in range(2):
            for dy in range(2):
                x2, y2 = x + dx * half, y + dy * half
                if x2 > w or y2 > w:
                    continue
                sc = _score_at(grids[lv - 1], cells, r, x2, y2)
                if sc <= best:
                    continue
                # insertion into cb[:k], ascending
                q = k
                while q > 0 and cb[q - 1] > sc:
                    cb[q], cx[q], cy[q] = cb[q - 1], cx[q - 1], cy[q - 1]
                    q -= 1
                cb[q], cx[q], cy[q] = sc, x2, y2
                k += 1
        for q in range(k):
            s_lv[sp], s_r[sp], s_x[sp], s_y[sp], s_b[sp] = lv - 1, r, cx[q], cy[q], cb[q]
            sp += 1
    return best, best_rot, best_ox, best_oy


@njit(cache=True)
def cached_nearest(moved, at, d1, radius, cand, tgt, gate, tau, out):  # pragma: no cover - compiled
    """Gated nearest neighbours of *moved* among each point's cached candidates, where the cache is certified
    (:mod:`registration.matching`): *cand* ``(N, K)`` holds every target point closer than *radius* to the
    point's search position *at* (nearest first, ``len(tgt)`` past the last), *d1* the nearest distance
    there. The point moved by ε, so a neighbour within the gate is at most min(gate, d1 + ε) from it and
    min(gate, d1 + ε) + ε from *at*: when that is below *radius* − *tau* the cache holds it. *out* gets the
    index (``len(tgt)`` = unmatched) of certified points, −1 for the others (to be searched again)."""
    n, k = cand.shape
    d = moved.shape[1]
    n_tgt = tgt.shape[0]
    for i in range(n):
        e2 = 0.0
        for a in range(d):
            v = moved[i, a] - at[i, a]
            e2 += v * v
        eps = math.sqrt(e2)
        if min(gate, d1[i] + eps) + eps >= radius[i] - tau:
            out[i] = -1
            continue
        best = np.inf
        bi = n_tgt
        for c in range(k):
            j = cand[i, c]
            if j >= n_tgt:
                break
            s2 = 0.0
            for a in range(d):
                v = moved[i, a] - tgt[j, a]
                s2 += v * v
            dist = math.sqrt(s2)
            if dist < best:
                best = dist
                bi = j
        out[i] = bi if best < gate else n_tgt


def compile_all() -> None:
    """Compile every kernel for the argument types the package passes, into numba's on-disk cache
    (``make install`` runs this once, so the first ``slam run`` does not spend ~8 s compiling)."""
    pts = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [0.0, 1.0], [1.0, 1.1], [2.0, 1.0]])
    g = PointGrid(pts)
    nearest_within(pts.copy(), g.points, *g.args(), 0.5)
    normals, have = np.zeros_like(pts), np.zeros(len(pts), dtype=bool)
    normals_2d(np.arange(len(pts)), normals, have, g.points, *g.args(), 3)
    plane_icp_2d(pts.copy(), np.eye(2), np.zeros(2), np.array([0.5]), 2, 1e-4, 1e-4, 2, 0.1, 3,
                 normals, have, 3, g.points, *g.args())
    score_candidates(np.zeros((4, 4), np.uint8), np.zeros((1, 3, 2), np.int32), np.zeros(1, np.int64),
                     np.zeros((1, 2), np.int64))
    for dim in (2, 3):
        q = np.zeros((2, dim))
        cached_nearest(q, q.copy(), np.zeros(2), np.ones(2), np.zeros((2, 4), np.int64), np.zeros((3, dim)), 0.5, 1e-9,
                       np.zeros(2, np.int64))
    branch_and_bound(np.zeros((2, 4, 4), np.uint8), np.zeros((1, 3, 2), np.int32), 1, 1, 0.0, 0, 0, 0, 0, 0, 0, 0, -1)


if __name__ == "__main__":
    compile_all()
