"""``python -m registration.compile_kernels``: every compiled kernel into numba's on-disk cache (``make install``)."""

from __future__ import annotations

import numpy as np

from .kernels import PointGrid, cached_nearest, nearest_within, normals_2d
from .kernels_correlative import branch_and_bound, rotated_cells, score_candidates, stamp_field
from .kernels_icp import plane_icp_2d
from .kernels_grid3d import VoxelGrid3D, normals_3d, voxel_first_3d
from .kernels_icp3d import plane_icp_3d
from .kernels_icp3d_point import point_icp_3d

__all__ = ["compile_all"]


def compile_all() -> None:
    """Compile every kernel for the argument types the package passes, into numba's on-disk cache
    (``make install`` runs this once, so the first ``slam run`` does not spend ~8 s compiling)."""
    pts = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [0.0, 1.0], [1.0, 1.1], [2.0, 1.0]])
    g = PointGrid(pts)
    nearest_within(pts.copy(), g.points, *g.args(), 0.5)
    normals, have = np.zeros_like(pts), np.zeros(len(pts), dtype=bool)
    normals_2d(np.arange(len(pts)), normals, have, g.points, *g.args(), 3)
    plane_icp_2d(pts.copy(), np.eye(2), np.zeros(2), np.array([0.5]), 2, 1e-4, 1e-4, 2, 0.1, 3,
                 normals, have, 3, g.points, *g.args())
    rotated_cells(pts, np.ones(2), np.zeros(2), 0.0, 0.0, -1.0, -1.0, 0.05)
    score_candidates(np.zeros((4, 4), np.uint8), np.zeros((1, 3, 2), np.int32), np.zeros(1, np.int64),
                     np.zeros((1, 2), np.int64))
    for dim in (2, 3):
        q = np.zeros((2, dim))
        cached_nearest(q, q.copy(), np.zeros(2), np.ones(2), np.zeros((2, 4), np.int64), np.zeros((3, dim)), 0.5, 1e-9,
                       np.zeros(2, np.int64))
    cloud = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [2.0, 0.0, 0.1], [0.0, 1.0, 0.0], [1.0, 1.1, 0.1], [2.0, 1.0, 0.0],
                      [0.0, 0.0, 1.0], [1.0, 0.0, 1.1], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0], [2.0, 2.0, 1.0], [0.5, 0.5, 0.5]])
    g3 = VoxelGrid3D(cloud)
    normals3, have3 = np.zeros_like(cloud), np.zeros(len(cloud), dtype=bool)
    normals_3d(np.arange(len(cloud)), normals3, have3, g3.points, *g3.args(), 3)
    plane_icp_3d(cloud.copy(), np.eye(3), np.zeros(3), np.array([0.5]), 2, 1e-4, 1e-4, 2, 0.1, 3, normals3, have3, 3,
                 g3.points, *g3.args())
    point_icp_3d(cloud.copy(), np.eye(3), np.zeros(3), np.array([0.5]), 2, 1e-4, 1e-4, 2, 0.1, 3, True, g3.points,
                 *g3.args())
    voxel_first_3d(cloud, 0.5)
    stamp_field(np.zeros(16, np.uint8), np.array([5], np.int64), np.array([0, 1], np.int64), np.array([255, 9], np.uint8))
    branch_and_bound(np.zeros((2, 4, 4), np.uint8), np.zeros((1, 3, 2), np.int32), 1, 1, 0.0, 0, 0, 0, 0, 0, 0, 0, -1, False)


if __name__ == "__main__":
    compile_all()
