"""g2o / TORO reading and writing: exact round trips, information order, kinds, kernels, malformed lines."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from core.errors import GraphFormatError
from slam.graph import PRIOR_NODE, PoseGraph, RobustKernel, read_g2o, read_graph, read_toro, write_g2o, write_toro
from tests.conftest import shared_path
from tests.graph_helpers import synthetic_graph


def _same(a: PoseGraph, b: PoseGraph) -> None:
    assert a.dim == b.dim
    np.testing.assert_array_equal(a.node_ids, b.node_ids)
    np.testing.assert_array_equal(a.node_params, b.node_params)
    np.testing.assert_array_equal(a.edge_ids[0], b.edge_ids[0])
    np.testing.assert_array_equal(a.edge_ids[1], b.edge_ids[1])
    np.testing.assert_array_equal(a.edge_params, b.edge_params)
    np.testing.assert_array_equal(a.edge_arrays().information, b.edge_arrays().information)
    np.testing.assert_array_equal(a.edge_arrays().measurements, b.edge_arrays().measurements)
    assert a.edge_kinds == b.edge_kinds
    assert a.edge_kernels == b.edge_kernels
    assert a.fixed_ids == b.fixed_ids


@pytest.mark.parametrize("name", ["intel.g2o", "sphere2500.g2o", "CSAIL.g2o", "tinyGrid3D.g2o"])
def test_g2o_round_trip_is_bit_exact(tmp_path, name):
    """read → write → read reproduces every number bit for bit (2D, 3D, with and without VERTEX lines)."""
    g = read_g2o(shared_path("pose_graphs", "sesync", name))
    out = tmp_path / "out.g2o"
    write_g2o(g, out)
    _same(g, read_g2o(out))


def test_g2o_counts_match_the_sesync_tables():
    """Pose and edge counts of the SE-Sync files equal Tables 1-2 of the IJRR paper (as listed in SOURCE.md)."""
    for name, n, m in [("CSAIL", 1045, 1172), ("intel", 1728, 2512), ("manhattan", 3500, 5453),
                       ("sphere2500", 2500, 4949)]:
        g = read_g2o(shared_path("pose_graphs", "sesync", f"{name}.g2o"))
        assert (g.num_nodes, g.num_edges) == (n, m)


def test_toro_information_order_differs_from_g2o():
    """TORO's CSAIL carries the same measurements as SE-Sync's CSAIL.g2o and the same θθ information (I_tt in
    TORO's 4th slot = g2o's I33 in its 6th), which only holds when the TORO order xx xy yy tt xt yt is honoured."""
    t = read_toro(shared_path("pose_graphs", "carlone_via_nanopgo", "CSAIL_P_toro.graph"))
    g = read_g2o(shared_path("pose_graphs", "sesync", "CSAIL.g2o"))
    np.testing.assert_array_equal(t.edge_params, g.edge_params)
    np.testing.assert_array_equal(t.edge_arrays().information[:, 2, 2], g.edge_arrays().information[:, 2, 2])
    assert np.all(np.linalg.eigvalsh(t.edge_arrays().information) > 0)


def test_toro_round_trip_and_format_detection(tmp_path):
    """TORO read → write → read is bit-exact, and read_graph picks the TORO reader by content."""
    src = shared_path("pose_graphs", "carlone_via_nanopgo", "CSAIL_P_toro.graph")
    g = read_graph(src)
    out = tmp_path / "g.graph"
    write_toro(g, out)
    _same(g, read_toro(out))
    line = out.read_text().splitlines()[g.num_nodes]
    vals = [float(v) for v in line.split()[3:]]
    info = g.edge_arrays().information[0]
    assert vals[3:] == [info[0, 0], info[0, 1], info[1, 1], info[2, 2], info[0, 2], info[1, 2]]


@pytest.mark.parametrize("dim", [2, 3])
def test_kinds_kernels_priors_and_fix_round_trip(tmp_path, dim):
    """Edge kinds that differ from the j = i+1 default, robust kernels, priors and FIX survive write → read."""
    rng = np.random.default_rng(3)
    g, P = synthetic_graph(rng, 8, dim, loops=3, noise=0.01)
    d = g.dof
    g.add_edge(2, 3, geo.relative(P[2], P[3]), 2 * np.eye(d), "loop", RobustKernel("cauchy", 2.5))
    g.add_edge(5, 2, geo.relative(P[5], P[2]), np.eye(d), "odometry")
    g.add_prior(4, P[4], 7 * np.eye(d), RobustKernel("huber", 0.5))
    g.set_kernel(RobustKernel("geman_mcclure", 1.0), ("loop",))
    g.fixed_ids = [0]
    out = tmp_path / "k.g2o"
    write_g2o(g, out)
    text = out.read_text()
    assert "# gpslam:edge kind=odometry" in text
    h = read_g2o(out)
    _same(g, h)
    assert h.edge_ids[0][-1] == PRIOR_NODE and h.edge_kinds[-1] == "prior"


def test_written_file_is_readable_by_gtsam(tmp_path):
    """Our tag comments do not disturb GTSAM's own g2o reader: it finds the same number of edges."""
    import gtsam

    rng = np.random.default_rng(4)
    g, _ = synthetic_graph(rng, 10, 3, loops=4, noise=0.01)
    g.add_edge(1, 2, g.edge(1).measurement, np.eye(6), "loop", RobustKernel("cauchy", 1.0))
    out = tmp_path / "g.g2o"
    write_g2o(g, out)
    graph, initial = gtsam.readG2o(str(out), True)
    assert graph.size() == g.num_edges and initial.size() == g.num_nodes


BAD = [
    ("EDGE_SE2 0 1 0.1 0.2\n", "line 1"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 zero 0\n", "line 2"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", "line 2"),
    ("VERTEX_SE2 0 0 0 0\n\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n", "line 3"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 -1\n", "line 2"),
    ("FOO 1 2 3\n", "line 1"),
    ("VERTEX_SE2 -1 0 0 0\n", "line 1"),
    ("# gpslam:edge kind=loop colour=red\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n", "line 1"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", "line 1"),
]


@pytest.mark.parametrize("text,where", BAD)
def test_malformed_line_names_file_and_line(tmp_path, text, where):
    """Every malformed record raises GraphFormatError whose message names the file and the line."""
    p = tmp_path / "bad.g2o"
    p.write_text(text)
    with pytest.raises(GraphFormatError) as exc:
        read_g2o(p)
    assert str(p) in str(exc.value) and where in str(exc.value)


def test_malformed_toro_line(tmp_path):
    """A TORO EDGE2 with a missing information entry names file and line."""
    p = tmp_path / "bad.graph"
    p.write_text("VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0\n")
    with pytest.raises(GraphFormatError, match="line 3"):
        read_toro(p)


def test_default_kinds_and_nodes_without_vertices():
    """Without tags, j = i+1 edges are odometry and others loops; VERTEX-less files get nodes in id order."""
    g = read_g2o(shared_path("pose_graphs", "sesync", "CSAIL.g2o"))
    i, j = g.edge_ids
    kinds = np.array(g.edge_kinds)
    assert np.all((kinds == "odometry") == (j == i + 1))
    np.testing.assert_array_equal(g.node_ids, np.arange(g.num_nodes))
    assert not g.has_initial_guess
