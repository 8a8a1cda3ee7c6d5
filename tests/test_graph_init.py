"""Initialisation: odometry chain and chordal relaxation (Carlone et al. ICRA 2015), cross-checked with GTSAM."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from core.errors import GpslamError
from slam.graph import PoseGraph, read_g2o
from slam.graph.costs import sesync_objective
from slam.graph.init import chordal_initialisation, initial_poses, odometry_initialisation
from tests.conftest import shared_path
from tests.graph_helpers import synthetic_graph


def _align(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Q expressed so that its node 0 coincides with P's node 0 (the gauge)."""
    return P[0] @ geo.inverse(Q[0]) @ Q


@pytest.mark.parametrize("dim", [2, 3])
def test_noise_free_graph_is_recovered_exactly(dim):
    """With consistent measurements the chordal relaxation is tight: both initialisations return the true poses."""
    rng = np.random.default_rng(7)
    g, P = synthetic_graph(rng, 60, dim, loops=25, noise=0.0)
    for Q in (chordal_initialisation(g), odometry_initialisation(g)):
        np.testing.assert_allclose(_align(P, Q), P, atol=1e-8)


@pytest.mark.parametrize("dim", [2, 3])
def test_chordal_beats_odometry_on_noisy_graphs(dim):
    """With noisy loops the chordal estimate has a (much) lower SE-Sync objective than dead reckoning."""
    rng = np.random.default_rng(8)
    g, _ = synthetic_graph(rng, 200, dim, loops=80, noise=0.05)
    assert sesync_objective(g, chordal_initialisation(g)) < 0.5 * sesync_objective(g, odometry_initialisation(g))


def test_odometry_reproduces_the_files_vertex_guesses():
    """city10000's and sphere2500's VERTEX poses are the odometry chain: composing the i→i+1 edges gives them."""
    for name, dim in [("city10000.g2o", 2), ("sphere2500.g2o", 3)]:
        g = read_g2o(shared_path("pose_graphs", "sesync", name))
        Q = odometry_initialisation(g)
        assert np.abs(Q[:, :dim, 3] - g.poses[:, :dim, 3]).max() < 1e-3 * np.ptp(g.poses[:, :dim, 3])


def test_chordal_cross_checked_with_gtsam_lago():
    """Our chordal rotations agree with gtsam.lago's (a different linear method) to a few degrees on intel and
    CSAIL, and ours reach an SE-Sync objective within 35 % of the published optimum (3.170e1, 5.235e1)."""
    import gtsam

    from slam.backends.gtsam_backend import from_values, _to_pose

    for name, fstar in [("intel.g2o", 52.35), ("CSAIL.g2o", 31.70)]:
        g = read_g2o(shared_path("pose_graphs", "sesync", name))
        P = chordal_initialisation(g)
        a = g.edge_arrays()
        fg = gtsam.NonlinearFactorGraph()
        for e in range(g.num_edges):  # lago needs diagonal noise models
            fg.add(gtsam.BetweenFactorPose2(int(a.ii[e]), int(a.jj[e]), _to_pose(a.measurements[e], 2),
                                            gtsam.noiseModel.Diagonal.Precisions(np.diag(a.information[e]))))
        fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        Q = from_values(gtsam.lago.initialize(fg), g.num_nodes, 2)
        d = np.abs(geo.wrap_angle(geo.matrix_to_xytheta(P)[:, 2] - geo.matrix_to_xytheta(Q)[:, 2]))
        assert np.degrees(np.median(d)) < 2.0 and np.degrees(d.max()) < 5.0
        assert sesync_objective(g, P) < 1.35 * fstar


def test_chordal_cross_checked_with_gtsam_initialize_pose3():
    """On sphere2500 our chordal rotations agree with gtsam.InitializePose3 to a few degrees, and our estimate
    has the lower SE-Sync objective (it solves that objective's relaxation with its κ, τ weights)."""
    import gtsam

    from slam.backends.gtsam_backend import build_factor_graph, from_values

    g = read_g2o(shared_path("pose_graphs", "sesync", "sphere2500.g2o"))
    P = chordal_initialisation(g)
    fg = build_factor_graph(g, anchor=True, anchor_poses=np.tile(np.eye(4), (g.num_nodes, 1, 1)))
    Q = from_values(gtsam.InitializePose3.initialize(fg), g.num_nodes, 3)
    ang = np.linalg.norm(geo.so3_log(np.swapaxes(P[:, :3, :3], 1, 2) @ Q[:, :3, :3]), axis=1)
    assert np.degrees(np.median(ang)) < 6.0 and np.degrees(ang.max()) < 12.0
    assert sesync_objective(g, P) < sesync_objective(g, Q)


def test_initial_poses_errors():
    """Missing VERTEX guesses and broken chains raise project errors, not numpy exceptions."""
    g = PoseGraph(2)
    for k in range(3):
        g.add_node(k)
    g.add_edge(0, 2, np.eye(4), np.eye(3))
    with pytest.raises(GpslamError):
        initial_poses(g, "file")
    with pytest.raises(GpslamError):
        initial_poses(g, "odometry")
    with pytest.raises(GpslamError):
        initial_poses(g, "magic")


def test_zero_edge_weight_equals_removing_the_edge():
    """Per-edge weights scale κ and τ: weight 0 on a loop edge gives the initialisation of the graph without it."""
    rng = np.random.default_rng(10)
    g, _ = synthetic_graph(rng, 50, 3, loops=20, noise=0.05)
    drop = next(e for e, kind in enumerate(g.edge_kinds) if kind == "loop")
    h = PoseGraph(3)
    for nid, T in zip(g.node_ids, g.poses):
        h.add_node(int(nid), T)
    for e, ed in enumerate(g.edges()):
        if e != drop:
            h.add_edge(ed.i, ed.j, ed.measurement, ed.information, ed.kind)
    w = np.ones(g.num_edges)
    w[drop] = 0.0
    np.testing.assert_allclose(chordal_initialisation(g, w), chordal_initialisation(h), atol=1e-9)
