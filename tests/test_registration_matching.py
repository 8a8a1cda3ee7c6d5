"""Incremental nearest-neighbour matching: every answer equals a fresh gated kd-tree query."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import geometry as geo
from registration import icp as icp_module
from registration.config import IcpConfig
from registration.matching import IncrementalMatcher, pair_distances


def _walk(rng, d: int, steps: int):
    """Rigid motions shrinking like an ICP's increments (cm down to µm), as 4×4 poses."""
    T = np.eye(4)
    for k in range(steps):
        s = 0.05 * 0.4**k if k % 7 else 0.3  # an occasional large jump resets most certificates
        xi = rng.normal(size=3 if d == 2 else 6) * s
        T = T @ (geo.se2_exp(xi) if d == 2 else geo.se3_exp(xi))
        yield T


def _target(rng, d: int) -> np.ndarray:
    """Clustered points (walls-like spacing) plus exact duplicates, so ties and near-ties occur."""
    P = rng.uniform(-4, 4, size=(1500, d))
    P[:300] = np.round(P[:300] * 20) / 20  # a grid: many equidistant neighbours
    return np.vstack([P, P[:50]])  # exact duplicates


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("incremental", [True, False])
def test_matches_equal_a_fresh_query_after_every_motion(d, incremental):
    """Over a walk of rigid motions and gate changes (coarse to fine, then wider again), each
    ``match`` gives the same matched coordinates and unmatched set as ``cKDTree.query(k=1,
    distance_upper_bound=gate)`` at the current positions (indices may differ only between duplicates)."""
    rng = np.random.default_rng(11 + d)
    P = _target(rng, d)
    tree = cKDTree(P)
    S = rng.uniform(-5, 5, size=(800, d))
    m = IncrementalMatcher(tree, incremental=incremental)
    gates = [1.0] * 6 + [0.5] * 6 + [0.25] * 6 + [0.6] * 6
    for gate, T in zip(gates, _walk(rng, d, len(gates))):
        moved = S @ T[:d, :d].T + T[:d, 3]
        got = m.match(moved, gate)
        want = tree.query(moved, k=1, distance_upper_bound=gate)[1]
        np.testing.assert_array_equal(got == tree.n, want == tree.n)
        ok = want < tree.n
        np.testing.assert_array_equal(P[got[ok]], P[want[ok]])
    if incremental:
        assert m.searched_points < 0.8 * len(S) * len(gates)  # small motions are certified without a search


def test_repeated_positions_need_no_search():
    """The same positions and gate again: no kd-tree search at all, in either mode."""
    rng = np.random.default_rng(2)
    tree = cKDTree(rng.uniform(-3, 3, size=(400, 2)))
    moved = rng.uniform(-3, 3, size=(100, 2))
    for incremental in (True, False):
        m = IncrementalMatcher(tree, incremental=incremental)
        a = m.match(moved, 0.4)
        n = m.searches
        b = m.match(moved, 0.4)
        np.testing.assert_array_equal(a, b)
        if incremental:  # a near-tie may still be searched again, but only a few points
            assert m.searched_points - len(moved) <= 5
        else:
            assert m.searches == n


def test_pair_distances_are_the_kdtree_distances():
    """``pair_distances`` reproduces cKDTree's nearest distances bit for bit (robust weights use them)."""
    rng = np.random.default_rng(4)
    for d in (2, 3):
        P = rng.uniform(-50, 50, size=(3000, d))
        Q = rng.uniform(-50, 50, size=(3000, d))
        dist, idx = cKDTree(P).query(Q)
        np.testing.assert_array_equal(pair_distances(Q, P[idx]), dist)


@pytest.mark.parametrize("robust", ["none", "huber", "trim"])
def test_icp_is_the_same_with_and_without_incremental_matching(monkeypatch, robust):
    """ICP on a 3D cloud gives the same pose, iterations and covariance whether its matches come
    from incremental re-searches or from a full query every iteration."""
    rng = np.random.default_rng(8)
    P = rng.uniform(-5, 5, size=(1200, 3))
    T = geo.se3_exp([0.15, -0.1, 0.05, 0.02, -0.03, 0.05])
    src = geo.transform_points(geo.inverse(T), P[:900]) + rng.normal(scale=0.01, size=(900, 3))
    cfg = IcpConfig(gates_m=(1.0, 0.5, 0.2), robust=robust, tol_translation_m=1e-10, tol_rotation_rad=1e-10, max_iterations=200)
    out = []
    for threshold in (0, 10**9):
        monkeypatch.setattr(icp_module, "INCREMENTAL_MIN_POINTS", threshold)
        out.append(icp_module.icp(src, P, None, cfg))
    a, b = out
    assert a.iterations == b.iterations and a.converged == b.converged and a.inliers == b.inliers
    assert np.abs(a.transform - b.transform).max() < 1e-12
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=0)


def test_point_to_plane_is_the_same_with_and_without_incremental_matching(monkeypatch):
    """Point-to-plane ICP on a box room gives the same pose and iterations whether its matches come
    from incremental re-searches or from a full query every iteration."""
    from registration import point_to_plane as p2pl

    rng = np.random.default_rng(9)
    faces = []
    for ax in range(3):
        for v in (-1.5, 1.5):
            p = rng.uniform(-1.5, 1.5, size=(800, 3))
            p[:, ax] = v
            faces.append(p)
    P = np.vstack(faces)
    T = geo.se3_exp([0.1, -0.05, 0.04, 0.02, -0.01, 0.03])
    src = geo.transform_points(geo.inverse(T), P[::2]) + rng.normal(scale=0.005, size=(len(P[::2]), 3))
    cfg = IcpConfig(gates_m=(0.5, 0.2), tol_translation_m=1e-10, tol_rotation_rad=1e-10, max_iterations=100)
    out = []
    for threshold in (0, 10**9):
        monkeypatch.setattr(p2pl, "INCREMENTAL_MIN_POINTS", threshold)
        out.append(p2pl.icp_point_to_plane(src, P, None, cfg))
    a, b = out
    assert a.iterations == b.iterations and a.inliers == b.inliers
    assert np.abs(a.transform - b.transform).max() < 1e-12
    assert np.abs(a.transform - T).max() < 0.01
