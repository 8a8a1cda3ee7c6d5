"""Polar scan descriptor for place recognition (Scan Context, Kim & Kim, IROS 2018, §III).

A scan's hit points (sensor frame) are binned into ``n_rings`` range rings × ``n_sectors`` angular
sectors. For a 3D cloud (``height=True``) each bin holds the maximum height of its points, as in the
paper (eq. 1), measured above the scan's own ground level (a low percentile of its heights, so that
no sensor height is configured); a 2D laser has no height, and its bins hold the fraction of the
scan's points falling in them instead. Two descriptors are compared over all cyclic column shifts
(eq. 6): the best shift estimates the relative heading, which seeds ICP. The *ring key* (eq. 7),
invariant to rotation, is the vector searched first, so revisits are found even when the odometry
estimate is far off: for heights the fraction of a ring's sectors that are occupied (the paper's
ψ = ‖r‖₀ / N_s), for the 2D occupancy the ring's share of the points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PolarDescriptorConfig:
    """Bins of the polar histogram. ``max_range`` in metres; rings are evenly spaced in range. ``height``:
    bins hold the maximum height above the ground level (3D clouds) instead of the share of points."""

    n_rings: int = 20
    n_sectors: int = 60
    max_range: float = 15.0
    height: bool = False


# Scan Context's own bins for a 3D LiDAR (Kim & Kim 2018, §IV-A: N_s = 60, N_r = 20, L_max = 80 m).
SCAN_CONTEXT_3D = PolarDescriptorConfig(n_rings=20, n_sectors=60, max_range=80.0, height=True)
# The ground level of a 3D scan: this percentile of its points' heights (most returns of a vehicle's
# LiDAR are the ground around it; a low percentile rather than the minimum ignores stray returns below it).
_GROUND_PERCENTILE = 5.0


def polar_descriptor(points: Array, cfg: PolarDescriptorConfig = PolarDescriptorConfig()) -> Array:
    """``(n_rings, n_sectors)`` descriptor: per (range, bearing) bin the fraction of hit points, or with
    ``cfg.height`` the maximum height (m) of the bin's points above the scan's ground level (0 for an
    empty bin, and for a bin of ground only).

    Args:
        points: ``(N, 2)`` or ``(N, 3)`` hit points in the sensor frame, metres (``(N, 3)`` for heights).
    """
    P = np.asarray(points, dtype=float)
    p = P[:, :2]
    r = np.hypot(p[:, 0], p[:, 1])
    keep = (r < cfg.max_range) & (r > 0)
    r, p = r[keep], p[keep]
    desc = np.zeros((cfg.n_rings, cfg.n_sectors))
    if len(r) == 0:
        return desc
    ring = np.minimum((r / cfg.max_range * cfg.n_rings).astype(int), cfg.n_rings - 1)
    bearing = np.arctan2(p[:, 1], p[:, 0]) % (2 * np.pi)
    sector = np.minimum((bearing / (2 * np.pi) * cfg.n_sectors).astype(int), cfg.n_sectors - 1)
    if cfg.height:
        z = P[keep, 2] if P.shape[1] > 2 else np.zeros(len(r))
        h = np.maximum(z - np.percentile(z, _GROUND_PERCENTILE), 0.0)
        np.maximum.at(desc, (ring, sector), h)
        return desc
    np.add.at(desc, (ring, sector), 1.0)
    return desc / len(r)


def ring_key(desc: Array, cfg: PolarDescriptorConfig = PolarDescriptorConfig()) -> Array:
    """Rotation-invariant summary (Scan Context eq. 7), shape ``(n_rings,)``: per ring the fraction of
    occupied sectors for heights, the ring's share of the points for the 2D occupancy."""
    if cfg.height:
        return np.count_nonzero(desc > 0, axis=-1) / desc.shape[-1]
    return desc.sum(axis=-1)


def shift_distances(query: Array, candidates: Array) -> Array:
    """Scan Context distance (eq. 5) between *query* and each candidate for every cyclic sector shift.

    Uses column-wise cosine distance averaged over the columns non-empty in either descriptor. Returns ``(M, n_sectors)``:
    entry ``[m, s]`` compares the query with candidate *m* rolled by *s* sectors. Vectorised with
    an FFT cross-correlation along the sector axis.
    """
    q = np.asarray(query, dtype=float)
    C = np.asarray(candidates, dtype=float)
    if C.ndim == 2:
        C = C[None]
    qn = np.linalg.norm(q, axis=0)  # (S,)
    cn = np.linalg.norm(C, axis=1)  # (M, S)
    qh = q / np.where(qn > 0, qn, 1.0)
    ch = C / np.where(cn > 0, cn, 1.0)[:, None, :]
    # corr[m, s] = Σ_col <q[:, col], c_m[:, col - s]> computed for all s via FFT along the sector axis.
    Fq = np.fft.rfft(qh, axis=-1)
    Fc = np.fft.rfft(ch, axis=-1)
    corr = np.fft.irfft((Fq[None] * np.conj(Fc)).sum(axis=1), n=q.shape[1], axis=-1)
    qmask = (qn > 0).astype(float)
    cmask = (cn > 0).astype(float)
    Fm = np.fft.irfft(np.fft.rfft(qmask)[None] * np.conj(np.fft.rfft(cmask, axis=-1)), n=q.shape[1], axis=-1)
    # Average over the columns non-empty in either: a column only one scan fills counts as distance 1.
    # (Averaging over the columns non-empty in both, a 180° scan shifted by ~180° overlaps the other
    # in one or two columns and scores ≈ 0 against any place: with a 180° laser nearly every query did.)
    both = np.rint(Fm)
    union = np.maximum(qmask.sum() + cmask.sum(axis=1)[:, None] - both, 1.0)
    return 1.0 - corr / union


def best_shift(query: Array, candidates: Array) -> tuple[Array, Array]:
    """Minimum Scan Context distance and the relative heading for each candidate.

    Returns ``(distance, yaw)`` where ``candidate_T_query ≈ Rot(yaw)`` (about the sensor origin):
    a query-frame point *p* appears in the candidate frame at ``Rot(yaw) p``. This is the initial
    rotation for the ICP that verifies the candidate; resolution ``2π / n_sectors``.
    """
    D = shift_distances(query, candidates)
    s = np.argmin(D, axis=1)
    n = np.asarray(query).shape[1]
    yaw = (s * 2 * np.pi / n + np.pi) % (2 * np.pi) - np.pi
    return D[np.arange(len(D)), s], -yaw


class DescriptorIndex:
    """Incremental store of descriptors with ring-key retrieval (exact nearest ring keys by brute force:
    a few thousand places are one (n, rings) distance evaluation, cheaper than rebuilding a k-d tree
    after every addition)."""

    def __init__(self, cfg: PolarDescriptorConfig = PolarDescriptorConfig()) -> None:
        self.cfg = cfg
        self._desc: list[Array] = []
        self._keys = np.empty((0, 0))  # ring keys, rows [0, n) used; capacity doubles
        self._ids = np.empty(0, dtype=np.int64)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, key_id: int, points: Array) -> Array:
        """Describe *points* and store the place as *key_id*; returns its descriptor."""
        d = polar_descriptor(points, self.cfg)
        self.insert(key_id, d)
        return d

    def insert(self, key_id: int, d: Array) -> None:
        """Store the place *key_id* by its descriptor *d* (:func:`polar_descriptor` with this index's config)."""
        key = ring_key(d, self.cfg)
        if self._n == len(self._keys):
            cap = max(64, 2 * self._n)
            keys, ids = np.empty((cap, len(key))), np.empty(cap, dtype=np.int64)
            if self._n:
                keys[: self._n], ids[: self._n] = self._keys[: self._n], self._ids[: self._n]
            self._keys, self._ids = keys, ids
        self._desc.append(d)
        self._keys[self._n], self._ids[self._n] = key, key_id
        self._n += 1

    def query(self, desc: Array, k: int = 10, exclude_after: int | None = None) -> list[tuple[int, float, float]]:
        """The *k* nearest stored places by ring key, re-ranked by shift distance.

        Returns ``(id, distance, yaw)`` sorted by distance; ids ≥ *exclude_after* are skipped
        (recent keyframes are not loop closures). The ring-key search looks at the 3k nearest of all
        places and keeps the first 2k not excluded.
        """
        total = self._n
        n = total if exclude_after is None else int(np.searchsorted(self._ids[:total], exclude_after))
        if n == 0:
            return []
        kk = min(total, max(k * 3, k))
        diff = self._keys[:total] - ring_key(desc, self.cfg)
        d2 = np.einsum("ij,ij->i", diff, diff)
        idx = np.argpartition(d2, kk - 1)[:kk] if kk < total else np.arange(total)
        idx = idx[np.lexsort((idx, d2[idx]))]  # nearest first, ties by insertion order (as a k-d tree's)
        idx = idx[(idx < n)][: k * 2]
        if len(idx) == 0:
            return []
        dist, yaw = best_shift(desc, np.asarray([self._desc[i] for i in idx]))
        order = np.argsort(dist)[:k]
        return [(int(self._ids[idx[o]]), float(dist[o]), float(yaw[o])) for o in order]
