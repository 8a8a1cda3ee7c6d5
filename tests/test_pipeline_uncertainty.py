"""Keyframe uncertainty relative to the newest keyframe, along the most certain path of the graph."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as G
from slam.loops.uncertainty import RelativeUncertainty


def _chain(n: int, var_t: float, var_r: float, planar: bool = True) -> tuple[RelativeUncertainty, np.ndarray]:
    """Keyframes 0 … n one metre apart along x, consecutive edges of the given traces."""
    u = RelativeUncertainty(planar)
    d = 2 if planar else 3
    r = 1 if planar else 3
    cov = np.diag([var_t / d] * d + [var_r / r] * r)
    for k in range(n):
        u.add_edge(k, k + 1, cov)
    pos = np.zeros((n + 1, d))
    pos[:, 0] = np.arange(n + 1)
    return u, pos


@pytest.mark.parametrize("planar", [True, False])
def test_translation_variance_adds_up_along_a_chain(planar):
    u, pos = _chain(30, 4e-4, 0.0, planar)
    unc = u.from_node(30, pos)
    np.testing.assert_allclose(unc.position_var, 4e-4 * (30 - np.arange(31)), rtol=1e-6, atol=1e-10)
    assert unc.position_var[30] == 0.0 and unc.rotation_var[30] == 0.0


def test_heading_noise_matches_monte_carlo_of_a_noisy_chain():
    """First-order lever-arm propagation against sampling: the position of the chain's far end."""
    n, st, sr = 20, 0.02, 0.01
    u, pos = _chain(n, 2 * st**2, sr**2)
    predicted = u.from_node(n, pos).position_var[0]
    rng = np.random.default_rng(5)
    step = G.xytheta_to_matrix(1.0, 0.0, 0.0)
    ends = []
    for _ in range(4000):
        T = np.eye(4)
        for _k in range(n):
            T = T @ step @ G.xytheta_to_matrix(*rng.normal(0.0, [st, st, sr]))
        ends.append(T[:2, 3])
    sampled = float(np.trace(np.cov(np.array(ends).T)))
    # The edge-centre lever arm is half a step longer than the exact one: slightly conservative.
    assert 0.95 * sampled < predicted < 1.25 * sampled
    # Rotation variances add along the chain.
    assert u.from_node(n, pos).rotation_var[0] == pytest.approx(n * sr**2)


def test_parallel_edges_use_the_most_certain_one():
    u = RelativeUncertainty(True)
    u.add_edge(0, 1, np.diag([1e-2, 1e-2, 1e-4]))  # e.g. the wheel edge
    u.add_edge(0, 1, np.diag([1e-4, 1e-4, 1e-6]))  # the registration edge
    unc = u.from_node(1, np.array([[0.0, 0.0], [0.5, 0.0]]))
    assert unc.position_var[0] == pytest.approx(2e-4 + 1e-6 * 0.25**2, rel=1e-6)


def test_a_loop_closure_shortens_the_path_and_the_rotation_follows_it():
    u, pos = _chain(100, 1e-3, 1e-5)
    pos[:, 0] = 10.0 * np.cos(np.linspace(0, 2 * np.pi, 101))  # a loop: keyframe 100 is back at 0
    pos = np.column_stack([pos[:, 0], 10.0 * np.sin(np.linspace(0, 2 * np.pi, 101))])
    before = u.from_node(100, pos)
    u.add_edge(0, 100, np.diag([2e-4, 2e-4, 3e-6]))
    after = u.from_node(100, pos)
    assert before.position_var[0] > 0.1  # a hundred metres of odometry
    assert after.position_var[0] == pytest.approx(4e-4, rel=1e-3)
    assert after.rotation_var[0] == pytest.approx(3e-6)
    # Keyframe 3 is now reached through the closure and three chain edges.
    assert after.rotation_var[3] == pytest.approx(3e-6 + 3e-5)
    assert after.position_var[3] < before.position_var[3]


def test_keyframes_beyond_the_limit_or_unconnected_carry_the_limit():
    u, pos = _chain(10, 1.0, 0.0)
    u_lim = RelativeUncertainty(True, limit_m2=4.5)
    for k in range(10):
        u_lim.add_edge(k, k + 1, np.diag([0.5, 0.5, 0.0]))
    unc = u_lim.from_node(10, pos)
    np.testing.assert_allclose(unc.position_var[6:], [4.0, 3.0, 2.0, 1.0, 0.0])
    assert np.all(unc.position_var[:6] == 4.5)
    # An unconnected keyframe (no edge yet) also gets the limit.
    alone = RelativeUncertainty(True, limit_m2=9.0).from_node(2, np.zeros((3, 2)))
    np.testing.assert_array_equal(alone.position_var, [9.0, 9.0, 0.0])
    assert alone.covariance(0, planar=True).shape == (3, 3)


def test_matches_a_plain_dijkstra_whatever_order_the_edges_arrive_in():
    """Edges added in any order (closures of older keyframes accepted late, either direction, parallel
    ones): the variances equal a textbook Dijkstra over the lever-arm weights, keeping for each pair its
    most certain edge, and the rotation variance is summed along the same path."""
    import heapq

    rng = np.random.default_rng(11)
    K = 60
    pos = np.cumsum(rng.normal(size=(K, 2)), axis=0)
    edges = [(k, k + 1) for k in range(K - 1)] + [(k, k + 1) for k in range(0, K - 1, 3)]
    edges += [tuple(rng.choice(K, 2, replace=False)) for _ in range(40)]
    order = rng.permutation(len(edges))
    covs = [np.diag(np.r_[rng.uniform(1e-4, 1e-2, 2), rng.uniform(1e-6, 1e-4)]) for _ in edges]
    u = RelativeUncertainty(True, limit_m2=1e6)
    for e in order:
        u.add_edge(int(edges[e][0]), int(edges[e][1]), covs[e])
    j = K - 1
    got = u.from_node(j, pos)
    best: dict[tuple[int, int], tuple[float, float]] = {}
    for (a, b), C in zip(edges, covs):
        w = np.trace(C[:2, :2]) + C[2, 2] * np.sum((0.5 * (pos[a] + pos[b]) - pos[j]) ** 2) + 1e-12
        key = (min(a, b), max(a, b))
        if key not in best or w < best[key][0]:
            best[key] = (w, C[2, 2])
    nbrs: dict[int, list[tuple[int, float, float]]] = {k: [] for k in range(K)}
    for (a, b), (w, vr) in best.items():
        nbrs[a].append((b, w, vr))
        nbrs[b].append((a, w, vr))
    dist, rot = np.full(K, np.inf), np.zeros(K)
    dist[j] = 0.0
    heap = [(0.0, j)]
    while heap:
        d, a = heapq.heappop(heap)
        if d > dist[a]:
            continue
        for b, w, vr in nbrs[a]:
            if d + w < dist[b]:
                dist[b], rot[b] = d + w, rot[a] + vr
                heapq.heappush(heap, (dist[b], b))
    np.testing.assert_allclose(got.position_var, dist, rtol=1e-12)
    np.testing.assert_allclose(got.rotation_var, rot, rtol=1e-9, atol=1e-15)


# ---------------------------------------------------------------------- the random-constant heading rate
def _drift_chain(n: int, rate: float) -> tuple[RelativeUncertainty, np.ndarray]:
    """Keyframes 0 … n one metre apart along x, edges without noise of their own, a heading rate σ *rate*."""
    u = RelativeUncertainty(True, limit_m2=1e6, drift_rad_per_m=rate)
    for k in range(n):
        u.add_edge(k, k + 1, np.zeros((3, 3)), length_m=1.0)
    pos = np.zeros((n + 1, 2))
    pos[:, 0] = np.arange(n + 1)
    return u, pos


def test_a_heading_rate_grows_the_rotation_sigma_with_the_path_not_its_square_root():
    n, rate = 200, np.radians(0.015)
    u, pos = _drift_chain(n, rate)
    unc = u.from_node(n, pos)
    k = np.arange(n + 1)
    np.testing.assert_allclose(np.sqrt(unc.rotation_var), rate * (n - k), rtol=1e-9, atol=1e-12)
    # Lever-weighted length from keyframe k: Σ over its n − k edges of the centre's distance to keyframe n.
    moment = 0.5 * (n - k) ** 2
    np.testing.assert_allclose(unc.position_var, 2 * (rate * moment) ** 2 + 1e-12 * (n - k), rtol=1e-9)  # Dijkstra adds 1e-12 per edge
    np.testing.assert_allclose(unc.drift_rotation_var, unc.rotation_var)
    noise = unc.without_drift()
    np.testing.assert_allclose(noise.position_var, 0.0, atol=1e-9)
    # The short-stretch variance of the pairwise closure test carries the same term.
    v = RelativeUncertainty(True, drift_rad_per_m=rate)
    for q in range(n):
        v.add_edge(q, q + 1, np.diag([1e-6, 1e-6, 1e-8]), length_m=1.0)
    assert v.chain_variance(0, n, pos)[1] == pytest.approx(n * 1e-8 + (rate * n) ** 2)


def test_the_heading_rate_bounds_a_sampled_constant_rate_on_every_axis():
    """Monte Carlo of the model itself: a chain of 1 m steps turned by a rate b ~ N(0, σ²) per metre. The
    predicted per-axis variance (position trace / 2) is the sampled variance of the worse axis to first
    order (within the sampling error of 4000 draws and the edge-centre lever arm's half step)."""
    n, rate = 60, 0.002
    u, pos = _drift_chain(n, rate)
    predicted = u.from_node(n, pos).position_var[0] / 2
    rng = np.random.default_rng(3)
    ends = []
    for b in rng.normal(0.0, rate, 4000):
        T = np.eye(4)
        for _k in range(n):
            T = T @ G.xytheta_to_matrix(1.0, 0.0, b)
        ends.append(G.inverse(T)[:2, 3])  # keyframe 0 seen from keyframe n
    worst = float(np.max(np.var(np.array(ends), axis=0)))
    assert 0.9 * worst < predicted < 1.1 * worst


def test_a_closure_resets_the_heading_rate():
    n, rate = 100, np.radians(0.015)
    u = RelativeUncertainty(True, limit_m2=1e6, drift_rad_per_m=rate)
    for k in range(n):
        u.add_edge(k, k + 1, np.diag([1e-4, 1e-4, 1e-5]), length_m=1.0)
    pos = np.column_stack([10.0 * np.cos(np.linspace(0, 2 * np.pi, n + 1)), 10.0 * np.sin(np.linspace(0, 2 * np.pi, n + 1))])
    u.add_edge(0, n, np.diag([1e-4, 1e-4, 1e-6]))  # a closure: no odometry length
    unc = u.from_node(n, pos)
    assert unc.drift_rotation_var[0] == 0.0 and unc.rotation_var[0] == pytest.approx(1e-6)
    # Keyframe 5 is reached through the closure and five one-metre edges: their drift only.
    assert unc.drift_rotation_var[5] == pytest.approx((5 * rate) ** 2)
    assert unc.rotation_var[5] == pytest.approx(1e-6 + 5e-5 + (5 * rate) ** 2)


@pytest.mark.parametrize("seed", range(5))
def test_sums_up_the_tree_are_each_rows_ancestors_in_the_numpy_forms_order(seed):
    """The compiled pointer doubling of from_node: each row plus every ancestor's row, bit for bit the numpy
    form (``acc + where(up != root, acc[up], 0)``, ``up = up[up]``), on random trees with unreached nodes."""
    from slam.loops.uncertainty import sum_to_root

    rng = np.random.default_rng(seed)
    K, root = 300, int(rng.integers(0, 300))
    parent = np.full(K, root)
    placed = [root]
    for v in rng.permutation([v for v in range(K) if v != root]):
        if rng.random() < 0.9:  # the rest hang off nothing (unreached): they point at the root, as from_node's do
            parent[v] = placed[int(rng.integers(0, len(placed)))]
            placed.append(int(v))
    reached = set(placed)
    acc = rng.random((K, 3)) * 10.0 ** rng.uniform(-6, 2, (K, 3))
    acc[root] = 0.0
    up, ref = parent.copy(), acc.copy()
    while True:
        nxt = up[up]
        ref = ref + np.where((up != root)[:, None], ref[up], 0.0)
        if np.array_equal(nxt, up):
            break
        up = nxt
    got = sum_to_root(acc, parent.astype(np.int64), root)
    assert got.tobytes() == ref.tobytes()
    for v in rng.choice(K, 20, replace=False):
        chain, u = acc[v].copy(), parent[v]
        while v in reached and u != root:
            chain += acc[u]
            u = parent[u]
        np.testing.assert_allclose(got[v], chain, rtol=1e-12)
