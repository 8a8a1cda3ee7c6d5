"""Pairwise consistency of loop closures and their largest consistent set: the test of Pairwise Consistent
Measurement set maximisation (PCM; Mangelson, Dominic, Eustice & Vasudevan, ICRA 2018) and its maximum
clique, exact here (Bron–Kerbosch with pivoting; Bron & Kerbosch 1973, Tomita et al. 2006).

Two closures a and b are consistent when the cycle Z_a⁻¹ (X_ia⁻¹ X_ib) Z_b (X_jb⁻¹ X_ja) — the first closure,
the estimate's stretch between the old keyframes, the second closure back, the stretch between the new
ones — is within the χ² gate of the identity under both closures' covariances and the two stretches' chain
variances (:meth:`~slam.loops.uncertainty.RelativeUncertainty.chain_variance`), the rotation variance carried
to translation over the closures' lever arm. The acceptance stage (:mod:`slam.loops.accept`) asks it of the
closures of a window, of a group against closures accepted alone nearby, and of two global matches.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from core import geometry as G

from .types import LoopClosure
from .uncertainty import RelativeUncertainty

Array = NDArray[np.float64]


class PairwiseConsistency:
    """PCM's pairwise test at a χ² *gate* (squared Mahalanobis distance, 3 dof planar, 6 spatial)."""

    def __init__(self, uncertainty: RelativeUncertainty, planar: bool, gate: float) -> None:
        self.uncertainty = uncertainty
        self.planar = planar
        self.dof = 3 if planar else 6
        self.gate = gate

    def consistent(self, a: LoopClosure, b: LoopClosure, poses: Array,
                   old_variance: tuple[float, float] | None = None) -> bool:
        """Whether closures *a* and *b* are consistent on the estimate *poses* (see the module docstring);
        *old_variance*, when given, replaces the chain variance between their old keyframes."""
        pos = poses[:, :(2 if self.planar else 3), 3]
        var_old = self.uncertainty.chain_variance(a.i, b.i, pos) if old_variance is None else old_variance
        return bool(self._cycles([a], [b], poses, np.array([var_old]),
                                 np.array([self.uncertainty.chain_variance(a.j, b.j, pos)]))[0])

    def of_pairs(self, pairs: list[tuple[LoopClosure, LoopClosure]], poses: Array) -> NDArray[np.bool_]:
        """:meth:`consistent` of each pair. A window's closures join a few new keyframes to a few old ones, so the
        chain variances are computed once per pair of keyframes, not once per pair of closures."""
        pos = poses[:, :(2 if self.planar else 3), 3]
        var_of = functools.cache(lambda u, v: self.uncertainty.chain_variance(u, v, pos))
        var_old, var_new = np.array([var_of(a.i, b.i) for a, b in pairs]), np.array([var_of(a.j, b.j) for a, b in pairs])
        return self._cycles([a for a, _ in pairs], [b for _, b in pairs], poses, var_old, var_new)

    def matrix(self, closures: list[LoopClosure], poses: Array) -> NDArray[np.bool_]:
        """The ``(n, n)`` matrix of :meth:`consistent` over *closures*."""
        n = len(closures)
        ok = np.eye(n, dtype=bool)
        if n > 1:
            x, y = np.triu_indices(n, 1)
            ok[x, y] = ok[y, x] = self.of_pairs([(closures[p], closures[q]) for p, q in zip(x, y)], poses)
        return ok

    def largest_set(self, closures: list[LoopClosure], poses: Array) -> list[LoopClosure]:
        """The largest pairwise-consistent subset (the maximum clique of :meth:`matrix`); ties go to the subset
        with most distinct new keyframes."""
        n = len(closures)
        if n == 0:
            return []
        ok = self.matrix(closures, poses)
        nbrs = [set(np.flatnonzero(ok[a]).tolist()) - {a} for a in range(n)]
        best: list[int] = []

        def key(members: list[int]) -> tuple[int, int]:
            return len({closures[m].j for m in members}), len(members)

        def expand(r: set[int], p: set[int], x: set[int]) -> None:
            nonlocal best
            if not p and not x:
                if key(sorted(r)) > key(best):
                    best = sorted(r)
                return
            if len(r) + len(p) <= len(best) and len({closures[m].j for m in r | p}) <= key(best)[0]:
                return  # cannot beat the best
            pivot = max(p | x, key=lambda u: len(nbrs[u] & p))
            for v in list(p - nbrs[pivot]):
                expand(r | {v}, p & nbrs[v], x & nbrs[v])
                p.remove(v)
                x.add(v)

        expand(set(), set(range(n)), set())
        return [closures[m] for m in best]

    def _cycles(self, a: list[LoopClosure], b: list[LoopClosure], poses: Array, var_old: Array,
                var_new: Array) -> NDArray[np.bool_]:
        """:meth:`consistent` of each pair ``(a[k], b[k])``, given the ``(n, 2)`` chain variances (translation m²,
        rotation rad²) between their old and between their new keyframes; one stacked computation."""
        Za, Zb = np.array([lc.measurement for lc in a]), np.array([lc.measurement for lc in b])
        Ca, Cb = np.array([lc.covariance for lc in a]), np.array([lc.covariance for lc in b])
        ia, ja = np.array([lc.i for lc in a]), np.array([lc.j for lc in a])
        ib, jb = np.array([lc.i for lc in b]), np.array([lc.j for lc in b])
        E = G.inverse(Za) @ G.relative(poses[ia], poses[ib]) @ Zb @ G.relative(poses[jb], poses[ja])
        e = G.se2_log(E) if self.planar else G.se3_log(E)
        d = 2 if self.planar else 3
        (ti, ri), (tj, rj) = var_old.T, var_new.T
        (ta, ra), (tb, rb) = ((np.trace(C[:, :d, :d], axis1=1, axis2=2), np.trace(C[:, d:, d:], axis1=1, axis2=2))
                              for C in (Ca, Cb))
        var_r = ri + rj + ra + rb
        lever2 = np.sum(Za[:, :d, 3] ** 2, axis=1) + np.sum(Zb[:, :d, 3] ** 2, axis=1)
        var_t = ti + tj + ta + tb + var_r * lever2
        m2 = np.sum(e[:, :d] ** 2, axis=1) / (var_t / d) + np.sum(e[:, d:] ** 2, axis=1) / (var_r / (self.dof - d))
        return m2 <= self.gate
