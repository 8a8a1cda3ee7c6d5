"""Compiled (numba) searches of registration: a uniform-grid index of 2D points with its gated nearest-neighbour
and k-nearest-neighbour searches and PCA normals, and the cached nearest-neighbour test of the 3D incremental
matcher. The ICP iterations that use them are in :mod:`registration.kernels_icp`, the correlative scorer in
:mod:`registration.kernels_correlative`; ``python -m registration.compile_kernels`` compiles all of them.

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

from core import geometry as G

Array = NDArray[np.float64]

__all__ = ["PointGrid", "nearest_point", "nearest_within", "knn_normal", "normals_2d", "cached_nearest", "insert_best",
           "same_matches", "solve_linear"]

# Grids larger than this many cells get coarser cells (a far target of a long-range laser spans ~160 m).
MAX_CELLS = 4_000_000


class PointGrid:
    """Uniform-grid index of 2D points ``(N, 2)`` (m) with cell side *cell* (m; grown when the bounding
    box would need more than 4 million cells)."""

    def __init__(self, points: Array, cell: float = 0.25) -> None:
        pts = np.ascontiguousarray(points[:, :2], dtype=np.float64)
        lo, hi = G.bounds(pts)
        span = float(max(hi[0] - lo[0], hi[1] - lo[1]))
        cell = max(cell, span / math.sqrt(MAX_CELLS))
        self.points = pts
        self.cell = float(cell)
        self.origin = lo
        self.nx = int((hi[0] - lo[0]) / cell) + 1
        self.ny = int((hi[1] - lo[1]) / cell) + 1
        self.order, self.starts = _bucket(pts, lo[0], lo[1], self.cell, self.nx, self.ny)

    def args(self) -> tuple:
        """The grid as the positional arguments every kernel takes after the points."""
        return (self.origin[0], self.origin[1], self.cell, self.nx, self.ny, self.order, self.starts)


@njit(cache=True, inline="always")
def same_matches(idx, solved):  # pragma: no cover - compiled
    """Whether every point's match *idx* equals the one the current pose was solved from (*solved*): the
    closed-form step would return the same pose, the unweighted loops' fixed point."""
    for p in range(idx.shape[0]):
        if idx[p] != solved[p]:
            return False
    return True


@njit(cache=True, inline="always")
def insert_best(bd, bi, k, d2, index):  # pragma: no cover - compiled
    """Insert the squared distance *d2* of point *index* into the ascending *k* best (*bd*, *bi*), dropping the
    last (the caller checked that *d2* beats it)."""
    s = k - 1
    while s > 0 and bd[s - 1] > d2:
        bd[s] = bd[s - 1]
        bi[s] = bi[s - 1]
        s -= 1
    bd[s] = d2
    bi[s] = index


@njit(cache=True)
def solve_linear(A, b):  # pragma: no cover - compiled
    """Gaussian elimination with partial pivoting of an n×n system; NaNs when a pivot is exactly 0."""
    n = b.shape[0]
    M = np.empty((n, n + 1))
    M[:, :n] = A
    M[:, n] = b
    for c in range(n):
        piv = c
        for r in range(c + 1, n):
            if abs(M[r, c]) > abs(M[piv, c]):
                piv = r
        if M[piv, c] == 0.0:
            return np.full(n, np.nan)
        if piv != c:
            for q in range(n + 1):
                M[c, q], M[piv, q] = M[piv, q], M[c, q]
        for r in range(c + 1, n):
            f = M[r, c] / M[c, c]
            for q in range(c, n + 1):
                M[r, q] -= f * M[c, q]
    x = np.empty(n)
    for c in range(n - 1, -1, -1):
        s = M[c, n]
        for q in range(c + 1, n):
            s -= M[c, q] * x[q]
        x[c] = s / M[c, c]
    return x


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
def nearest_point(x, y, pts, ox, oy, cell, nx, ny, order, starts, gate):  # pragma: no cover - compiled
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
        out[m] = nearest_point(queries[m, 0], queries[m, 1], pts, ox, oy, cell, nx, ny, order, starts, gate)[0]
    return out


@njit(cache=True)
def knn_normal(p, pts, ox, oy, cell, nx, ny, order, starts, k, bd, bi):  # pragma: no cover - compiled
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
                        if d2 < bd[k - 1]:
                            insert_best(bd, bi, k, d2, o)
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
            normals[p, 0], normals[p, 1] = knn_normal(p, pts, ox, oy, cell, nx, ny, order, starts, k, bd, bi)
            have[p] = True


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
