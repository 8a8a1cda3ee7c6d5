"""Correlative 2D scan matching by branch and bound over a max-pooled likelihood-field pyramid.

Global search of a window of (x, y, θ) for the pose that puts a scan's points on a target's
likelihood field: Olson, "Real-time correlative scan matching", ICRA 2009 (§III, multi-resolution
search), in the depth-bounded form of Hess et al., "Real-time loop closure in 2D LIDAR SLAM",
ICRA 2016 (§V-B/C: precomputed grids of maxima over 2^h × 2^h blocks bound every translation in a
block, Eq. 14–15; angular step from the farthest point, Eq. 7). ICP converges only from inside its
basin (a few tens of cm); this finds the basin first, e.g. for a revisit whose estimate is off by
a metre along a corridor.

Frames: target points and the searched pose are in the target's frame; scan points in the scan's
sensor frame. Units: metres and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import geometry as G
from .errors import DegenerateInputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class CorrelativeResult:
    """Best pose ``target_T_scan`` in the window, its score (mean likelihood of the scan's points, in
    [0, 1]) and the score at the initial guess."""

    transform: Array
    score: float
    guess_score: float


class LikelihoodPyramid:
    """Likelihood field of target points (stored ×255 as uint8), exp(−d²/2σ²) with d the distance to the nearest point's cell
    (Thrun et al., Probabilistic Robotics §6.4), and its max-pooled levels: level h holds, at cell c,
    the maximum over cells c … c + 2^h − 1 in both axes (Hess et al. 2016, Eq. 14)."""

    def __init__(self, points: Array, resolution: float = 0.05, sigma: float = 0.05, levels: int = 6) -> None:
        pts = np.asarray(points, dtype=np.float64)[:, :2]
        if len(pts) == 0:
            raise DegenerateInputError("correlative matching needs target points")
        if resolution <= 0 or sigma <= 0 or levels < 0:
            raise ValueError("resolution and sigma must be positive, levels non-negative")
        self.resolution = float(resolution)
        self.levels = int(levels)
        reach = int(np.ceil(3.0 * sigma / resolution))
        pad = reach + 2**self.levels + 1  # zero border: clipped indices read 0 at every level
        lo = pts.min(axis=0)
        self.origin = lo - pad * resolution
        cells = np.floor((pts - self.origin) / resolution).astype(np.int64)
        shape = tuple(int(s) for s in cells.max(axis=0) + pad + 1)
        # Stored as bytes (likelihood × 255): the pyramid of a 30 m local map at 5 cm is ~2.5 MB.
        self.grids = [likelihood_field(cells, shape, resolution, sigma)]
        for h in range(1, self.levels + 1):
            prev, s = self.grids[-1], 2 ** (h - 1)
            g = prev.copy()
            g[:-s, :] = np.maximum(g[:-s, :], prev[s:, :])
            g[:, :-s] = np.maximum(g[:, :-s], g[:, s:])
            self.grids.append(g)

    @property
    def shape(self) -> tuple[int, int]:
        """Cells along x and y (every level has the same shape)."""
        return self.grids[0].shape  # type: ignore[return-value]

    def cells(self, points: Array) -> NDArray[np.int64]:
        """Integer cell coordinates (…, 2) of points (…, 2) in the target frame."""
        return np.floor((points - self.origin) / self.resolution).astype(np.int64)

    def score_candidates(self, level: int, cells: NDArray[np.integer], rot: NDArray[np.int64],
                         offsets: NDArray[np.int64]) -> NDArray[np.float64]:
        """Mean over the scan's points of the level-*level* grid at ``cells[rot[c]] + offsets[c]`` for each
        candidate c: the exact score at level 0, an upper bound for the 2^level block of offsets above."""
        from . import kernels  # compiled loop: the per-point gather is the search's whole cost

        return kernels.score_candidates(self.grids[level], cells, np.ascontiguousarray(rot, dtype=np.int64),
                                        np.ascontiguousarray(offsets, dtype=np.int64))


def likelihood_field(cells: NDArray[np.int64], shape: tuple[int, int], resolution: float, sigma: float) -> NDArray[np.uint8]:
    """``rint(255 · exp(−d²/2σ²))`` (0 beyond 3σ) on a grid of *shape*, d (m) the distance from each cell
    to the nearest of the occupied *cells* ``(N, 2)`` (which lie at least ⌈3σ/resolution⌉ cells inside).

    The value falls with distance, so the field is the maximum over occupied cells of a stamp of
    the offsets within 3σ — the same numbers as a Euclidean distance transform of the whole grid
    (bit for bit: the same float operations on the same integer offsets), at a cost in the
    occupied cells, not the grid's area."""
    reach = int(np.ceil(3.0 * sigma / resolution))
    occ = np.unique(cells[:, 0] * shape[1] + cells[:, 1])
    field = np.zeros(shape, dtype=np.uint8)
    flat = field.reshape(-1)
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            d = np.sqrt(float(di * di + dj * dj)) * resolution
            if d > 3.0 * sigma:
                continue
            v = np.uint8(np.rint(np.exp(-0.5 * (d / sigma) ** 2) * 255.0))
            at = occ + (di * shape[1] + dj)  # each cell once per offset: plain fancy assignment
            flat[at] = np.maximum(flat[at], v)
    return field


def angular_step(points: Array, resolution: float) -> float:
    """Rotation step that moves the farthest point (95th percentile range) by at most one cell (Hess et al. 2016, Eq. 7)."""
    r = float(np.percentile(np.hypot(points[:, 0], points[:, 1]), 95))
    r = max(r, 2.0 * resolution)
    return float(np.arccos(1.0 - resolution**2 / (2.0 * r**2)))


def match(scan_points: Array, pyramid: LikelihoodPyramid, guess: Array, window_m: float, window_rad: float,
          max_candidates: int = 200_000, greedy_descents: int = 4, min_score: float = 0.0,
          min_gain: float = 0.0) -> CorrelativeResult:
    """Best ``target_T_scan`` within ±*window_m* (x and y) and ±*window_rad* of the planar 4×4 *guess*.

    Exact over the discretised window: breadth-first branch and bound; the lower bound is the best
    score reached by greedy descents from the most promising blocks of each level, and blocks whose
    max-pooled bound cannot beat it are dropped. *max_candidates* bounds the memory of one gather.
    *min_score* starts the bound there (Cartographer's ``min_score``, Hess et al. 2016 §V-C): blocks
    that cannot reach it are never expanded; when no pose in the window scores above it (nor the
    guess), the result is the guess with its score, which is then below *min_score*.
    *min_gain*: a pose counts only when it beats the guess's score by this much (a caller that starts
    from the search's pose only then need not see smaller gains). When the guess reaches *min_score*
    the bound starts at guess score + *min_gain*, so the result is the window's maximum when that is
    at least this high and the guess otherwise; the rest is pruned without being expanded.
    """
    pts = np.asarray(scan_points, dtype=np.float64)[:, :2]
    if len(pts) < 3:
        raise DegenerateInputError("correlative matching needs at least 3 scan points")
    x0, y0, th0 = G.matrix_to_xytheta(np.asarray(guess))
    res = pyramid.resolution
    step = angular_step(pts, res)
    k = int(np.ceil(window_rad / step))
    thetas = th0 + step * np.arange(-k, k + 1)
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    rotated = np.stack([c * pts[:, 0] - s * pts[:, 1] + x0, s * pts[:, 0] + c * pts[:, 1] + y0], axis=-1)
    cells = pyramid.cells(rotated).astype(np.int32)  # (R, N, 2); int32 halves the gathers' index traffic
    w = int(np.ceil(window_m / res))

    top = pyramid.levels
    while top > 0 and 2 ** (top - 1) >= 2 * w + 1:
        top -= 1
    h = 2**top
    grid = np.arange(-w, w + 1, h)
    ox, oy = np.meshgrid(grid, grid, indexing="ij")
    base = np.stack([ox.ravel(), oy.ravel()], axis=1)
    rot = np.repeat(np.arange(len(thetas)), len(base))
    off = np.tile(base, (len(thetas), 1))

    guess_score = float(pyramid.score_candidates(0, cells, np.array([k]), np.zeros((1, 2), np.int64))[0])
    children = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.int64)

    def descend(level: int, r: NDArray[np.int64], o: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Greedy descents from blocks (r[m], o[m]) at *level* (> 0) along the best child to level 0:
        reachable scores (lower bounds) and their offsets."""
        for lv in range(level - 1, -1, -1):
            o_c = o[:, None, :] + children[None] * 2**lv  # (m, 4, 2)
            sc = pyramid.score_candidates(lv, cells, np.repeat(r, 4), o_c.reshape(-1, 2)).reshape(-1, 4)
            sc[~(o_c <= w).all(axis=2)] = -1.0
            pick = np.argmax(sc, axis=1)
            o = o_c[np.arange(len(o)), pick]
        return sc[np.arange(len(o)), pick], o

    floor = max(guess_score, min_score)
    if min_gain > 0 and guess_score >= min_score:
        floor = guess_score + min_gain - 1e-12  # a maximum of exactly guess + min_gain still counts
    best, best_rot, best_off = floor, k, np.zeros(2, np.int64)
    bounds = pyramid.score_candidates(top, cells, rot, off)
    chunk = max(1, max_candidates // 4)
    # Breadth-first branch and bound; at each level the most promising blocks are first descended
    # greedily so that the lower bound is tight before the level is pruned.
    for level in range(top, -1, -1):
        if level < top:
            off = (off[:, None, :] + children[None] * 2**level).reshape(-1, 2)
            rot = np.repeat(rot, 4)
            keep = (off <= w).all(axis=1)
            off, rot = off[keep], rot[keep]
            bounds = np.concatenate([pyramid.score_candidates(level, cells, rot[i:i + chunk], off[i:i + chunk])
                                     for i in range(0, len(off), chunk)])
        if level > 0:
            top_m = np.argsort(bounds)[::-1][:greedy_descents]
            top_m = top_m[bounds[top_m] > best]
            if len(top_m):
                sc, o = descend(level, rot[top_m], off[top_m])
                m = int(np.argmax(sc))
                if sc[m] > best:
                    best, best_rot, best_off = float(sc[m]), int(rot[top_m[m]]), o[m]
        keep = bounds > best
        off, rot, bounds = off[keep], rot[keep], bounds[keep]
        if len(off) == 0:
            break
        if level == 0:
            i = int(np.argmax(bounds))
            best, best_rot, best_off = float(bounds[i]), int(rot[i]), off[i]

    if best_rot == k and not best_off.any():  # nothing beat the guess (or min_score)
        return CorrelativeResult(np.asarray(guess, dtype=np.float64).copy(), guess_score, guess_score)
    T = G.xytheta_to_matrix(x0 + best_off[0] * res, y0 + best_off[1] * res, thetas[best_rot])
    return CorrelativeResult(T, best, guess_score)
