"""Nearest-neighbour correspondences of points that move between ICP iterations, searched again
only where the motion could have changed them.

A k = 2 search (within the bound B) at positions m⁰ gives the nearest distance d₁ and the second
d₂ (∞ when beyond B, so "≥ B"). A point moved by ε = ‖m − m⁰‖ changes each distance by at most ε
(triangle inequality), so with gate g it keeps its nearest neighbour and its side of the gate while

* inside the gate (d₁ < g):  ε < g − d₁  and  2ε < min(d₂, B) − d₁,
* outside the gate:          ε < min(d₁, B) − g.

Points within a margin τ (far above rounding) of these limits are searched again; the others keep
their match, which is exactly what a fresh search returns (the kd-tree search is exact). This is
the plain triangle-inequality bound; Nüchter, Lingemann & Hertzberg ("Cached k-d tree search for
ICP algorithms", 3DIM 2007) reuse the previous search differently (restarting from the cached leaf).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

Array = NDArray[np.float64]

__all__ = ["IncrementalMatcher", "pair_distances"]

# Safety margin (m) on the certified motion: distances are computed to ~1e-14 m, so a neighbour
# swap or a gate crossing closer than this to the limit is always searched again.
_TAU = 1e-9

# Below this many points a search costs mostly its fixed per-call overhead (~25 µs in scipy's cKDTree),
# so re-searching a subset saves little: the matcher then searches all points at once with k = 1.
INCREMENTAL_MIN_POINTS = 2000

# Below this many points per search, scipy's thread start/join costs more than a parallel search saves.
_PARALLEL_MIN_POINTS = 20000

# Search bound B as a multiple of the gate: a wider bound lets points outside the gate move further
# before they are searched again, at the price of a longer search for them.
_BOUND_FACTOR = 2.0


def pair_distances(moved: Array, matched: Array) -> Array:
    """Euclidean distances (m) of paired rows, computed as cKDTree does (bit for bit)."""
    diff = moved - matched
    return np.sqrt((diff * diff).sum(axis=1))


class IncrementalMatcher:
    """Gated nearest neighbours in a fixed kd-tree for a point set that moves (an ICP source).

    :meth:`match` returns the same indices as ``tree.query(moved, k=1, distance_upper_bound=gate)``
    (unmatched = ``tree.n``). With *incremental* it searches only the points whose certified region
    (module docstring) the motion left; otherwise it searches all of them, and a repeated call with
    the same *moved* array and gate returns the previous answer. *workers* are cKDTree threads for
    searches of ≥ 20000 points (smaller ones use one). Points ``(N, d)`` in the tree's frame (m).
    """

    def __init__(self, tree: cKDTree, workers: int = -1, incremental: bool = True) -> None:
        self.tree = tree
        self.workers = workers
        self.incremental = incremental
        self.searches = 0  # kd-tree calls so far
        self.searched_points = 0  # points searched so far
        self._at: Array | None = None  # positions of each point's last search (the array itself when not incremental)
        self._gate: float | None = None

    def _workers(self, n: int) -> int:
        return self.workers if n >= _PARALLEL_MIN_POINTS else 1

    def _search(self, points: Array, gate: float) -> tuple[Array, Array, Array, float]:
        bound = _BOUND_FACTOR * gate
        dist, idx = self.tree.query(points, k=2, distance_upper_bound=bound, workers=self._workers(len(points)))
        self.searches += 1
        self.searched_points += len(points)
        return dist[:, 0].copy(), dist[:, 1].copy(), idx[:, 0].copy(), bound

    @staticmethod
    def _limit(d1: Array, d2: Array, bound: Array, gate: float) -> Array:
        """Squared certified motion per point (−1 where there is none)."""
        inside = d1 < gate
        m = np.where(inside, np.minimum(gate - d1, 0.5 * (np.minimum(d2, bound) - d1)),
                     np.minimum(d1, bound) - gate) - _TAU
        return np.where(m > 0.0, m * m, -1.0)

    def match(self, moved: Array, gate: float) -> NDArray[np.intp]:
        """Index of the nearest tree point closer than *gate* to each row of *moved*, else ``tree.n``."""
        if not self.incremental:
            if moved is not self._at or gate != self._gate:
                self._i1 = self.tree.query(moved, k=1, distance_upper_bound=gate, workers=self._workers(len(moved)))[1]
                self._at, self._gate = moved, gate
                self.searches += 1
                self.searched_points += len(moved)
            return self._i1
        fresh = self._at is None or self._at.shape != moved.shape
        if fresh:
            self._d1, self._d2, self._i1, b = self._search(moved, gate)
            self._bound = np.full(len(moved), b)
            self._at = moved.copy()
        if gate != self._gate:
            self._lim = self._limit(self._d1, self._d2, self._bound, gate)
            self._gate = gate
        if not fresh:
            disp = moved - self._at
            sel = np.flatnonzero((disp * disp).sum(axis=1) >= self._lim)
            if len(sel):
                pts = moved.take(sel, axis=0)
                d1, d2, i1, b = self._search(pts, gate)
                self._at[sel], self._d1[sel], self._d2[sel], self._i1[sel], self._bound[sel] = pts, d1, d2, i1, b
                self._lim[sel] = self._limit(d1, d2, np.full(len(sel), b), gate)
        return np.where(self._d1 < gate, self._i1, self.tree.n)
