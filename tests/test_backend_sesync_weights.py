"""Edges whose information matrix is not positive definite but whose SE-Sync weights κ, τ are positive
(Rosen et al. 2019, eq. 14): read, solved by the chordal back end with one warning, refused by GTSAM
with the edges named; an edge without positive κ, τ is refused at its line."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from core.errors import GpslamError, GraphFormatError
from slam.backends.chordal import solve_chordal
from slam.backends.gtsam_backend import optimize
from slam.cli import main
from slam.graph import PoseGraph, read_g2o, write_g2o
from slam.graph.costs import chordal_weights
from slam.graph.init import chordal_initialisation
from tests.conftest import SHARED

EVERY = 97  # every 97th edge gets an indefinite information matrix


def _sesync(name: str):
    p = SHARED / "pose_graphs" / "sesync" / name
    assert p.exists(), f"shared data missing: {p}"  # needs ../shared/data: fail, never skip
    return read_g2o(p)


def _coupled(graph):
    """A copy whose every 97th edge has a translation–rotation coupling large enough to make its information
    indefinite while its translation and rotation blocks — and so κ and τ — stay as they were."""
    d = graph.dim
    g = PoseGraph(d)
    for vid, par in zip(graph.node_ids, graph.node_params):
        g.add_node(int(vid), params=par)
    info = graph.edge_arrays().information.copy()
    hit = list(range(0, graph.num_edges, EVERY))
    for e in hit:
        I = info[e]
        I[0, d] = I[d, 0] = 2.0 * np.sqrt(I[0, 0] * I[d, d])  # |I_xr| > sqrt(I_xx I_rr): a negative 2×2 minor
        assert np.linalg.eigvalsh(I)[0] < 0
    ii, jj = graph.edge_ids
    for i, j, par, I, kind in zip(ii, jj, graph.edge_params, info, graph.edge_kinds):
        g.add_edge(int(i), int(j), None, I, kind, params=par)
    return g, hit


@pytest.fixture(params=["intel.g2o", "tinyGrid3D.g2o"])
def graphs(request, tmp_path):
    orig = _sesync(request.param)
    mod, hit = _coupled(orig)
    p = tmp_path / f"coupled_{request.param}"
    write_g2o(mod, p)
    return orig, p, hit


def test_indefinite_information_with_positive_weights_is_read(graphs):
    """The reader accepts the file (it refused it as 'not positive definite'); κ and τ equal the original's."""
    orig, p, _ = graphs
    g = read_g2o(p)
    for a, b in zip(chordal_weights(g), chordal_weights(orig)):
        np.testing.assert_array_equal(a, b)
    assert not np.all(np.linalg.eigvalsh(g.edge_arrays().information)[:, 0] > 0)


def test_chordal_solution_equals_the_original_and_warns_once_with_the_count(graphs):
    """The chordal back end sees only κ and τ, so the coupled graph's optimum is the original's bit for bit;
    it warns once, with the number of such edges."""
    orig, p, hit = graphs
    g = read_g2o(p)
    P0 = chordal_initialisation(orig)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = solve_chordal(g, P0, max_iterations=20)
    want = solve_chordal(orig, P0, max_iterations=20)
    np.testing.assert_array_equal(got.poses, want.poses)
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == 1 and f"{len(hit)} edge" in msgs[0] and "not positive definite" in msgs[0]


def test_gtsam_names_the_edges_it_cannot_use(graphs):
    """GTSAM's Gaussian noise needs a positive-definite information (it factors it silently into a wrong
    square root otherwise): the back end refuses, naming the first such edges by their vertices."""
    _, p, hit = graphs
    g = read_g2o(p)
    i, j = (int(a[hit[0]]) for a in g.edge_ids)
    with pytest.raises(GpslamError) as ei:
        optimize(g)
    msg = str(ei.value)
    assert f"{len(hit)} edge" in msg and f"{i} → {j}" in msg and "--backend chordal" in msg


def test_cli_solve_chordal_reports_no_gtsam_error_for_such_a_graph(graphs, capsys):
    """`slam solve --backend chordal` succeeds with one warning line; the GTSAM χ² it cannot compute is null;
    `--backend gtsam` exits 2 with one line."""
    _, p, hit = graphs
    with pytest.raises(SystemExit) as ei:
        main(["solve", str(p), "--backend", "chordal"])
    cap = capsys.readouterr()
    assert (ei.value.code or 0) == 0, cap.err
    rec = json.loads(cap.out)
    assert rec["gtsam_error"] is None and np.isfinite(rec["sesync_objective"])
    assert [ln for ln in cap.err.splitlines() if ln.startswith("warning:")] == cap.err.strip().splitlines()
    assert len(cap.err.strip().splitlines()) == 1
    with pytest.raises(SystemExit) as ei:
        main(["solve", str(p), "--backend", "gtsam"])
    cap = capsys.readouterr()
    assert ei.value.code == 2 and len(cap.err.strip().splitlines()) == 1 and cap.err.startswith(f"error: {p}: ")


@pytest.mark.parametrize("info,what", [
    ("1 0 0 1 0 -1", "κ"),  # I_θθ < 0
    ("-1 0 0 -1 0 1", "τ"),  # negative translation block
    ("0 0 0 0 0 1", "τ"),  # singular translation block
])
def test_an_edge_without_positive_weights_is_refused_at_its_line(tmp_path, info, what):
    """κ ≤ 0 or τ ≤ 0 (or a singular translation block): no back end can use the edge: error at its line."""
    p = tmp_path / "bad.g2o"
    p.write_text(f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 {info}\n")
    with pytest.raises(GraphFormatError) as ei:
        read_g2o(p)
    assert ei.value.where == "line 3" and what in ei.value.what
