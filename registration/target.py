"""The target of an alignment, prepared once for many: points, k-d tree (3D) or grid index (2D), and
PCA normals computed on demand (Hoppe et al. 1992); and the gated nearest-neighbour query every ICP
variant ends with. Points ``(N, d)`` in the target frame, metres."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from core.errors import DegenerateInputError, GeometryError
from .voxel import voxel_downsample

Array = NDArray[np.float64]

__all__ = ["IcpTarget", "estimate_normals", "gated_nearest"]

# Below this many queries scipy's thread start/join costs more than the parallel search saves.
_PARALLEL_MIN_QUERIES = 20000


def _workers(n: int, workers: int) -> int:
    """cKDTree ``workers`` for *n* queries: one thread for small batches."""
    return workers if n >= _PARALLEL_MIN_QUERIES else 1


def estimate_normals(points: Array, tree: cKDTree, k: int = 10, workers: int = -1,
                     return_eigenvalues: bool = False) -> Array | tuple[Array, Array]:
    """Unit normals ``(N, d)`` at *points* from the *k* nearest points of *tree* (PCA, Hoppe 1992).

    The normal is the eigenvector of the smallest eigenvalue of the neighbours' scatter matrix;
    its sign is arbitrary (only n nᵀ is used). With *return_eigenvalues* (3D only) the ascending
    scatter eigenvalues ``(N, 3)`` are returned too, for planarity tests."""
    k = min(k, tree.n)
    _, nn = tree.query(points, k=k, workers=workers if len(points) >= 20000 else 1)
    data = tree.data
    # One contiguous (N, k) array per axis, centred on the neighbourhood mean: cheaper than the
    # (N, k, d) gather and strided reductions for the few-point batches of 2D scans.
    cols = [data[:, j].take(nn) for j in range(data.shape[1])]
    for c in cols:
        c -= (c.sum(axis=1) / k)[:, None]
    if len(cols) == 2:
        # 2×2 scatter [[a, b], [b, c]]: the principal axis is at ½·atan2(2b, a − c); the normal is ⊥ to it.
        cx, cy = cols
        a = np.einsum("nk,nk->n", cx, cx)
        b = np.einsum("nk,nk->n", cx, cy)
        cc = np.einsum("nk,nk->n", cy, cy)
        phi = 0.5 * np.arctan2(2.0 * b, a - cc)
        out = np.empty((len(phi), 2))
        np.negative(np.sin(phi), out=out[:, 0])
        np.cos(phi, out=out[:, 1])
        return out
    C = np.empty((len(nn), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            C[:, i, j] = np.einsum("nk,nk->n", cols[i], cols[j])
            if j != i:
                C[:, j, i] = C[:, i, j]
    ev, V = np.linalg.eigh(C)
    if return_eigenvalues:
        return V[:, :, 0], ev
    return V[:, :, 0]


class IcpTarget:
    """A target point set prepared once for many alignments: subsampled points, kd-tree and
    (lazily) PCA normals. Points ``(N, d)`` in the target frame, metres."""

    def __init__(self, points: ArrayLike, voxel_m: float | None = None, normal_neighbors: int = 10,
                 workers: int = -1) -> None:
        P = np.asarray(points, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] not in (2, 3):
            raise GeometryError(f"target points must be (N, 2) or (N, 3), got shape {P.shape}")
        self.points = voxel_downsample(P, voxel_m, mode="centroid") if voxel_m else P
        if len(self.points) < 3:
            raise DegenerateInputError(f"target has {len(self.points)} points; ICP needs at least 3")
        self.dim = self.points.shape[1]
        self._tree: cKDTree | None = None
        self._grid = None
        self._grid3 = None
        self.normal_neighbors = normal_neighbors
        self.workers = workers
        # Normals are computed on demand, point by point, and kept: an alignment needs them only at
        # the target points it matches (a scan against a ten-scan local map: about a tenth). The
        # compiled 2D ICPs (registration.kernels_icp) fills these two arrays in place.
        self._normals = np.empty((len(self.points), self.dim))  # C order: the compiled kernels' layout
        self._have = np.zeros(len(self.points), dtype=bool)
        self._have_all = False

    @property
    def tree(self) -> cKDTree:
        """k-d tree of the points (built on first use: compiled 2D alignments search :attr:`grid`)."""
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    @property
    def grid(self):
        """2D only: the uniform-grid index of the compiled kernels (:class:`registration.kernels.PointGrid`)."""
        if self._grid is None:
            from .kernels import PointGrid

            self._grid = PointGrid(self.points)
        return self._grid

    @property
    def grid3(self):
        """3D only: the hashed voxel-grid index of the compiled kernels (:class:`registration.kernels_grid3d.VoxelGrid3D`)."""
        if self._grid3 is None:
            from .kernels_grid3d import VoxelGrid3D

            self._grid3 = VoxelGrid3D(self.points)
        return self._grid3

    def normals(self, index: NDArray[np.intp] | None = None) -> Array:
        """Unit PCA normals (smallest-eigenvalue eigenvector of the k-neighbour scatter) of the
        target points *index* (all when None), computed once per point."""
        if self.dim == 2:  # compiled grid search, one point at a time (same estimator)
            from .kernels import normals_2d

            g = self.grid
            want = np.arange(len(self.points)) if index is None else np.asarray(index, dtype=np.int64)
            normals_2d(want, self._normals, self._have, g.points, *g.args(), min(self.normal_neighbors, len(self.points)))
            return self._normals if index is None else self._normals.take(index, axis=0)
        if index is None:
            if not self._have_all:
                missing = np.flatnonzero(~self._have)
                self._normals[missing] = estimate_normals(self.points[missing], self.tree, self.normal_neighbors, self.workers)
                self._have[:] = self._have_all = True
            return self._normals
        if not self._have_all:
            missing = index[~self._have[index]]
            if len(missing):
                missing = np.unique(missing)
                self._normals[missing] = estimate_normals(self.points[missing], self.tree, self.normal_neighbors, self.workers)
                self._have[missing] = True
        return self._normals.take(index, axis=0)


def gated_nearest(tgt: IcpTarget, points: Array, gate: float, workers: int = 1) -> NDArray[np.intp]:
    """Index of the target point nearest to each row of *points*, strictly within *gate* (m), else
    ``len(tgt.points)`` (as cKDTree reports a miss): the compiled grid search in 2D, the k-d tree in 3D."""
    if tgt.dim == 2:
        from .kernels import nearest_within

        g = tgt.grid
        idx = nearest_within(np.ascontiguousarray(points, dtype=np.float64), g.points, *g.args(), float(gate))
        idx[idx < 0] = len(tgt.points)
        return idx
    return tgt.tree.query(points, k=1, distance_upper_bound=gate, workers=_workers(len(points), workers))[1]
