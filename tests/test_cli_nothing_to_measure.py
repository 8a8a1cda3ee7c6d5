"""Nothing to measure is an error (exit 2, one line), never 'nan' with exit 0: eval rpe with no pair at the
given distance, eval loops on a graph without loop closures, and slam run --relations/--gt that match
no scan (then nothing is written either)."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from core.trajectory import Trajectory, write_tum
from slam.graph import PoseGraph, write_g2o
from tests.cli_helpers import corridor_log, one_error_line
from tests.cli_helpers import slam as _slam

pytestmark = pytest.mark.xdist_group("pipeline")


def _one_error(code, out, err, *names):
    one_error_line(code, err, *names)
    assert "nan" not in out


def _traj(n=30):
    th = np.linspace(0, 2 * np.pi, n)
    return Trajectory(np.arange(float(n)), geo.xytheta_to_matrix(3 * np.cos(th), 3 * np.sin(th), th))


def test_rpe_without_any_pair_is_an_error(tmp_path, capsys):
    """--delta 1000 frames on 30 poses: no pair, so no statistic: exit 2 naming --delta (not 'rmse: nan')."""
    write_tum(tmp_path / "a.tum", _traj())
    for extra in (["--delta", "1000"], ["--delta", "500", "--delta-unit", "m"]):
        code, out, err = _slam(["eval", "rpe", tmp_path / "a.tum", tmp_path / "a.tum", *extra], capsys)
        _one_error(code, out, err, "--delta", "a.tum")


def test_loops_on_a_graph_without_loop_closures_is_an_error(tmp_path, capsys):
    """A pure odometry chain has no loop closure to score: exit 2 naming the graph (not 'precision: nan')."""
    t = _traj()
    g = PoseGraph(2)
    for k, T in enumerate(t.poses):
        g.add_node(k, T)
    for k in range(len(t) - 1):
        g.add_edge(k, k + 1, geo.relative(t.poses[k], t.poses[k + 1]), np.eye(3))
    write_g2o(g, tmp_path / "chain.g2o")
    code, out, err = _slam(["eval", "loops", tmp_path / "chain.g2o"], capsys)
    _one_error(code, out, err, tmp_path / "chain.g2o", "no loop")


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    sim = corridor_log(d / "c.mcap", 60, seed=3)
    return d / "c.mcap", sim


@pytest.mark.parametrize("kind", ["relations", "gt"])
def test_run_against_a_reference_that_matches_no_scan_is_an_error(tmp_path, sim_log, capsys, kind):
    """slam run --relations/--gt with stamps far from every scan: exit 2 with one line naming the file, and no
    output folder (as eval relations/ape would refuse it), instead of all-null metrics with exit 0."""
    log, sim = sim_log
    ref = tmp_path / f"far.{kind}"
    if kind == "relations":
        ref.write_text("".join(f"{1e6 + k} {1e6 + k + 1} 0.1 0 0 0 0 0\n" for k in range(5)))
    else:
        write_tum(ref, Trajectory(sim.stamps + 1e6, sim.ground_truth))
    out = tmp_path / "run"
    code, stdout, err = _slam(["run", log, "--out", out, "--quiet", "--map", "none", f"--{kind}", ref], capsys)
    _one_error(code, stdout, err, ref)
    assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_malformed_relations_file_is_refused_before_the_run(tmp_path, sim_log, capsys):
    """The --relations file is read before any scan is: a bad line is exit 2 naming it, and the run never
    starts (no 'log:' line)."""
    log, _ = sim_log
    ref = tmp_path / "bad.relations"
    ref.write_text("1 2 0 0 0 0 0\n")
    code, stdout, err = _slam(["run", log, "--out", tmp_path / "run", "--quiet", "--relations", ref], capsys)
    _one_error(code, stdout, err, f"{ref}:line 1")
    assert "log:" not in stdout
