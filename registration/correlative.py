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

from core import geometry as G
from core.errors import DegenerateInputError

from . import kernels_correlative as kernels  # compiled loops: the per-point gathers are the search's whole cost

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
        lo = G.bounds(pts)[0]
        self.origin = lo - pad * resolution
        cells = np.floor((pts - self.origin) / resolution).astype(np.int64)
        shape = tuple(int(s) for s in G.bounds(cells)[1] + pad + 1)
        # Stored as bytes (likelihood × 255): the pyramid of a 30 m local map at 5 cm is ~2.5 MB.
        # One (levels + 1, H, W) array: level h is grids[h].
        self.grids = np.empty((self.levels + 1,) + shape, dtype=np.uint8)
        self.grids[0] = likelihood_field(cells, shape, resolution, sigma)
        for h in range(1, self.levels + 1):
            prev, g, s = self.grids[h - 1], self.grids[h], 2 ** (h - 1)
            g[:] = prev
            g[:-s, :] = np.maximum(g[:-s, :], prev[s:, :])
            g[:, :-s] = np.maximum(g[:, :-s], g[:, s:])

    @property
    def shape(self) -> tuple[int, int]:
        """Cells along x and y (every level has the same shape)."""
        return self.grids.shape[1:]  # type: ignore[return-value]

    def cells(self, points: Array) -> NDArray[np.int64]:
        """Integer cell coordinates (…, 2) of points (…, 2) in the target frame."""
        return np.floor((points - self.origin) / self.resolution).astype(np.int64)

    def score_candidates(self, level: int, cells: NDArray[np.integer], rot: NDArray[np.int64],
                         offsets: NDArray[np.int64]) -> NDArray[np.float64]:
        """Mean over the scan's points of the level-*level* grid at ``cells[rot[c]] + offsets[c]`` for each
        candidate c: the exact score at level 0, an upper bound for the 2^level block of offsets above."""
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
    field = np.zeros(shape, dtype=np.uint8)
    flat = field.reshape(-1)
    seen = np.zeros(flat.shape, dtype=bool)  # the occupied cells, each once and in order (np.unique's, without its sort)
    seen[cells[:, 0] * shape[1] + cells[:, 1]] = True
    occ = np.flatnonzero(seen)
    offsets, values = [], []
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            d = np.sqrt(float(di * di + dj * dj)) * resolution
            if d > 3.0 * sigma:
                continue
            values.append(np.uint8(np.rint(np.exp(-0.5 * (d / sigma) ** 2) * 255.0)))
            offsets.append(di * shape[1] + dj)
    kernels.stamp_field(flat, occ, np.array(offsets, dtype=np.int64), np.array(values, dtype=np.uint8))
    return field


def angular_step(points: Array, resolution: float) -> float:
    """Rotation step that moves the farthest point (95th percentile range) by at most one cell (Hess et al. 2016, Eq. 7)."""
    rng = np.hypot(points[:, 0], points[:, 1])
    # np.percentile's linear interpolation, from a partial sort (the full call costs ~0.1 ms, paid for every one of thousands of candidates)
    pos = 0.95 * (len(rng) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(rng) - 1)
    part = np.partition(rng, (lo, hi))
    r = float(part[lo] + (pos - lo) * (part[hi] - part[lo]))
    r = max(r, 2.0 * resolution)
    return float(np.arccos(1.0 - resolution**2 / (2.0 * r**2)))


@dataclass(frozen=True)
class SearchGrid:
    """The discretised window of :func:`match`: the scan's cells ``(R, N, 2)`` at each of the R headings
    ``thetas`` (the guess's is index *k*), offsets in [−w, w]² cells around the guess's (x0, y0)."""

    x0: float
    y0: float
    thetas: Array
    k: int
    cells: NDArray[np.int32]
    w: int


def search_grid(scan_points: Array, pyramid: LikelihoodPyramid, guess: Array, window_m: float,
                window_rad: float) -> SearchGrid:
    """The candidates :func:`match` searches: headings ±*window_rad* around the planar 4×4 *guess* at the
    angular step of Hess et al. 2016 (Eq. 7), offsets ±*window_m* at the pyramid's resolution."""
    pts, (x0, y0, th0), step = _scan_at(scan_points, pyramid, guess, "correlative matching")
    res = pyramid.resolution
    k = int(np.ceil(window_rad / step))
    thetas = th0 + step * np.arange(-k, k + 1)
    return SearchGrid(float(x0), float(y0), thetas, k, _cells(pts, pyramid, x0, y0, thetas), int(np.ceil(window_m / res)))


def _scan_at(scan_points: Array, pyramid: LikelihoodPyramid, pose: Array, what: str) -> tuple[Array, Array, float]:
    """The scan's points ``(N, 2)``, the planar 4×4 *pose* as (x, y, θ) and the angular step of the
    pyramid's cells for this scan; DegenerateInputError (*what* needs …) under 3 points."""
    pts = np.asarray(scan_points, dtype=np.float64)[:, :2]
    if len(pts) < 3:
        raise DegenerateInputError(f"{what} needs at least 3 scan points")
    return pts, G.matrix_to_xytheta(np.asarray(pose)), angular_step(pts, pyramid.resolution)


def _cells(pts: Array, pyramid: LikelihoodPyramid, x0: float, y0: float, thetas: Array) -> NDArray[np.int32]:
    """Cells ``(R, N, 2)`` of the scan points *pts* ``(N, 2)`` turned by each of the R *thetas* and moved to (x0, y0)."""
    # Cosines and sines from numpy (numba's may differ in the last bit), the rest compiled; int32 halves the
    # gathers' index traffic.
    return kernels.rotated_cells(np.ascontiguousarray(pts), np.cos(thetas), np.sin(thetas), float(x0), float(y0),
                                 float(pyramid.origin[0]), float(pyramid.origin[1]), pyramid.resolution)


def match(scan_points: Array, pyramid: LikelihoodPyramid, guess: Array, window_m: float, window_rad: float,
          min_score: float = 0.0, min_gain: float = 0.0) -> CorrelativeResult:
    """Best ``target_T_scan`` within ±*window_m* (x and y) and ±*window_rad* of the planar 4×4 *guess*.

    Exact over the discretised window (:func:`search_grid`): depth-first branch and bound, children
    best first (Hess et al. 2016, Algorithm 3), compiled (:func:`registration.kernels_correlative.branch_and_bound`);
    a block is expanded only when its max-pooled bound beats the best score found so far.
    *min_score* starts the bound there (Cartographer's ``min_score``, Hess et al. 2016 §V-C): blocks
    that cannot reach it are never expanded; when no pose in the window scores above it (nor the
    guess), the result is the guess with its score, which is then below *min_score*.
    *min_gain*: a pose counts only when it beats the guess's score by this much (a caller that starts
    from the search's pose only then need not see smaller gains). When the guess reaches *min_score*
    the bound starts at guess score + *min_gain*, so the result is the window's maximum when that is
    at least this high and the guess otherwise; the rest is pruned without being expanded.
    """
    g = search_grid(scan_points, pyramid, guess, window_m, window_rad)
    top = _top_level(pyramid, g)
    guess_score = float(pyramid.score_candidates(0, g.cells, np.array([g.k]), np.zeros((1, 2), np.int64))[0])
    floor = max(guess_score, min_score)
    if min_gain > 0 and guess_score >= min_score:
        floor = guess_score + min_gain - 1e-12  # a maximum of exactly guess + min_gain still counts
    best, best_rot, ox, oy = kernels.branch_and_bound(pyramid.grids, g.cells, top, g.w, floor, g.k, 0, 0,
                                                      0, 0, 0, 0, -1, False)
    if best_rot == g.k and ox == 0 and oy == 0:  # nothing beat the guess (or min_score)
        return CorrelativeResult(np.asarray(guess, dtype=np.float64).copy(), guess_score, guess_score)
    res = pyramid.resolution
    T = G.xytheta_to_matrix(g.x0 + ox * res, g.y0 + oy * res, g.thetas[best_rot])
    return CorrelativeResult(T, float(best), guess_score)


def _top_level(pyramid: LikelihoodPyramid, g: SearchGrid) -> int:
    """The coarsest level worth starting from: a level below that already spans the window in one block."""
    top = pyramid.levels
    while top > 0 and 2 ** (top - 1) >= 2 * g.w + 1:
        top -= 1
    return top


def best_elsewhere(scan_points: Array, pyramid: LikelihoodPyramid, guess: Array, window_m: float, window_rad: float,
                   pose: Array, radius_m: float, radius_rad: float, min_score: float, *, first: bool = False) -> float | None:
    """The best score above *min_score* in the window of :func:`match` around *guess*, leaving out the
    poses within *radius_m* (in x and in y) and *radius_rad* of the planar 4×4 *pose*; None when no pose
    elsewhere reaches *min_score* (the bound prunes the rest). A match is unique when nothing elsewhere
    scores almost as well: the ratio test of place recognition (Lowe, IJCV 2004, §7.1), here over the
    correlative search window. With *first* the score of the first pose found above *min_score* (not
    necessarily the best): a test that only asks whether one exists gets the same answer sooner."""
    g = search_grid(scan_points, pyramid, guess, window_m, window_rad)
    x, y, th = G.matrix_to_xytheta(np.asarray(pose))
    step = float(g.thetas[1] - g.thetas[0]) if len(g.thetas) > 1 else 1.0
    res = pyramid.resolution
    ex = (int(round((th - g.thetas[0]) / step)), int(round((x - g.x0) / res)), int(round((y - g.y0) / res)),
          int(np.ceil(radius_rad / step)), int(np.ceil(radius_m / res)))
    floor = float(min_score) - 1e-12
    best, _, _, _ = kernels.branch_and_bound(pyramid.grids, g.cells, _top_level(pyramid, g), g.w, floor, -1, 0, 0, *ex, first)
    return float(best) if best > floor else None


def score_at(scan_points: Array, pyramid: LikelihoodPyramid, pose: Array) -> float:
    """The correlative score (mean likelihood of the scan's points, 0–1) of one planar 4×4 *pose*."""
    pts = np.asarray(scan_points, dtype=np.float64)[:, :2]
    if len(pts) == 0:
        return 0.0
    x, y, th = G.matrix_to_xytheta(np.asarray(pose))
    c, s = np.cos(th), np.sin(th)
    moved = np.stack([c * pts[:, 0] - s * pts[:, 1] + x, s * pts[:, 0] + c * pts[:, 1] + y], axis=-1)
    cells = pyramid.cells(moved[None]).astype(np.int32)
    return float(pyramid.score_candidates(0, cells, np.zeros(1, np.int64), np.zeros((1, 2), np.int64))[0])


def ambiguity(scan_points: Array, pyramid: LikelihoodPyramid, pose: Array, window_m: float, ratio: float,
              radius_cells: int = 3, headings: int = 2) -> Array:
    """How far the scan's score surface lets its pose slide: the second moment ``(3, 3)`` about the planar
    4×4 *pose* of the poses within ±*window_m* (x and y, cells of the pyramid) and ±*headings* angular
    steps whose score reaches *ratio* × the best of them, in the right-perturbation tangent of *pose*
    (δ = (Rᵀ Δt, Δθ)); zero when every such pose lies within *radius_cells* cells (and the heading steps)
    of *pose*, i.e. the surface has one sharp peak there.

    The registration's Fisher information is the curvature of the one minimum ICP reached; in a corridor
    that minimum is sharp across the corridor and every shift along it scores about as well, so a step
    matched a metre along it still claims centimetres. The level set of the correlative score surface
    (Olson, "Real-time correlative scan matching", ICRA 2009, §IV: the covariance of the match from the
    cost surface) shows the slide; its second moment about *pose* covers a second peak as well."""
    pts, (x0, y0, th0), step = _scan_at(scan_points, pyramid, pose, "the score surface")
    res = pyramid.resolution
    thetas = th0 + step * np.arange(-headings, headings + 1)
    cells = _cells(pts, pyramid, x0, y0, thetas)
    w = int(np.ceil(window_m / res))
    o = np.arange(-w, w + 1)
    ox, oy = np.meshgrid(o, o, indexing="ij")
    n = ox.size
    rot = np.repeat(np.arange(len(thetas), dtype=np.int64), n)
    offsets = np.tile(np.stack([ox.ravel(), oy.ravel()], axis=1), (len(thetas), 1)).astype(np.int64)
    scores = pyramid.score_candidates(0, cells, rot, offsets)
    near = scores >= ratio * scores.max()
    if np.abs(offsets[near]).max() <= radius_cells:  # near holds the best pose at least
        return np.zeros((3, 3))
    d = offsets[near] * res
    R0 = G.xytheta_to_matrix(0.0, 0.0, th0)[:2, :2]
    delta = np.column_stack([d @ R0, thetas[rot[near]] - th0])  # rows Rᵀd: the right-perturbation translation
    return delta.T @ delta / len(delta)
