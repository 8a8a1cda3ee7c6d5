"""Compiled (numba) searches of 3D points on a uniform cell grid: exact k-nearest neighbours, the PCA normals of
:func:`registration.target.estimate_normals`, and the first-point voxel subsampling of
:func:`registration.voxel.voxel_downsample` — the parts of :mod:`registration.kernels_icp3d` that do not iterate a
pose. The numpy / scipy versions stay as their references (tests check that both agree).

Grid: points bucketed into cubic cells of side ``cell`` (1 m; coarser when the box would need more than
``MAX_CELLS``) over their bounding box by a counting sort, and stored cell by cell. A search visits the 2×2×2
cells around the query, then cubic shells of cells around its own, skipping cells farther than the k-th point
found; once every unvisited cell is farther (the faces of the visited block), the search ends exactly (the 2D
grid of :mod:`registration.kernels` does the same with square rings). A dense grid over a 200 m × 200 m × 20 m
local map holds 800k cells at 1 m and builds in ~10 ms for 270k points; a hash of the occupied cells was slower
to build and to probe (measured on real LiDAR frames; docs/ODOMETRY.md, "3D").

Frames: every argument is in one frame; metres.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from .kernels import insert_best

Array = NDArray[np.float64]

__all__ = ["VoxelGrid3D", "cell_index", "knn3", "normal_at", "normals_3d", "voxel_first_3d"]

#: hash multiplier of the voxel subsampling (Fibonacci hashing, Knuth TAOCP vol. 3 §6.4)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)

#: Grids larger than this many cells get coarser cells (a 200 m × 200 m × 20 m local map at 1 m holds 800k).
MAX_CELLS = 8_000_000


class VoxelGrid3D:
    """Uniform-grid index of 3D points ``(N, 3)`` (m) over their bounding box, cubic cells of side *cell* (m;
    grown when the box would need more than ``MAX_CELLS``). The points are kept reordered cell by cell
    (``cell_points``; ``order``: their indices in *points*) so that a search reads each cell's points from one
    contiguous block: cell (i, j, k) holds ``cell_points[starts[c] : starts[c + 1]]``, c = (i·ny + j)·nz + k."""

    def __init__(self, points: Array, cell: float = 1.0) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"VoxelGrid3D needs (N, 3) points, got shape {pts.shape}")
        lo, hi = _bounds(pts)
        span = np.maximum(hi - lo, 1e-9)
        cell = max(float(cell), float(np.prod(span) / MAX_CELLS) ** (1.0 / 3.0))
        dims = np.floor(span / cell).astype(np.int64) + 1
        while int(np.prod(dims)) > MAX_CELLS:  # rounding up each axis can overshoot
            cell *= 1.1
            dims = np.floor(span / cell).astype(np.int64) + 1
        self.points, self.cell, self.origin, self.dims = pts, cell, lo, dims
        self.starts, self.order, self.cell_points = _bucket3(pts, lo, cell, dims)

    def args(self) -> tuple:
        """The grid as the positional arguments every kernel takes after the points."""
        return (self.cell_points, self.origin, self.cell, self.dims, self.starts, self.order)


@njit(cache=True)
def _bounds(pts):  # pragma: no cover - compiled
    lo = pts[0].copy()
    hi = pts[0].copy()
    for p in range(1, pts.shape[0]):
        for a in range(3):
            v = pts[p, a]
            if v < lo[a]:
                lo[a] = v
            elif v > hi[a]:
                hi[a] = v
    return lo, hi


@njit(cache=True, inline="always")
def cell_index(x, y, z, origin, cell, dims):  # pragma: no cover - compiled
    """Dense index of the cell holding (x, y, z), clamped into the box (only box points are bucketed)."""
    i = min(max(int(math.floor((x - origin[0]) / cell)), 0), dims[0] - 1)
    j = min(max(int(math.floor((y - origin[1]) / cell)), 0), dims[1] - 1)
    k = min(max(int(math.floor((z - origin[2]) / cell)), 0), dims[2] - 1)
    return (i * dims[1] + j) * dims[2] + k


@njit(cache=True)
def _bucket3(pts, origin, cell, dims):  # pragma: no cover - compiled
    n = pts.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    key = np.empty(n, np.int64)
    starts = np.zeros(ncell + 1, np.int64)
    for p in range(n):
        c = cell_index(pts[p, 0], pts[p, 1], pts[p, 2], origin, cell, dims)
        key[p] = c
        starts[c + 1] += 1
    for c in range(ncell):
        starts[c + 1] += starts[c]
    fill = starts[:-1].copy()
    order = np.empty(n, np.int64)
    for p in range(n):  # ascending point index within a cell
        order[fill[key[p]]] = p
        fill[key[p]] += 1
    cell_points = np.empty((n, 3))
    for q in range(n):
        o = order[q]
        cell_points[q, 0], cell_points[q, 1], cell_points[q, 2] = pts[o, 0], pts[o, 1], pts[o, 2]
    return starts, order, cell_points


#: margin (m) on the geometric cell bounds of the searches: a point's cell is floor((p − origin) / cell) in floating
#: point, so its box is known to ~1e-14 m; distances within this of a bound are treated as inside it
_MARGIN = 1e-9


@njit(cache=True, inline="always")
def _reach(x, lo, r, cell):  # pragma: no cover - compiled
    """Distance from coordinate *x* to the faces of shells 0 … r about its cell (lower corner *lo* of that cell)."""
    a = lo - r * cell
    return min(x - a, a + (2 * r + 1) * cell - x)


@njit(cache=True, inline="always")
def _gap(x, lo, d, cell):  # pragma: no cover - compiled
    """Distance from coordinate *x* to the interval of the cell *d* steps from its own (lower corner *lo*)."""
    if d > 0:
        return max(lo + d * cell - x - _MARGIN, 0.0)
    if d < 0:
        return max(x - (lo + (d + 1) * cell) - _MARGIN, 0.0)
    return 0.0


@njit(cache=True, inline="always")
def _visit(c, x, y, z, cpts, order, starts, k, b2, bd, bi):  # pragma: no cover - compiled
    """Insert the points of cell *c* closer than the current k-th (and than √b2) into the sorted k best."""
    lim = min(bd[k - 1], b2)
    for q in range(starts[c], starts[c + 1]):
        ux = cpts[q, 0] - x
        uy = cpts[q, 1] - y
        uz = cpts[q, 2] - z
        d2 = ux * ux + uy * uy + uz * uz
        if d2 < lim:
            insert_best(bd, bi, k, d2, order[q])
            lim = min(bd[k - 1], b2)


@njit(cache=True, inline="always")
def knn3(x, y, z, pts, cpts, origin, cell, dims, starts, order, k, bound, bd, bi, max_r=1 << 30):  # pragma: no cover - compiled
    """The *k* grid points nearest to (x, y, z) strictly closer than *bound* (``inf``: unbounded), nearest first:
    squared distances in ``bd[:k]`` and indices in ``bi[:k]`` (``inf`` / −1 past the last found). Exact: a cell
    is skipped when its box is farther than the k-th point found so far (or than *bound*), and the search stops
    once every unvisited cell is. It visits first the 2×2×2 cells around the query (its own and the nearer
    neighbour along each axis: every point within half a cell of the query is in them), then cubic shells of
    cells about its own. Returns False when it stopped at shell *max_r* before that."""
    ci = int(math.floor((x - origin[0]) / cell))
    cj = int(math.floor((y - origin[1]) / cell))
    ck = int(math.floor((z - origin[2]) / cell))
    lox, loy, loz = origin[0] + ci * cell, origin[1] + cj * cell, origin[2] + ck * cell
    for s in range(k):
        bd[s] = np.inf
        bi[s] = -1
    b2 = bound * bound
    nx, ny, nz = dims[0], dims[1], dims[2]
    # the 2×2×2 block: offsets 0 and s* along each axis
    sx = -1 if x - lox < 0.5 * cell else 1
    sy = -1 if y - loy < 0.5 * cell else 1
    sz = -1 if z - loz < 0.5 * cell else 1
    for a in range(2):
        di = a * sx
        if ci + di < 0 or ci + di >= nx:
            continue
        gx = _gap(x, lox, di, cell)
        for b in range(2):
            dj = b * sy
            if cj + dj < 0 or cj + dj >= ny:
                continue
            gy = _gap(y, loy, dj, cell)
            for e in range(2):
                dk = e * sz
                if ck + dk < 0 or ck + dk >= nz:
                    continue
                gz = _gap(z, loz, dk, cell)
                g2 = gx * gx + gy * gy + gz * gz
                if g2 < bd[k - 1] and g2 < b2:
                    _visit(((ci + di) * ny + cj + dj) * nz + ck + dk, x, y, z, cpts, order, starts, k, b2, bd, bi)
    rx = min(x - lox, lox + cell - x) + cell  # the block's faces: one cell beyond the query's own on the near side
    ry = min(y - loy, loy + cell - y) + cell
    rz = min(z - loz, loz + cell - z) + cell
    rx = min(rx, lox + cell - x if sx < 0 else x - lox)
    ry = min(ry, loy + cell - y if sy < 0 else y - loy)
    rz = min(rz, loz + cell - z if sz < 0 else z - loz)
    reach = min(rx, ry, rz) - _MARGIN
    if reach >= bound or (bi[k - 1] >= 0 and bd[k - 1] <= reach * reach):
        return True
    r = 1
    while True:
        for di in range(-r, r + 1):
            ei = di == -r or di == r
            if ci + di < 0 or ci + di >= nx:
                continue
            gx = _gap(x, lox, di, cell)
            gx2 = gx * gx
            in_x = r == 1 and (di == 0 or di == sx)
            for dj in range(-r, r + 1):
                ej = ei or dj == -r or dj == r
                if cj + dj < 0 or cj + dj >= ny:
                    continue
                gy = _gap(y, loy, dj, cell)
                gxy2 = gx2 + gy * gy
                if gxy2 >= bd[k - 1] or gxy2 >= b2:
                    continue
                in_xy = in_x and (dj == 0 or dj == sy)
                dk = -r
                while dk <= r:
                    step = 1 if ej else 2 * r
                    if ck + dk < 0 or ck + dk >= nz or (in_xy and (dk == 0 or dk == sz)):
                        dk += step
                        continue
                    gz = _gap(z, loz, dk, cell)
                    g2 = gxy2 + gz * gz
                    if g2 < bd[k - 1] and g2 < b2:
                        _visit(((ci + di) * ny + cj + dj) * nz + ck + dk, x, y, z, cpts, order, starts, k, b2, bd, bi)
                    dk += step
        reach = min(_reach(x, lox, r, cell), _reach(y, loy, r, cell), _reach(z, loz, r, cell)) - _MARGIN
        if reach >= bound or (bi[k - 1] >= 0 and bd[k - 1] <= reach * reach):
            break
        if ci - r <= 0 and ci + r >= nx - 1 and cj - r <= 0 and cj + r >= ny - 1 and ck - r <= 0 and ck + r >= nz - 1:
            break  # every cell of the grid visited
        if r >= max_r:
            return False
        r += 1
    return True


@njit(cache=True, inline="always")
def _rotate(app, aqq, apq, apr, aqr, vp0, vp1, vp2, vq0, vq1, vq2):  # pragma: no cover - compiled
    """One Jacobi rotation zeroing a_pq of a symmetric 3×3 (r the third index): the new a_pp, a_qq, a_pr, a_qr
    and eigenvector columns p, q."""
    theta = (aqq - app) / (2.0 * apq)
    t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    return (app - t * apq, aqq + t * apq, c * apr - s * aqr, s * apr + c * aqr,
            c * vp0 - s * vq0, c * vp1 - s * vq1, c * vp2 - s * vq2, s * vp0 + c * vq0, s * vp1 + c * vq1,
            s * vp2 + c * vq2)


@njit(cache=True, inline="always")
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):  # pragma: no cover - compiled
    """Unit eigenvector of the smallest eigenvalue of the symmetric 3×3 matrix, by cyclic Jacobi rotations
    (Golub & Van Loan §8.5) to machine precision, in scalars (no array per call)."""
    v00, v01, v02, v10, v11, v12, v20, v21, v22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0  # v_ij: row i, column j
    for _sweep in range(50):
        off = a01 * a01 + a02 * a02 + a12 * a12
        if off == 0.0 or off <= 1e-36 * (a00 * a00 + a11 * a11 + a22 * a22):
            break
        if a01 != 0.0:  # (p, q, r) = (0, 1, 2)
            a00, a11, a02, a12, v00, v10, v20, v01, v11, v21 = _rotate(a00, a11, a01, a02, a12,
                                                                       v00, v10, v20, v01, v11, v21)
            a01 = 0.0
        if a02 != 0.0:  # (0, 2, 1)
            a00, a22, a01, a12, v00, v10, v20, v02, v12, v22 = _rotate(a00, a22, a02, a01, a12,
                                                                       v00, v10, v20, v02, v12, v22)
            a02 = 0.0
        if a12 != 0.0:  # (1, 2, 0)
            a11, a22, a01, a02, v01, v11, v21, v02, v12, v22 = _rotate(a11, a22, a12, a01, a02,
                                                                       v01, v11, v21, v02, v12, v22)
            a12 = 0.0
    if a00 <= a11 and a00 <= a22:
        x, y, z = v00, v10, v20
    elif a11 <= a22:
        x, y, z = v01, v11, v21
    else:
        x, y, z = v02, v12, v22
    nv = math.sqrt(x * x + y * y + z * z)
    return x / nv, y / nv, z / nv


@njit(cache=True, inline="always")
def normal_at(p, normals, pts, cpts, origin, cell, dims, starts, order, k, bd, bi):  # pragma: no cover - compiled
    """PCA normal of grid point *p* from its *k* nearest grid points (itself included), as estimate_normals."""
    knn3(pts[p, 0], pts[p, 1], pts[p, 2], pts, cpts, origin, cell, dims, starts, order, k, np.inf, bd, bi)
    mx = my = mz = 0.0
    for s in range(k):
        o = bi[s]
        mx += pts[o, 0]
        my += pts[o, 1]
        mz += pts[o, 2]
    mx /= k
    my /= k
    mz /= k
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for s in range(k):
        o = bi[s]
        ux, uy, uz = pts[o, 0] - mx, pts[o, 1] - my, pts[o, 2] - mz
        a00 += ux * ux
        a01 += ux * uy
        a02 += ux * uz
        a11 += uy * uy
        a12 += uy * uz
        a22 += uz * uz
    normals[p, 0], normals[p, 1], normals[p, 2] = _smallest_eigenvector(a00, a01, a02, a11, a12, a22)


@njit(cache=True)
def normals_3d(index, normals, have, pts, cpts, origin, cell, dims, starts, order, k):  # pragma: no cover - compiled
    """Fill ``normals[p]`` for each p in *index* not yet *have* (k-neighbour PCA, k ≤ number of points)."""
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    for m in range(index.shape[0]):
        p = index[m]
        if not have[p]:
            normal_at(p, normals, pts, cpts, origin, cell, dims, starts, order, k, bd, bi)
            have[p] = True


@njit(cache=True)
def voxel_first_3d(pts, size):  # pragma: no cover - compiled
    """Indices of the first point of each voxel of edge *size* (``floor(p / size)``), in input order — the rows
    ``registration.voxel.voxel_downsample(points, size, "first")`` keeps — and the voxel index range
    ``(lo, hi)`` per axis (voxel_keys refuses spans it cannot pack)."""
    n = pts.shape[0]
    bits = 4
    while (1 << bits) < 2 * n:
        bits += 1
    mask = (1 << bits) - 1
    slots = np.full((1 << bits, 3), np.iinfo(np.int64).min, np.int64)  # the voxel (i, j, k) of each used slot
    keep = np.empty(n, np.int64)
    lo = np.full(3, np.iinfo(np.int64).max, np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, np.int64)
    m = 0
    for p in range(n):
        i = np.int64(math.floor(pts[p, 0] / size))
        j = np.int64(math.floor(pts[p, 1] / size))
        k = np.int64(math.floor(pts[p, 2] / size))
        lo[0], lo[1], lo[2] = min(lo[0], i), min(lo[1], j), min(lo[2], k)
        hi[0], hi[1], hi[2] = max(hi[0], i), max(hi[1], j), max(hi[2], k)
        hk = np.uint64(i * 73856093) ^ np.uint64(j * 19349663) ^ np.uint64(k * 83492791)
        h = np.int64((hk * _GOLDEN) >> np.uint64(64 - bits))
        while True:
            if slots[h, 0] == np.iinfo(np.int64).min:
                slots[h, 0], slots[h, 1], slots[h, 2] = i, j, k
                keep[m] = p
                m += 1
                break
            if slots[h, 0] == i and slots[h, 1] == j and slots[h, 2] == k:
                break
            h = (h + 1) & mask
    return keep[:m], lo, hi
