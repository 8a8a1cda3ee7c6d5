"""Variance components of a pose graph's edge groups: drawn with known scales of their modelled covariances,
the estimate recovers them from the graph's redundancy; unit scales change nothing; each component scales
its own part of a covariance; the pipeline's final solve uses them only when the closures give enough redundancy."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as G
from slam.backends.gtsam_backend import optimize
from slam.backends.variance_components import covariance_components, estimate_variance_components, scaled_graph
from slam.graph import PoseGraph
from slam.loops import LoopClosure
from slam.pipeline.backend import PipelineBackend
from slam.pipeline.config import BackendConfig, LoopConfig


def _exp(xi: np.ndarray, dim: int) -> np.ndarray:
    return G.se2_exp(xi) if dim == 2 else G.se3_exp(xi)


def _laps(dim: int, laps: int = 3, per_lap: int = 120) -> np.ndarray:
    """Poses around a 12 m circle, *laps* times (a gentle rise and roll in 3D)."""
    k = np.arange(laps * per_lap)
    a = 2 * np.pi * k / per_lap
    P = G.xytheta_to_matrix(6 * np.sin(a), 6 - 6 * np.cos(a), a)
    if dim == 3:
        P = P @ G.se3_exp(np.column_stack([np.zeros((len(k), 2)), 0.2 * np.sin(a / 3), 0.05 * np.cos(a), 0.03 * np.sin(a),
                                           np.zeros(len(k))]))
    return P


def _modelled(dim: int, kind: str) -> np.ndarray:
    """Modelled covariances with correlated translation and rotation (a lever arm)."""
    if dim == 2:
        base = {"registration": np.diag([0.02, 0.01, np.radians(0.5)]), "wheel": np.diag([0.05, 0.03, np.radians(1.0)]),
                "loop": np.diag([0.03, 0.03, np.radians(0.6)])}[kind]
        cov = base @ base
        cov[1, 2] = cov[2, 1] = 0.6 * np.sqrt(cov[1, 1] * cov[2, 2])
        return cov
    s = {"registration": (0.02, 0.004), "wheel": (0.05, 0.015), "loop": (0.03, 0.01)}[kind]
    cov = np.diag([s[0] ** 2] * 3 + [s[1] ** 2] * 3)
    cov[1, 5] = cov[5, 1] = 0.5 * s[0] * s[1]
    return cov


TRUE_SCALES = {("registration", "translation"): 0.25, ("registration", "rotation"): 0.1,
               ("wheel", "translation"): 2.0, ("wheel", "rotation"): 1.0,
               ("loop", "translation"): 0.5, ("loop", "rotation"): 0.5}


def _drawn(cov: np.ndarray, group: str, dim: int, rng: np.random.Generator) -> np.ndarray:
    """A tangent error drawn from the covariance whose components are scaled by the group's true scales."""
    nt = 2 if dim == 2 else 3
    C, A_inv, B_inv = covariance_components(np.linalg.inv(cov)[None], nt)
    A = np.linalg.inv(A_inv[0]) * TRUE_SCALES[(group, "translation")]
    B = np.linalg.inv(B_inv[0]) * TRUE_SCALES[(group, "rotation")]
    L = np.eye(len(cov))
    L[:nt, nt:] = C[0]
    D = np.zeros_like(cov)
    D[:nt, :nt], D[nt:, nt:] = A, B
    return rng.multivariate_normal(np.zeros(len(cov)), L @ D @ L.T)


def _graph(dim: int, seed: int = 1) -> tuple[PoseGraph, list[str], np.ndarray]:
    """Registration and wheel edges between consecutive poses and closures between laps, each drawn with its
    group's true scales of the modelled covariance it carries."""
    rng = np.random.default_rng(seed)
    truth = _laps(dim)
    g = PoseGraph(dim)
    groups: list[str] = []
    for k, T in enumerate(truth):
        g.add_node(k, T)

    def edge(i: int, j: int, group: str) -> None:
        cov = _modelled(dim, group)
        Z = G.relative(truth[i], truth[j]) @ _exp(_drawn(cov, group, dim, rng), dim)
        g.add_edge(i, j, Z, np.linalg.inv(cov), "odometry" if group != "loop" else "loop")
        groups.append(group)

    for k in range(1, len(truth)):
        edge(k - 1, k, "registration")
        edge(k - 1, k, "wheel")
    for k in range(0, len(truth) - 120, 2):
        edge(k, k + 120, "loop")
    return g, groups, truth


@pytest.mark.parametrize("dim", [2, 3])
def test_the_scales_each_group_was_drawn_with_are_recovered(dim):
    g, groups, _ = _graph(dim)
    P = optimize(g, g.poses, method="lm", use_kernels=False).poses
    vc = estimate_variance_components(g, P, groups, max_iterations=60)
    assert vc.converged
    for key, truth in TRUE_SCALES.items():
        # The estimate's relative σ is √(2 / redundancy): the surest group determines the poses and keeps the
        # least redundancy (50–150 here), the others hundreds.
        assert vc.redundancy[key] > 40
        assert vc.scales[key] == pytest.approx(truth, rel=0.3), key
    # The shares of the redundancy add up to observations − unknowns.
    d = g.dof
    assert sum(vc.redundancy.values()) == pytest.approx(d * (g.num_edges - g.num_nodes + 1), rel=0.05)


def test_scaled_graph_scales_each_component_and_only_it():
    g, groups, _ = _graph(2)
    same = scaled_graph(g, groups, {})
    np.testing.assert_allclose(same.edge_arrays().information, g.edge_arrays().information, rtol=1e-9)
    scales = {("registration", "translation"): 3.0, ("registration", "rotation"): 0.2}
    out = scaled_graph(g, groups, scales)
    e = groups.index("registration")
    S0 = np.linalg.inv(g.edge_arrays().information[e])
    S1 = np.linalg.inv(out.edge_arrays().information[e])
    # The rotation block and the translation it carries scale by the rotation's factor ...
    assert S1[2, 2] == pytest.approx(0.2 * S0[2, 2])
    np.testing.assert_allclose(S1[:2, 2], 0.2 * S0[:2, 2])
    # ... and the translation's own part (what is left once the rotation's share is taken out) by its own.
    own0 = S0[:2, :2] - np.outer(S0[:2, 2], S0[2, :2]) / S0[2, 2]
    own1 = S1[:2, :2] - np.outer(S1[:2, 2], S1[2, :2]) / S1[2, 2]
    np.testing.assert_allclose(own1, 3.0 * own0)
    w = groups.index("wheel")
    np.testing.assert_allclose(out.edge_arrays().information[w], g.edge_arrays().information[w])


def _backend(closures: int) -> tuple[PipelineBackend, np.ndarray]:
    rng = np.random.default_rng(3)
    truth = _laps(2, laps=2, per_lap=120)
    be = PipelineBackend(BackendConfig(kind="gtsam", variance_components=True), LoopConfig(), planar=True)
    for k, T in enumerate(truth):
        be.add_keyframe(k, T)
        if k:
            for group in ("registration", "wheel"):
                cov = _modelled(2, group)
                Z = G.relative(truth[k - 1], T) @ G.se2_exp(_drawn(cov, group, 2, rng))
                be.add_odometry(k - 1, k, Z, cov, group=group)
    for k in range(0, 2 * closures, 2):
        cov = _modelled(2, "loop")
        Z = G.relative(truth[k], truth[k + 120]) @ G.se2_exp(_drawn(cov, "loop", 2, rng))
        be.add_loop(LoopClosure(k, k + 120, Z, cov, 1.0, 0.01, "spatial"))
    be.update(True)
    return be, truth


def test_the_final_solve_takes_the_scales_when_the_closures_give_enough_redundancy():
    be, _ = _backend(closures=60)
    before = be.graph.edge_arrays().information.copy()
    be.finish()
    vc = be.variance_components
    assert vc is not None
    assert vc.scales[("registration", "rotation")] < 0.5 < vc.scales[("wheel", "translation")]
    # graph.g2o will hold what the final solve used: the scaled covariances and no kernels.
    assert all(e.kernel is None for e in be.graph.edges())
    after = be.graph.edge_arrays().information
    assert len(after) == len(before) - be.pruned_loops
    assert be.graph.edge_arrays().kinds.tolist().count(1) == 60 - be.pruned_loops
    reg = [e for e, g in enumerate(be.groups) if g == "registration"]
    np.testing.assert_allclose(np.linalg.inv(after[reg[0]])[2, 2],
                               vc.scales[("registration", "rotation")] * np.linalg.inv(before[reg[0]])[2, 2])


def test_a_few_closures_leave_the_model_as_it_is():
    be, _ = _backend(closures=3)
    assert be.config.variance_components
    before = be.graph.edge_arrays().information.copy()
    be.finish()
    assert be.variance_components is None
    np.testing.assert_allclose(be.graph.edge_arrays().information, before)
