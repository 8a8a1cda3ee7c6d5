"""Disconnected pose graphs: refused by ``slam solve`` unless --allow-disconnected, which anchors every
component and says so; then both back ends give the same solution."""

from __future__ import annotations

import json

import numpy as np

from core import geometry as geo
from slam.graph import PoseGraph, read_g2o, write_g2o
from tests.cli_helpers import slam
from tests.graph_helpers import synthetic_graph


def _solve(args, capsys):
    return slam(["solve", *args], capsys)


def _two_pieces(rng, prior_on_second: bool = False) -> tuple[PoseGraph, list[int]]:
    """Two noisy chains with loops (ids 0-14 and 20-34) that no edge joins; vertices at perturbed poses."""
    a, _ = synthetic_graph(rng, 15, 2, loops=3, noise=0.02)
    b, _ = synthetic_graph(rng, 15, 2, loops=3, noise=0.02)
    g = PoseGraph(2)
    for part, off in ((a, 0), (b, 20)):
        for vid, T in zip(part.node_ids, part.poses):
            g.add_node(int(vid) + off, T @ geo.xytheta_to_matrix(*rng.normal(0, 0.05, 3)))
        for e in part.edges():
            g.add_edge(e.i + off, e.j + off, e.measurement, e.information)
    if prior_on_second:
        g.add_prior(20, b.poses[0] @ geo.xytheta_to_matrix(50.0, 0.0, 0.0), np.eye(3) * 100.0)
    return g, [0, 20]


def test_a_disconnected_graph_is_refused(tmp_path, rng, capsys):
    """Two components and no anchor between them: exit 2 with one line naming the file and the parts
    (the placement of the second part relative to the first is not determined by the file)."""
    g, _ = _two_pieces(rng)
    p = tmp_path / "two.g2o"
    write_g2o(g, p)
    for backend in ("gtsam", "chordal"):
        code, out, err = _solve([str(p), "--backend", backend], capsys)
        assert code == 2 and out == ""
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {p}: ") and "not connected" in lines[0]
        assert "2 components" in lines[0] and "--allow-disconnected" in lines[0]


def test_allow_disconnected_anchors_each_component_and_the_back_ends_agree(tmp_path, rng, capsys):
    """--allow-disconnected: a warning says each component is held at its first node; both back ends then
    keep nodes 0 and 20 at their file poses and reach the same poses (the cut-off part no longer drifts
    apart between them)."""
    g, firsts = _two_pieces(rng)
    p = tmp_path / "two.g2o"
    write_g2o(g, p)
    sol = {}
    for backend in ("gtsam", "chordal"):
        out = tmp_path / f"{backend}.g2o"
        code, stdout, err = _solve([str(p), "--backend", backend, "--init", "file", "--allow-disconnected",
                                    "--out", str(out)], capsys)
        assert code == 0, err
        assert "warning:" in err and "2 components" in err and "0, 20" in err
        assert json.loads(stdout)["nodes"] == 30
        sol[backend] = read_g2o(out)
        for vid in firsts:
            np.testing.assert_allclose(sol[backend].pose(vid), g.pose(vid), atol=1e-6)
    diff = np.abs(sol["gtsam"].poses[:, :2, 3] - sol["chordal"].poses[:, :2, 3]).max()
    assert diff < 0.05  # the two objectives differ (log-map vs chordal), the gauge does not


def test_a_component_with_its_own_prior_is_anchored(tmp_path, rng, capsys):
    """A second component that carries a prior is determined by it: no refusal, no flag needed."""
    g, _ = _two_pieces(rng, prior_on_second=True)
    g.fixed_ids = [0]
    p = tmp_path / "prior.g2o"
    write_g2o(g, p)
    code, _, err = _solve([str(p), "--backend", "chordal", "--init", "file"], capsys)
    assert code == 0, err
    assert "warning" not in err


def test_anchor_of_a_connected_graph_is_unchanged(rng):
    """The gauge of a connected graph stays what it was: node index 0, none with priors, FIX'ed nodes."""
    g, _ = synthetic_graph(rng, 10, 2, loops=2)
    assert g.anchor_indices().tolist() == [0]
    g.add_prior(3, g.pose(3), np.eye(3))
    assert g.anchor_indices().tolist() == []
    g.fixed_ids = [5]
    assert g.anchor_indices().tolist() == [5]
