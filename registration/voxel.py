"""Voxel-grid subsampling of point sets (vectorised; one point per occupied voxel).

A voxel of edge ``size`` (m) is indexed by ``floor(p / size)``; voxel keys are packed into one
int64 and deduplicated with a sort (``np.unique``), so the cost is O(N log N) with no Python loop.
"""

from __future__ import annotations

from typing import Iterable, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as G
from core.errors import GeometryError

Array = NDArray[np.float64]

__all__ = ["voxel_keys", "voxel_downsample", "voxel_downsample_stream"]

#: 3D clouds of at least this many points (a LiDAR scan) are subsampled by the compiled hash of
#: registration.kernels_grid3d.voxel_first_3d — the same rows, without the sort; below it numpy's sort is as quick.
_COMPILED_MIN_POINTS = 20000


def _first_3d(P: Array, size: float) -> Array:
    """``voxel_downsample(P, size, "first")`` of a 3D cloud by one compiled pass over a hash of the voxels."""
    from .kernels_grid3d import voxel_first_3d

    if size <= 0 or not np.isfinite(size):
        raise GeometryError(f"voxel size must be positive and finite, got {size}")
    keep, lo, hi = voxel_first_3d(np.ascontiguousarray(P), size)
    if np.prod((hi - lo + 1).astype(np.float64)) >= 2.0**62:
        raise GeometryError(f"point extent too large for voxel size {size} m")
    return P[keep]


def voxel_keys(points: Array, size: float) -> NDArray[np.int64]:
    """One int64 key per point identifying its voxel of edge *size* (m)."""
    if size <= 0 or not np.isfinite(size):
        raise GeometryError(f"voxel size must be positive and finite, got {size}")
    ijk = np.floor(points / size).astype(np.int64)
    lo, hi = G.bounds(ijk)
    ijk -= lo
    span = hi - lo + 1
    if np.prod(span.astype(np.float64)) >= 2.0**62:
        raise GeometryError(f"point extent too large for voxel size {size} m")
    key = ijk[:, 0]
    for a in range(1, ijk.shape[1]):
        key = key * span[a] + ijk[:, a]
    return key


def voxel_downsample(points: ArrayLike, size: float | None, mode: Literal["first", "centroid"] = "first") -> Array:
    """Keep one point per voxel of edge *size* (m): the first point met (``first``, as KISS-ICP
    does) or the mean of the voxel's points (``centroid``, as Open3D's ``voxel_down_sample``).
    ``size`` None or 0 returns the input unchanged. Input and output are ``(N, d)`` in the same frame.
    """
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise GeometryError(f"points must be (N, 2) or (N, 3), got shape {P.shape}")
    if not size or len(P) == 0:
        return P
    if mode == "first" and P.shape[1] == 3 and len(P) >= _COMPILED_MIN_POINTS:
        return _first_3d(P, float(size))
    key = voxel_keys(P, float(size))
    if mode == "first":
        _, first = np.unique(key, return_index=True)
        return P[np.sort(first)]
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = np.zeros((len(counts), P.shape[1]))
    np.add.at(out, inv, P)
    return out / counts[:, None]


def voxel_downsample_stream(parts: Iterable[ArrayLike], size: float, batch_points: int = 2_000_000) -> Array:
    """:func:`voxel_downsample` (``first``) of the concatenation of *parts*, holding about *batch_points* input
    points at a time instead of all of them: each batch is reduced as it fills, then the reductions. Exactly
    the one-shot result — the first point of a voxel overall is the first of the earliest batch that has
    the voxel, and every reduction keeps the order of first occurrence."""
    kept: list[Array] = []
    batch: list[Array] = []
    n = 0
    for part in parts:
        P = np.asarray(part, dtype=np.float64)
        batch.append(P)
        n += len(P)
        if n >= batch_points:
            kept.append(voxel_downsample(np.vstack(batch), size))
            batch, n = [], 0
    if batch:
        kept.append(voxel_downsample(np.vstack(batch), size))
    if not kept:
        raise GeometryError("no points to downsample")
    return voxel_downsample(np.vstack(kept), size) if len(kept) > 1 else kept[0]
