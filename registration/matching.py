"""Nearest-neighbour correspondences of points that move between ICP iterations, searched again
only where the motion could have changed them.

Each search (within the bound B) caches a point's K nearest target points at its position m⁰: every
target point closer than ρ = min(d_K, B) to m⁰, where d₁ ≤ … ≤ d_K are their distances (ρ = B when fewer
than K lie within it). After the point moved by ε = ‖m − m⁰‖, a neighbour within the gate g is at most
min(g, d₁ + ε) from m (the old nearest one is at most d₁ + ε away), hence at most min(g, d₁ + ε) + ε from
m⁰ (triangle inequality). While that is below ρ, the nearest neighbour within the gate, if any, is among
the cached points, and comparing their distances at m gives exactly what a fresh search returns (the
kd-tree search is exact); otherwise the point is searched again. Points within a margin τ (far above
rounding) of the limit are searched again too. This is the plain triangle-inequality bound; Nüchter,
Lingemann & Hertzberg ("Cached k-d tree search for ICP algorithms", 3DIM 2007) reuse the previous
search differently (restarting from the cached leaf). The candidate comparison is compiled
(:func:`registration.kernels.cached_nearest`).
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

# Neighbours cached per point (K): a point keeps its answer without a search while its motion stays within
# about half the gap between its nearest and its K-th neighbour; more cost each search and each check.
_CACHED = 8


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
        self._data = np.ascontiguousarray(tree.data, dtype=np.float64)

    def _workers(self, n: int) -> int:
        return self.workers if n >= _PARALLEL_MIN_POINTS else 1

    def _search(self, points: Array, gate: float) -> tuple[Array, Array, NDArray[np.intp]]:
        """Nearest distance, cache radius ρ and the cached candidates ``(N, K)`` of *points* (module docstring)."""
        bound = _BOUND_FACTOR * gate
        k = max(2, min(_CACHED, self.tree.n))
        dist, idx = self.tree.query(points, k=k, distance_upper_bound=bound, workers=self._workers(len(points)))
        self.searches += 1
        self.searched_points += len(points)
        return dist[:, 0].copy(), np.minimum(dist[:, -1], bound), np.ascontiguousarray(idx, dtype=np.intp)

    def match(self, moved: Array, gate: float) -> NDArray[np.intp]:
        """Index of the nearest tree point closer than *gate* to each row of *moved*, else ``tree.n``."""
        if not self.incremental:
            if moved is not self._at or gate != self._gate:
                self._i1 = self.tree.query(moved, k=1, distance_upper_bound=gate, workers=self._workers(len(moved)))[1]
                self._at, self._gate = moved, gate
                self.searches += 1
                self.searched_points += len(moved)
            return self._i1
        n = self.tree.n
        if self._at is None or self._at.shape != moved.shape:
            self._d1, self._radius, self._cand = self._search(moved, gate)
            self._at = np.array(moved, dtype=np.float64, order="C")
            return np.where(self._d1 < gate, self._cand[:, 0], n)
        from .kernels import cached_nearest

        out = np.empty(len(moved), dtype=np.intp)
        cached_nearest(np.ascontiguousarray(moved, dtype=np.float64), self._at, self._d1, self._radius, self._cand,
                       self._data, float(gate), _TAU, out)
        sel = np.flatnonzero(out < 0)
        if len(sel):
            pts = moved.take(sel, axis=0)
            d1, radius, cand = self._search(pts, gate)
            self._at[sel], self._d1[sel], self._radius[sel], self._cand[sel] = pts, d1, radius, cand
            out[sel] = np.where(d1 < gate, cand[:, 0], n)
        return out
