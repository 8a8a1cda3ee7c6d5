"""How uncertain is each keyframe's position relative to the newest one? Along the graph, not the odometry.

A loop candidate's relative pose is only as certain as the chain of constraints that links it to
the new keyframe. "The uncertainty accumulated since the last closure" is that chain only when the
last closure was with the candidate's own pass: a robot just closed with its previous pass down a
corridor can meet the corridor's first pass, hundreds of keyframes older, a metre away from where the
estimate puts it, with a since-closure σ of centimetres, and every correct closure is gated out
(the measured case is in docs/LOOP_CLOSURE.md).

Here the chain is the most certain path in the graph of odometry, wheel and loop edges (Dijkstra,
as in the "graph distance" candidate gating of Olson 2009 and Bosse's Atlas), with the edge weight
the variance it adds to the new keyframe's position seen from the far end:

    w_e = tr Σ_t,e + tr Σ_r,e · ‖c_e − p_j‖²

(translation variance plus rotation variance times the squared lever arm from the edge's centre
c_e to the new keyframe p_j — first-order propagation of a heading error along the chain). The sum
along a path over-estimates the relative variance when parallel paths exist (they would only add
information), so gates built on it err on the permissive side; the verification tests then decide.

Independent errors per edge are not all the odometry makes. Scan matching along corridors and
miscalibrated wheels turn the heading by a rate that stays the same for hundreds of metres (measured on
the development set: 0.03–0.04 °/m over 200–800 m of path, 2–3 × the chain's own σ; docs/LOOP_CLOSURE.md),
and independent increments, whose σ grows with the square root of the path, cannot say so. The model
therefore adds a random constant (Gelb, *Applied Optimal Estimation*, 1974, §3.2; the systematic odometry
error of Borenstein & Feng, 1996): a heading rate b ~ N(0, σ_b²) per metre travelled on odometry edges,
common to the whole path. Along the same most certain path, with L = Σ ℓ_e its odometry length and
M = Σ ℓ_e ‖c_e − p_j‖ its lever-weighted length, b turns the far end by b·L and moves it by up to b·M:

    rotation variance += r (σ_b L)²,   position variance += d (σ_b M)²

(r, d the rotation and translation dimensions: every axis may carry all of it). Closure edges have no
length: a closure resets the drift, as it does on the robot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

Array = NDArray[np.float64]

__all__ = ["RelativeUncertainty", "NodeUncertainty"]

_PAIR_BASE = 1 << 31  # keyframe ids stay below it


@dataclass(frozen=True)
class NodeUncertainty:
    """Per keyframe, relative to the source keyframe: position variance (m², trace of the 2×2 or
    3×3 block) and rotation variance (rad², trace), along the most certain path of the graph.
    Keyframes farther than the search limit, or unreachable, carry the limit."""

    position_var: Array
    rotation_var: Array
    drift_position_var: Array | None = None  # the part of the above from the heading-rate term (None: 0)
    drift_rotation_var: Array | None = None

    def covariance(self, i: int, planar: bool) -> Array:
        """An isotropic ``(dof, dof)`` covariance of keyframe *i* relative to the source (translation first)."""
        d = 2 if planar else 3
        r = 1 if planar else 3
        return np.diag([self.position_var[i] / d] * d + [self.rotation_var[i] / r] * r)

    def without_drift(self) -> "NodeUncertainty":
        """The independent edge noise alone (the heading-rate term left out)."""
        if self.drift_position_var is None or self.drift_rotation_var is None:
            return self
        return NodeUncertainty(self.position_var - self.drift_position_var, self.rotation_var - self.drift_rotation_var)


@njit(cache=True)
def sum_to_root(acc: Array, up: NDArray[np.int64], root: int) -> Array:  # pragma: no cover - compiled
    """Each row of *acc* ``(K, c)`` summed with the rows of all its ancestors up the tree *up* (each node's
    parent; the *root*, and nodes hanging off nothing, point at *root*), by pointer doubling: each round
    adds the row the node points at and then points it at that row's target, until every pointer is at
    the root (log₂ of the depth rounds; the loop form of ``acc + where(up != root, acc[up], 0)``,
    ``up = up[up]``, the same additions in the same order)."""
    K, c = acc.shape
    up = up.copy()
    nxt = np.empty_like(up)
    cur, new = acc.copy(), np.empty_like(acc)
    while True:
        settled = True
        for v in range(K):
            nxt[v] = up[up[v]]
            settled = settled and nxt[v] == up[v]
        for v in range(K):
            u = up[v]
            for k in range(c):
                new[v, k] = cur[v, k] + (cur[u, k] if u != root else 0.0)
        cur, new = new, cur
        if settled:
            return cur
        up, nxt = nxt, up


class RelativeUncertainty:
    """The graph's edges with their covariances; :meth:`from_node` runs the search from one keyframe.

    Args:
        planar: 2D (3×3 covariances, x y θ) or 3D (6×6, translation first).
        limit_m2: position variance beyond which the search stops (keyframes farther get this value).
        drift_rad_per_m: σ_b of the random-constant heading rate of the odometry (module docstring); 0: none.
    """

    def __init__(self, planar: bool, limit_m2: float = 100.0, drift_rad_per_m: float = 0.0) -> None:
        self.planar = planar
        self.limit_m2 = float(limit_m2)
        self.drift = float(drift_rad_per_m)
        self.scale = 1.0  # every variance times this (≥ 1: the run's own closures found the model too sure, slam.loops.calibration)
        # Edges in arrays that double when full (read every keyframe: no list-to-array copy each time),
        # kept sorted by keyframe pair (newer end, then older end): a new keyframe's edges go in at or
        # near the end, so inserting in place is cheap and the search needs no sort.
        self._n = 0
        self._ends = np.zeros((64, 2), dtype=np.int64)  # (older, newer) keyframe of each edge
        self._var = np.zeros((64, 2))  # translation, rotation variance (traces)
        self._len = np.zeros(64)  # odometry length (m) of each edge; 0 for closures
        self._step_var = np.zeros((64, 2))  # row k: the fused variances of the step from keyframe k − 1 to k
        self._step_len = np.zeros(64)  # row k: the odometry length of the step from keyframe k − 1 to k

    @staticmethod
    def _key(lo, hi):  # type: ignore[no-untyped-def]
        """One sort key per keyframe pair (older *lo*, newer *hi*; ints or arrays): row-major in (hi, lo)."""
        return hi * _PAIR_BASE + lo

    def add_edge(self, i: int, j: int, covariance: Array, length_m: float = 0.0) -> None:
        """An edge between keyframes *i* and *j* with its ``(dof, dof)`` covariance (any frame: traces only)
        and, for odometry, the path length it measured (m; the drift model's; 0 for a loop closure)."""
        d = 2 if self.planar else 3
        C = np.asarray(covariance, dtype=float)
        n = self._n
        if n == len(self._ends):
            self._ends = np.concatenate([self._ends, np.zeros_like(self._ends)])
            self._var = np.concatenate([self._var, np.zeros_like(self._var)])
            self._len = np.concatenate([self._len, np.zeros_like(self._len)])
        lo, hi = min(i, j), max(i, j)
        at = n
        if n and (hi, lo) < (self._ends[n - 1, 1], self._ends[n - 1, 0]):
            keys = self._key(self._ends[:n, 0], self._ends[:n, 1])
            at = int(np.searchsorted(keys, self._key(lo, hi), side="right"))
            for a in (self._ends, self._var, self._len):  # shift the (few) later edges up by one
                a[at + 1:n + 1] = a[at:n].copy()
        self._ends[at] = (lo, hi)
        self._var[at] = (np.trace(C[:d, :d]), np.trace(C[d:, d:]))
        self._len[at] = float(length_m)
        self._n = n + 1
        if hi == lo + 1:  # a step of the chain: parallel edges add their information
            while hi >= len(self._step_var):
                self._step_var = np.concatenate([self._step_var, np.zeros_like(self._step_var)])
                self._step_len = np.concatenate([self._step_len, np.zeros_like(self._step_len)])
            self._step_len[hi] = max(self._step_len[hi], float(length_m))
            old = self._step_var[hi]
            new = self._var[at]
            self._step_var[hi] = np.where(old > 0, old * new / np.maximum(old + new, 1e-300), new)

    def chain_variance(self, a: int, b: int, positions: Array) -> tuple[float, float]:
        """(translation variance m², rotation variance rad²) of keyframe *b* relative to *a* along the chain
        of consecutive keyframes a, a+1, …, b — each step's parallel edges (registration and wheels) fused
        by adding their information per block — with the lever-arm propagation of :meth:`from_node`,
        lever arms to *b* on the current estimate *positions*. The pairwise consistency of two closures
        uses it for the short stretches between their old and between their new keyframes."""
        lo, hi = min(a, b), max(a, b)
        if lo == hi:
            return 0.0, 0.0
        steps = np.arange(lo + 1, hi + 1)
        if hi >= len(self._step_var) or np.any(self._step_var[steps, 0] <= 0):
            return self.limit_m2, self.limit_m2  # a step without an edge: no chain
        centre = 0.5 * (positions[steps - 1] + positions[steps])
        lever2 = np.sum((centre - positions[b]) ** 2, axis=1)
        vt, vr = self._step_var[steps, 0], self._step_var[steps, 1]
        ell = self._step_len[steps]
        dt, dr = self._drift_variance(float(np.sum(ell)), float(np.sum(ell * np.sqrt(lever2))))
        return self.scale * (float(np.sum(vt + vr * lever2)) + dt), self.scale * (float(np.sum(vr)) + dr)

    def _drift_variance(self, length_m, moment_m2):  # type: ignore[no-untyped-def]
        """(position, rotation) variance traces of the random-constant heading rate over a path of odometry
        length *length_m* and lever-weighted length *moment_m2* (scalars or arrays)."""
        d, r = (2, 1) if self.planar else (3, 3)
        return d * (self.drift * moment_m2) ** 2, r * (self.drift * length_m) ** 2

    def from_node(self, j: int, positions: Array) -> NodeUncertainty:
        """Uncertainty of every keyframe ``0 … len(positions) − 1`` relative to keyframe *j*.

        *positions* ``(K, 2|3)`` are the current estimates (m), for the lever arms."""
        K = len(positions)
        limit = self.limit_m2
        if not self._n:
            pv = np.full(K, limit)
            pv[j] = 0.0
            return NodeUncertainty(pv, np.where(pv > 0, limit, 0.0))
        lo, hi = self._ends[: self._n, 0], self._ends[: self._n, 1]
        vt, vr = self._var[: self._n, 0], self._var[: self._n, 1]
        ell = self._len[: self._n]
        centre = 0.5 * (positions[lo] + positions[hi])
        lever2 = np.sum((centre - positions[j]) ** 2, axis=1)
        w = vt + vr * lever2 + 1e-12  # strictly positive: csgraph drops explicit zeros
        # Parallel edges (odometry and wheel, repeated closures): keep the most certain one. The edges
        # are sorted by pair, so each pair's edges are one run: its minimum by reduceat, no sort.
        pair = self._key(lo, hi)
        new_run = np.ones(self._n, dtype=bool)
        new_run[1:] = pair[1:] != pair[:-1]
        starts = np.flatnonzero(new_run)
        run = np.cumsum(new_run) - 1
        is_min = np.flatnonzero(w == np.minimum.reduceat(w, starts)[run])
        first = np.ones(len(is_min), dtype=bool)
        first[1:] = run[is_min][1:] != run[is_min][:-1]
        keep = is_min[first]  # the first edge of each run at its minimum
        lo, hi, w, vr, pair = lo[keep], hi[keep], w[keep], vr[keep], pair[keep]  # pair is sorted
        ell, lever = ell[keep], np.sqrt(lever2[keep])
        # Row = newer end, column = older end: already the CSR order, built without a sort.
        indptr = np.searchsorted(hi, np.arange(K + 1))
        graph = csr_matrix((w, lo, indptr), shape=(K, K))
        dist, pred = dijkstra(graph, directed=False, indices=j, return_predecessors=True, limit=limit)
        reached = np.isfinite(dist)
        s = self.scale
        pos_var = np.where(reached, np.minimum(s * dist, limit), limit)
        # Rotation variance, odometry length and lever-weighted length along the same paths: the edge from
        # each keyframe's predecessor, summed up the predecessor tree by pointer doubling (log₂ K steps).
        has = reached & (pred >= 0)
        idx = np.flatnonzero(has)
        acc = np.zeros((K, 3))
        p = pred[idx]
        e = np.searchsorted(pair, self._key(np.minimum(p, idx), np.maximum(p, idx)))
        acc[idx] = np.column_stack([vr[e], ell[e], ell[e] * lever[e]])
        acc = sum_to_root(acc, np.where(has, pred, j).astype(np.int64), j)
        dt, dr = self._drift_variance(acc[:, 1], acc[:, 2])
        dt = np.where(reached, np.minimum(s * dt, limit - pos_var), 0.0)
        dr = np.where(reached, s * dr, 0.0)
        rot_var = np.where(reached, s * acc[:, 0], limit)
        return NodeUncertainty(pos_var + dt, rot_var + dr, dt, dr)
