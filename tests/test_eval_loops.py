"""Loop-closure scoring: Hess et al. 2016 precision and ground-truth precision/recall on constructed graphs."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo

pytest.importorskip("slam.graph")
from slam.graph import PoseGraph, read_g2o, write_g2o  # noqa: E402
from evaluation.loops import loop_edges_from_graph, score_against_truth, score_loops, true_revisits  # noqa: E402

N_LAP = 40


def _two_laps() -> np.ndarray:
    """A circle of radius 5 m driven twice: node j + N_LAP is at node j's pose."""
    th = np.linspace(0, 2 * np.pi, N_LAP, endpoint=False)
    th = np.concatenate([th, th])
    return geo.xytheta_to_matrix(5 * np.cos(th), 5 * np.sin(th), th + np.pi / 2)


def _graph(gt: np.ndarray, loops: list[tuple[int, int, np.ndarray]]) -> PoseGraph:
    g = PoseGraph(2)
    for k, T in enumerate(gt):
        g.add_node(k, T)
    info = np.diag([100.0, 100.0, 400.0])
    for k in range(len(gt) - 1):
        g.add_edge(k, k + 1, geo.relative(gt[k], gt[k + 1]), info, "odometry")
    for i, j, C in loops:
        g.add_edge(i, j, geo.relative(gt[i], gt[j]) @ C, info, "loop")
    return g


def test_precision_counts_constraints_within_20cm_and_1deg(tmp_path):
    """With the true poses as the solution, a loop corrupted by C is violated by exactly (‖t_C‖, angle C):
    corruptions (0.1 m, 0.5°) count correct, (0.3 m, 0°) and (0 m, 2°) do not → precision 2/4."""
    gt = _two_laps()
    C = [geo.xytheta_to_matrix(0.1, 0.0, np.radians(0.5)), geo.xytheta_to_matrix(0.3, 0, 0),
         geo.xytheta_to_matrix(0, 0, np.radians(2.0)), np.eye(4)]
    g = _graph(gt, [(j, j + N_LAP, c) for j, c in zip((3, 10, 20, 30), C)])
    write_g2o(g, tmp_path / "g.g2o")  # loop kinds must survive the file
    g2 = read_g2o(tmp_path / "g.g2o")
    loops = loop_edges_from_graph(g2)
    assert len(loops) == 4
    s = score_loops(loops, gt)
    np.testing.assert_allclose(s.trans_violation, [0.1, 0.3, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(s.rot_violation_deg, [0.5, 0.0, 2.0, 0.0], atol=1e-7)
    assert s.correct.tolist() == [True, False, False, True] and s.precision == 0.5


def test_precision_is_gauge_invariant():
    """Moving the whole solution by a rigid transform does not change any violation."""
    gt = _two_laps()
    g = _graph(gt, [(j, j + N_LAP, geo.xytheta_to_matrix(0.05 * j + 0.01, 0, 0)) for j in range(0, N_LAP, 4)])
    loops = loop_edges_from_graph(g)
    a = score_loops(loops, gt)
    b = score_loops(loops, geo.xytheta_to_matrix(3, 4, 1.0) @ gt)
    np.testing.assert_allclose(a.trans_violation, b.trans_violation, atol=1e-12)
    assert a.precision == b.precision


def test_truth_precision_and_recall_known_answer():
    """Lap 2 revisits lap 1 node for node (40 true-revisit nodes). 20 exact closures on distinct revisit nodes
    + 5 closures off by 1 m give precision 20/25 and recall 20/40."""
    gt = _two_laps()
    assert true_revisits(gt, revisit_radius=0.3, min_separation=10).tolist() == list(range(N_LAP, 2 * N_LAP))
    good = [(j, j + N_LAP, np.eye(4)) for j in range(20)]
    bad = [(j, j + N_LAP, geo.xytheta_to_matrix(1.0, 0, 0)) for j in range(20, 25)]
    g = _graph(gt, good + bad)
    s = score_against_truth(loop_edges_from_graph(g), gt, revisit_radius=0.3, min_separation=10)
    assert s.n_loops == 25 and s.n_true_positive == 20 and s.precision == pytest.approx(0.8)
    assert s.n_revisit_nodes == 40 and s.n_revisit_nodes_found == 20 and s.recall == pytest.approx(0.5)


def test_truth_errors_tell_an_imprecise_closure_from_a_gross_one():
    """Closures off the truth by known amounts: exact ones, 1.2° ones (wrong by the 1° criterion, right place),
    1.5 m and 10° ones (gross: beyond the revisit radius or 5°). The errors are the corruptions, and only the
    last two kinds are gross."""
    gt = _two_laps()
    kinds = [np.eye(4)] * 6 + [geo.xytheta_to_matrix(0.05, 0, np.radians(1.2))] * 3 \
        + [geo.xytheta_to_matrix(1.5, 0, 0)] * 2 + [geo.xytheta_to_matrix(0, 0, np.radians(10.0))]
    g = _graph(gt, [(j, j + N_LAP, c) for j, c in enumerate(kinds)])
    s = score_against_truth(loop_edges_from_graph(g), gt, revisit_radius=1.0, min_separation=10)
    np.testing.assert_allclose(s.trans_error_m, [0.0] * 6 + [0.05] * 3 + [1.5] * 2 + [0.0], atol=1e-9)
    np.testing.assert_allclose(s.rot_error_deg, [0.0] * 6 + [1.2] * 3 + [0.0] * 2 + [10.0], atol=1e-7)
    assert s.n_true_positive == 6
    assert s.gross.tolist() == [False] * 9 + [True] * 3
    d = s.to_dict()
    assert d["n_gross"] == 3 and d["trans_error_m"]["max"] == pytest.approx(1.5)
    assert d["rot_error_deg"]["p50"] == pytest.approx(0.0, abs=1e-7) and d["rot_error_deg"]["max"] == pytest.approx(10.0)
