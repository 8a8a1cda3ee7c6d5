"""The compiled 3D kernels (registration.kernels_grid3d, kernels_icp3d, kernels_icp3d_point) against the numpy / scipy implementations they replace
on the LiDAR odometry's hot path: the same k nearest neighbours, normals, voxel subsampling and ICP poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import geometry as geo
from core.errors import DegenerateInputError
from registration import alignment, kernels_grid3d as k3
from registration.config import IcpConfig
from registration.icp import icp
from registration.point_to_plane import icp_point_to_plane
from registration.target import IcpTarget, estimate_normals


def _scene(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """A street-like cloud: ground, two facades, a few poles, 1 cm noise, and scattered clutter (some far)."""
    m = n // 6
    ground = np.column_stack([rng.uniform(-20, 20, 2 * m), rng.uniform(-8, 8, 2 * m), np.full(2 * m, -1.7)])
    left = np.column_stack([rng.uniform(-20, 20, m), np.full(m, 8.0), rng.uniform(-1.7, 6, m)])
    right = np.column_stack([rng.uniform(-20, 20, m), np.full(m, -8.0) + 0.05 * rng.uniform(-20, 20, m) / 20,
                             rng.uniform(-1.7, 4, m)])
    a = rng.uniform(0, 2 * np.pi, m // 2)
    poles = np.column_stack([np.repeat([3.0, -9.0], m // 4) + 0.15 * np.cos(a), np.repeat([4.0, -5.0], m // 4)
                             + 0.15 * np.sin(a), rng.uniform(-1.7, 3, m // 2)])
    clutter = rng.uniform(-40, 40, (m // 2, 3)) * np.array([1.0, 1.0, 0.2])
    P = np.vstack([ground, left, right, poles, clutter])
    return P + rng.normal(0, 0.01, P.shape)


def _knn(grid: k3.VoxelGrid3D, Q: np.ndarray, k: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
    bd, bi = np.empty(k), np.empty(k, np.int64)
    D, I = np.empty((len(Q), k)), np.empty((len(Q), k), np.int64)
    for i, q in enumerate(Q):
        k3.knn3(q[0], q[1], q[2], grid.points, *grid.args(), k, bound, bd, bi)
        D[i], I[i] = bd, bi
    return D, I


@pytest.mark.parametrize("cell", [0.2, 1.0, 5.0])
@pytest.mark.parametrize("k, bound", [(1, np.inf), (8, 3.0), (10, np.inf), (8, 0.3)])
def test_grid_knn_equals_the_kd_tree(cell, k, bound):
    rng = np.random.default_rng(int(cell * 10) + k)
    P = _scene(rng, 3000)
    g = k3.VoxelGrid3D(P, cell)
    Q = np.vstack([P[rng.choice(len(P), 300, replace=False)] + rng.normal(0, 0.2, (300, 3)),
                   rng.uniform(-60, 60, (100, 3))])  # some queries far outside the points' box
    D, I = _knn(g, Q, k, bound)
    want_d, want_i = cKDTree(P).query(Q, k=k, distance_upper_bound=bound)
    want_d, want_i = want_d.reshape(len(Q), k), want_i.reshape(len(Q), k)
    found = np.isfinite(want_d)
    np.testing.assert_array_equal(np.isfinite(D), found)
    np.testing.assert_array_equal(I[found], want_i[found])
    np.testing.assert_allclose(np.sqrt(D[found]), want_d[found], rtol=0, atol=1e-12)
    assert (I[~found] == -1).all()


def test_grid_normals_equal_the_kd_tree_pca_normals():
    rng = np.random.default_rng(5)
    P = _scene(rng)
    tgt = IcpTarget(P, normal_neighbors=10)
    g = tgt.grid3
    normals, have = np.empty_like(P), np.zeros(len(P), dtype=bool)
    k3.normals_3d(np.arange(len(P)), normals, have, g.points, *g.args(), 10)
    want, ev = estimate_normals(P, cKDTree(P), 10, return_eigenvalues=True)
    assert have.all()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    # The sign of a normal is arbitrary; where the two smallest scatter eigenvalues are well apart (a
    # defined normal) both agree to rounding.
    ok = ev[:, 1] - ev[:, 0] > 1e-6 * ev[:, 2]
    assert ok.mean() > 0.9
    assert np.abs(np.abs(np.einsum("ij,ij->i", normals[ok], want[ok])) - 1.0).max() < 1e-9


def _street_pair(seed: int):
    """The scene, 4000 of its points seen from a pose 0.4 m / 3° off (returned), 2 cm noise, 5 % outliers."""
    rng = np.random.default_rng(seed)
    P = _scene(rng, 12000)
    xi = np.concatenate([rng.uniform(-0.4, 0.4, 3) * [1, 1, 0.2], rng.uniform(-0.05, 0.05, 3) * [0.3, 0.3, 1]])
    T = geo.se3_exp(xi)
    src = geo.transform_points(geo.inverse(T), P[rng.choice(len(P), 4000, replace=False)])
    src = src + rng.normal(0, 0.02, src.shape)
    src[:200] += rng.uniform(-2, 2, (200, 3))
    return P, src, T


@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
@pytest.mark.parametrize("seed", range(3))
def test_compiled_3d_icp_equals_the_numpy_loop(monkeypatch, robust, seed):
    """plane_icp_3d against the numpy iterations it replaces: the same pose (to rounding), iterations,
    convergence, inliers and covariance, coarse-to-fine gates, from a start 0.4 m / 3° off."""
    P, src, T = _street_pair(seed)
    cfg = IcpConfig(gates_m=(1.5, 0.6, 0.3), max_iterations=60, tol_translation_m=1e-7, tol_rotation_rad=1e-8,
                    robust=robust, robust_scale_m=0.2, voxel_m=0.3)
    fast = icp_point_to_plane(src, IcpTarget(P), None, cfg)
    monkeypatch.setattr(alignment, "COMPILED_3D", False)
    ref = icp_point_to_plane(src, IcpTarget(P), None, cfg)
    assert np.abs(fast.transform - ref.transform).max() < 1e-10
    assert (fast.iterations, fast.converged, fast.inliers) == (ref.iterations, ref.converged, ref.inliers)
    np.testing.assert_allclose(fast.covariance, ref.covariance, rtol=1e-7, atol=1e-16)
    assert np.abs(geo.se3_log(geo.relative(T, fast.transform))).max() < 0.01


@pytest.mark.parametrize("compiled", [True, False])
def test_both_3d_loops_refuse_too_few_pairs_and_a_singular_system(monkeypatch, compiled):
    monkeypatch.setattr(alignment, "COMPILED_3D", compiled)
    P = _scene(np.random.default_rng(1), 3000)
    with pytest.raises(DegenerateInputError, match=r"iteration 1: 0 pairs within 1.0 m \(need 10\)"):
        icp_point_to_plane(P + 100.0, P, None, IcpConfig(gates_m=(1.0, 0.5)))
    rng = np.random.default_rng(2)
    plane = np.column_stack([rng.uniform(-5, 5, (500, 2)), np.zeros(500)])  # slides in x, y and turns about z
    with pytest.raises(DegenerateInputError, match="singular normal equations"):
        icp_point_to_plane(plane, plane, None, IcpConfig(gates_m=(0.5,)))


@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("tol", [1e-7, 1e-10])
def test_compiled_3d_point_icp_equals_the_numpy_loop(monkeypatch, robust, seed, tol):
    """point_icp_3d against the numpy iterations of icp(): the same pose (to rounding), iterations, convergence,
    inliers and covariance, coarse-to-fine gates, from a start 0.4 m / 3° off; unweighted with the repeated-match
    fixed point, weighted to the increment tolerance."""
    P, src, T = _street_pair(seed)
    cfg = IcpConfig(gates_m=(1.5, 0.6, 0.3), max_iterations=60, tol_translation_m=tol, tol_rotation_rad=tol / 10,
                    robust=robust, robust_scale_m=0.2, voxel_m=0.3)
    fast = icp(src, IcpTarget(P), None, cfg)
    monkeypatch.setattr(alignment, "COMPILED_3D", False)
    ref = icp(src, IcpTarget(P), None, cfg)
    assert np.abs(fast.transform - ref.transform).max() < 1e-10
    assert (fast.iterations, fast.converged, fast.inliers) == (ref.iterations, ref.converged, ref.inliers)
    assert fast.rmse == pytest.approx(ref.rmse, rel=1e-9)
    np.testing.assert_allclose(fast.covariance, ref.covariance, rtol=1e-7, atol=1e-16)
    assert np.abs(geo.se3_log(geo.relative(T, fast.transform))).max() < 0.01


@pytest.mark.parametrize("max_iterations", [1, 4])
def test_compiled_3d_point_icp_stops_at_the_iteration_cap_like_the_numpy_loop(monkeypatch, max_iterations):
    """The cap ends an early stage: the evaluation still uses the last gate, in both loops."""
    P, src, _ = _street_pair(4)
    cfg = IcpConfig(gates_m=(1.5, 0.6, 0.3), max_iterations=max_iterations, voxel_m=0.3)
    fast = icp(src, IcpTarget(P), None, cfg)
    monkeypatch.setattr(alignment, "COMPILED_3D", False)
    ref = icp(src, IcpTarget(P), None, cfg)
    assert np.abs(fast.transform - ref.transform).max() < 1e-10
    assert (fast.iterations, fast.converged, fast.inliers) == (ref.iterations, ref.converged, ref.inliers) \
        == (max_iterations, False, ref.inliers)


@pytest.mark.parametrize("compiled", [True, False])
def test_both_3d_point_icp_loops_refuse_too_few_pairs_and_zero_weights(monkeypatch, compiled):
    monkeypatch.setattr(alignment, "COMPILED_3D", compiled)
    P = _scene(np.random.default_rng(1), 3000)
    with pytest.raises(DegenerateInputError, match=r"^ICP iteration 1: 0 pairs within 1.0 m \(need 10\)$"):
        icp(P + 100.0, P, None, IcpConfig(gates_m=(1.0, 0.5)))
    with pytest.raises(DegenerateInputError, match=r"^ICP iteration 1: 2 pairs within 1.0 m \(need 10\)$"):
        icp(np.vstack([P[:2], P + 100.0]), P, None, IcpConfig(gates_m=(1.0, 0.5)))
    # Cauchy weights of pairs ~1 cm apart underflow to 0 at a 1e-200 m scale
    with pytest.raises(DegenerateInputError, match="^all correspondence weights are zero$"), np.errstate(over="ignore"):
        icp(P + 0.01, P, None, IcpConfig(gates_m=(1.0,), robust="cauchy", robust_scale_m=1e-200))


@pytest.mark.parametrize("size", [0.05, 0.3, 1.0])
def test_compiled_voxel_subsampling_keeps_the_same_rows(monkeypatch, size):
    """A LiDAR-sized cloud (≥ 20000 points) goes through the compiled hash: the same first point per voxel,
    in the same order, as the sort of packed keys; negative coordinates and points on voxel faces included."""
    from registration import voxel

    rng = np.random.default_rng(11)
    P = np.vstack([_scene(rng, 30000), np.round(rng.uniform(-3, 3, (2000, 3)) / size) * size])
    fast = voxel.voxel_downsample(P, size)
    monkeypatch.setattr(voxel, "_COMPILED_MIN_POINTS", 10**12)
    np.testing.assert_array_equal(fast, voxel.voxel_downsample(P, size))
    with pytest.raises(Exception, match="positive"):
        monkeypatch.setattr(voxel, "_COMPILED_MIN_POINTS", 0)
        voxel.voxel_downsample(P, -1.0)
