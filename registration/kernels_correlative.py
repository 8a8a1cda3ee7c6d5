"""Compiled (numba) correlative scan matching: the score of rotated scans on a likelihood grid at many offsets,
and the depth-first branch and bound over a grid pyramid (Olson 2009; Hess et al. 2016, Algorithm 3), the loop
forms of :mod:`registration.correlative`'s numpy search."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["rotated_cells", "score_candidates", "branch_and_bound", "stamp_field"]


@njit(cache=True)
def rotated_cells(pts, cos_t, sin_t, x0, y0, origin_x, origin_y, resolution):  # pragma: no cover - compiled
    """Cells ``(R, N, 2)`` (int32) of the points *pts* ``(N, 2)`` turned by each of R headings (their cosines and
    sines) and moved to (*x0*, *y0*), on a grid whose cell (0, 0) starts at the origin: the same arithmetic,
    in the same order, as :func:`registration.correlative._cells`' numpy form, without its temporaries."""
    R, N = cos_t.shape[0], pts.shape[0]
    out = np.empty((R, N, 2), np.int32)
    for r in range(R):
        c, s = cos_t[r], sin_t[r]
        for p in range(N):
            x = c * pts[p, 0] - s * pts[p, 1] + x0
            y = s * pts[p, 0] + c * pts[p, 1] + y0
            out[r, p, 0] = np.int32(np.floor((x - origin_x) / resolution))
            out[r, p, 1] = np.int32(np.floor((y - origin_y) / resolution))
    return out


@njit(cache=True)
def stamp_field(flat, occ, offsets, values):  # pragma: no cover - compiled
    """``flat[c + offsets[k]] = max(flat[c + offsets[k]], values[k])`` for every occupied flat cell c of *occ*
    and every stamp offset k: :func:`registration.correlative.likelihood_field`'s maximum of stamps."""
    for k in range(offsets.shape[0]):
        off, v = offsets[k], values[k]
        for c in occ:
            if flat[c + off] < v:
                flat[c + off] = v


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


@njit(cache=True, inline="always")
def _score_children(grid, cells, r, x, y, half, out):  # pragma: no cover - compiled
    """:func:`_score_at` of the four children of a block, offsets (x, y), (x, y + half), (x + half, y) and
    (x + half, y + half), into *out* in that order: one pass over the points for all four (the points'
    cells are read once; ~1.5× faster than four passes on the loop-closure searches)."""
    H, W = grid.shape
    n = cells.shape[1]
    a0 = a1 = a2 = a3 = 0
    for p in range(n):
        cx = cells[r, p, 0] + x
        cy = cells[r, p, 1] + y
        i0, i1 = min(max(cx, 0), H - 1), min(max(cx + half, 0), H - 1)
        j0, j1 = min(max(cy, 0), W - 1), min(max(cy + half, 0), W - 1)
        a0 += grid[i0, j0]
        a1 += grid[i0, j1]
        a2 += grid[i1, j0]
        a3 += grid[i1, j1]
    out[0] = float(a0) / n / 255.0
    out[1] = float(a1) / n / 255.0
    out[2] = float(a2) / n / 255.0
    out[3] = float(a3) / n / 255.0


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
                     ex_r, ex_x, ex_y, ex_dr, ex_dxy, first=False):  # pragma: no cover - compiled
    """Depth-first branch and bound of ``registration.correlative.match`` (Hess et al. 2016, Algorithm 3).

    *grids* ``(L, H, W)`` uint8: the pyramid's max-pooled levels; *cells* ``(R, N, 2)``: the scan's
    cells at each of R rotations. Candidates are (rotation, offset) with offsets in [−w, w]² cells:
    level-*top* blocks of 2^top × 2^top offsets from −w, each split into its four children down to
    level 0 (single offsets). Children are visited best first, so the first leaves reached are good
    and the bound prunes the rest; a block is expanded only when its bound (the max-pooled score)
    exceeds *best*. Returns the best (score, rotation, ox, oy) strictly above the starting *best*,
    or the starting values when nothing in the window beats it. With *ex_dxy* ≥ 0 the candidates within
    *ex_dr* rotations and *ex_dxy* cells (in x and in y) of (*ex_r*, *ex_x*, *ex_y*) are excluded: the
    best pose elsewhere, for the uniqueness test of a match (blocks wholly inside are skipped). With *first*
    the search ends at the first candidate above the starting *best*, which is then returned: whether any
    candidate beats it, decided without proving which one is the best (the same answer, since every
    candidate above the bound is reached unless one was found before)."""
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
    children = np.empty(4)
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
            if first:
                break
            continue
        half = 1 << (lv - 1)
        _score_children(grids[lv - 1], cells, r, x, y, half, children)
        k = 0
        for dx in range(2):
            for dy in range(2):
                x2, y2 = x + dx * half, y + dy * half
                if x2 > w or y2 > w:
                    continue
                sc = children[2 * dx + dy]
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
