"""Costs: SE-Sync objective (IJRR eq. 12) with κ/τ from the information matrix, and GTSAM's χ²."""

from __future__ import annotations

import numpy as np

from core import geometry as geo
from slam.graph import PoseGraph
from slam.graph.costs import chordal_weights, gtsam_error, sesync_objective
from tests.graph_helpers import synthetic_graph


def test_weights_follow_sesync_utils():
    """2D: τ = 2/tr(I_tt⁻¹), κ = I_θθ; 3D: τ = 3/tr(I_tt⁻¹), κ = 3/(2 tr(I_rr⁻¹)) — isotropic cases in closed form."""
    g = PoseGraph(2)
    g.add_node(0, np.eye(4)), g.add_node(1, np.eye(4))
    g.add_edge(0, 1, np.eye(4), np.diag([4.0, 4.0, 9.0]))
    g.add_edge(0, 1, np.eye(4), np.diag([1.0, 3.0, 2.0]), "loop")
    k, t = chordal_weights(g)
    np.testing.assert_allclose(k, [9.0, 2.0])
    np.testing.assert_allclose(t, [4.0, 2.0 / (1.0 + 1.0 / 3.0)])
    g3 = PoseGraph(3)
    g3.add_node(0, np.eye(4)), g3.add_node(1, np.eye(4))
    g3.add_edge(0, 1, np.eye(4), np.diag([5.0] * 3 + [8.0] * 3))
    k, t = chordal_weights(g3)
    np.testing.assert_allclose(k, [4.0])
    np.testing.assert_allclose(t, [5.0])


def test_planar_rotation_term_is_8_sin_squared():
    """For planar rotations ‖R_j − R_i R̃‖_F² = 8 sin²(δθ/2) and the translation term is τ‖Δt‖²."""
    g = PoseGraph(2)
    g.add_node(0, np.eye(4))
    g.add_node(1, geo.xytheta_to_matrix(1.0, 2.0, 0.7))
    g.add_edge(0, 1, geo.xytheta_to_matrix(1.5, 2.0, 0.2), np.diag([3.0, 3.0, 5.0]))
    expected = 5.0 * 8.0 * np.sin(0.5 / 2) ** 2 + 3.0 * 0.5**2
    assert np.isclose(sesync_objective(g), expected)


def test_zero_at_truth_and_invariant_to_the_gauge():
    """The objective vanishes on consistent data and does not change when all poses move by one rigid motion."""
    rng = np.random.default_rng(1)
    g, P = synthetic_graph(rng, 30, 3, loops=10, noise=0.0)
    assert sesync_objective(g, P) < 1e-20
    g, P = synthetic_graph(rng, 30, 3, loops=10, noise=0.05)
    G = geo.se3_exp([1.0, -2.0, 0.5, 0.3, -0.2, 0.9])
    assert np.isclose(sesync_objective(g, P), sesync_objective(g, G @ P), rtol=1e-12)


def test_gtsam_error_is_half_the_log_map_chi2():
    """graph.error equals ½ Σ eᵀΩe with e = Log(Z⁻¹ X_i⁻¹ X_j) in our (translation-first) order, for an
    anisotropic full information matrix in 3D — this checks the Pose3 information reordering."""
    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + np.eye(6)
    g, P = synthetic_graph(rng, 6, 3, loops=3, noise=0.05, info=info)
    a = g.edge_arrays()
    e = geo.se3_log(geo.inverse(a.measurements) @ geo.inverse(P[a.ii]) @ P[a.jj])
    expected = 0.5 * np.einsum("ma,mab,mb->", e, a.information, e)
    assert np.isclose(gtsam_error(g, P), expected, rtol=1e-9)
    g2, P2 = synthetic_graph(rng, 6, 2, loops=3, noise=0.05, info=info[:3, :3])
    a = g2.edge_arrays()
    e = geo.se2_log(geo.inverse(a.measurements) @ geo.inverse(P2[a.ii]) @ P2[a.jj])
    assert np.isclose(gtsam_error(g2, P2), 0.5 * np.einsum("ma,mab,mb->", e, a.information, e), rtol=1e-9)
