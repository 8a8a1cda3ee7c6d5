"""`slam eval` command lines: error reporting, loop scoring and relations output."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core import geometry as geo
from core.trajectory import Trajectory, write_tum

SLAM = str(Path(sys.executable).parent / "slam")


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([SLAM, "eval", *map(str, args)], capture_output=True, text=True)


def test_malformed_trajectory_is_one_error_line_naming_file_and_line(tmp_path):
    """A bad TUM line makes `slam eval ape` exit 2 with one 'error: FILE:line N: ...' line on stderr."""
    (tmp_path / "bad.tum").write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    (tmp_path / "ok.tum").write_text("0 0 0 0 0 0 0 1\n")
    r = _run("ape", tmp_path / "bad.tum", tmp_path / "ok.tum")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "bad.tum:line 2" in lines[0]


def test_no_common_stamps_is_an_error(tmp_path):
    """Trajectories without any stamp within --max-diff give a one-line error, not a traceback."""
    write_tum(tmp_path / "a.tum", Trajectory(np.arange(5.0), np.tile(np.eye(4), (5, 1, 1))))
    write_tum(tmp_path / "b.tum", Trajectory(np.arange(5.0) + 100, np.tile(np.eye(4), (5, 1, 1))))
    r = _run("ape", tmp_path / "a.tum", tmp_path / "b.tum")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr


def test_relations_cli_reports_missing_and_json(tmp_path):
    """`slam eval relations` prints n_missing for relations whose stamps the trajectory lacks and writes --json."""
    poses = geo.xytheta_to_matrix(np.arange(10.0), np.zeros(10), np.zeros(10))
    write_tum(tmp_path / "t.tum", Trajectory(np.arange(10.0), poses))
    (tmp_path / "x.relations").write_text("0 1 1 0 0 0 0 0\n1 3 2 0 0 0 0 0\n5 50 1 0 0 0 0 0\n")
    r = _run("relations", tmp_path / "t.tum", tmp_path / "x.relations", "--json", tmp_path / "o.json")
    assert r.returncode == 0, r.stderr
    printed = dict(line.split(": ", 1) for line in r.stdout.splitlines() if line.count(": ") == 1)
    assert printed["n_missing"] == "1" and printed["n_used"] == "2" and float(printed["trans_mean"]) == 0.0
    assert "not recognised" in r.stdout
    assert json.loads((tmp_path / "o.json").read_text())["n_missing"] == 1


def test_relations_none_of_which_match_the_trajectory_are_an_error(tmp_path):
    """A trajectory from another log (no relation stamp in it) exits 2 with one line naming the trajectory,
    rather than printing a 'nan ± nan' table."""
    write_tum(tmp_path / "t.tum", Trajectory(np.arange(10.0), np.tile(np.eye(4), (10, 1, 1))))
    (tmp_path / "x.relations").write_text("100 101 1 0 0 0 0 0\n200 203 2 0 0 0 0 0\n")
    r = _run("relations", tmp_path / "t.tum", tmp_path / "x.relations")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ")
    assert "t.tum" in lines[0] and "x.relations" in lines[0] and "nan" not in r.stdout


def _two_laps(n: int):  # type: ignore[no-untyped-def]
    """Two laps of a 5 m circle in *n* poses, and the planar graph of its exact odometry (information 100)."""
    from slam.graph import PoseGraph

    th = np.linspace(0, 4 * np.pi, n, endpoint=False)
    gt = geo.xytheta_to_matrix(5 * np.cos(th), 5 * np.sin(th), th + np.pi / 2)
    g = PoseGraph(2)
    for k in range(n):
        g.add_node(k, gt[k])
    for k in range(n - 1):
        g.add_edge(k, k + 1, geo.relative(gt[k], gt[k + 1]), np.eye(3) * 100)
    return gt, g


def test_loops_cli_with_ground_truth(tmp_path):
    """`slam eval loops GRAPH --gt` prints the self-scored precision and the ground-truth precision/recall."""
    pytest.importorskip("slam.graph")
    from slam.graph import write_g2o

    n = 60
    gt, g = _two_laps(n)
    info = np.eye(3) * 100
    for k in range(0, 10):
        C = np.eye(4) if k < 8 else geo.xytheta_to_matrix(0.0, 0.5, 0.0)
        g.add_edge(k, k + 30, geo.relative(gt[k], gt[k + 30]) @ C, info)
    write_g2o(g, tmp_path / "g.g2o")
    write_tum(tmp_path / "gt.tum", Trajectory(np.arange(float(n)), gt))
    r = _run("loops", tmp_path / "g.g2o", "--gt", tmp_path / "gt.tum", "--revisit-radius", "0.3", "--min-separation", "10")
    assert r.returncode == 0, r.stderr
    p = dict(line.split(": ", 1) for line in r.stdout.splitlines())
    assert p["loops"] == "10" and float(p["precision"]) == pytest.approx(0.8)
    assert float(p["gt_precision"]) == pytest.approx(0.8) and p["gt_revisit_nodes"] == "30"
    assert float(p["gt_recall"]) == pytest.approx(8 / 30)
    assert p["gt_gross"] == "2"  # the two closures 0.5 m off lie beyond the 0.3 m revisit radius: another place


def test_g2o_estimate_with_stamp_file_equals_tum(tmp_path, rng):
    """A g2o-vertex estimate with --est-stamps ('id stamp') gives the same APE as the same poses in TUM."""
    n = 30
    P = geo.xytheta_to_matrix(np.cumsum(rng.uniform(0, 1, n)), rng.normal(0, 0.1, n), rng.normal(0, 0.1, n))
    st = 50.0 + 0.5 * np.arange(n)
    write_tum(tmp_path / "est.tum", Trajectory(st, P))
    write_tum(tmp_path / "ref.tum", Trajectory(st, P @ geo.xytheta_to_matrix(0.1, 0.0, 0.0)))
    (tmp_path / "est.g2o").write_text("".join(
        f"VERTEX_SE2 {k} {x!r} {y!r} {t!r}\n" for k, (x, y, t) in enumerate(geo.matrix_to_xytheta(P).tolist())))
    (tmp_path / "ids.txt").write_text("".join(f"{k} {float(s)!r}\n" for k, s in enumerate(st)))
    a = _run("ape", tmp_path / "est.tum", tmp_path / "ref.tum")
    b = _run("ape", tmp_path / "est.g2o", tmp_path / "ref.tum", "--est-stamps", tmp_path / "ids.txt")
    assert a.returncode == b.returncode == 0, b.stderr
    pa = dict(line.split(": ", 1) for line in a.stdout.splitlines())
    pb = dict(line.split(": ", 1) for line in b.stdout.splitlines())
    assert float(pa["rmse"]) == pytest.approx(0.1) and float(pb["rmse"]) == pytest.approx(float(pa["rmse"]), rel=1e-12)
    assert pb["pairs"] == str(n)


def test_nees_with_a_rotation_scale_term_is_never_larger_and_the_heading_fit_does_not_depend_on_it(tmp_path):
    """`slam eval nees` on a real run (the bundled Intel log's first 5000 scans): adding the rotation's scale
    term (`--turn-drift`) adds a positive semi-definite matrix to every chain's covariance, so no bin's mean
    NEES may grow and no predicted σ may shrink; the fit of the heading error on path and turn reads the
    errors alone, so both runs report the same one."""
    from tests.conftest import DATA

    run = tmp_path / "run"
    r = subprocess.run([SLAM, "run", str(DATA / "intel.clf.bz2"), "--out", str(run), "--max-scans", "5000",
                        "--map", "none", "--quiet"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    out = {}
    for sigma in (0.0, 0.01):
        r = _run("nees", run, DATA / "intel.relations", "--turn-drift", sigma, "--json", tmp_path / f"{sigma}.json")
        assert r.returncode == 0, r.stderr
        out[sigma] = json.loads((tmp_path / f"{sigma}.json").read_text())
    plain, term = out[0.0], out[0.01]
    assert plain["relations"] == term["relations"] > 0 and term["turn_drift_rad_per_rad"] == 0.01
    for a, b in zip(plain["bins"], term["bins"], strict=True):
        assert b["nees_mean"] <= a["nees_mean"] + 1e-12 and b["sigma_rotation_deg"] >= a["sigma_rotation_deg"] - 1e-12
    assert any(b["nees_mean"] < a["nees_mean"] for a, b in zip(plain["bins"], term["bins"]))
    assert plain["heading_fit"] is not None and plain["heading_fit"] == term["heading_fit"]
    # Without relations the run's own closures are the reference: every loop edge of graph.g2o is one chain.
    from slam.graph.g2o import read_g2o

    r = _run("nees", run, "--json", tmp_path / "closures.json")
    assert r.returncode == 0, r.stderr
    own = json.loads((tmp_path / "closures.json").read_text())
    loops = sum(e.kind == "loop" for e in read_g2o(run / "graph.g2o").edges())
    assert own["reference"] == "closures" and own["closures"] == loops == sum(b["n"] for b in own["bins"]) > 0
    # By default the chains carry the run's own calibration (summary.json), and its table is the summary's.
    summary = json.loads((run / "summary.json").read_text())
    model = summary["chain_model"]
    assert own["model"] == "run" and (own["walk"], own["jitter"]) == (model["walk"], model["jitter"])
    assert [b["nees_mean"] for b in own["bins"]] == pytest.approx([b["nees_mean"] for b in model["closure_nees"]], rel=1e-9)
    # The walk fitted to them makes the chains of 101 keyframes or more average NEES/dof 1; without --jitter the
    # jitter keeps each step's stated covariance, which is the run's own calibration.
    for extra, name in ((["--jitter", 1], "fixed"), ([], "split")):
        r = _run("nees", run, *extra, "--fit-walk", "--json", tmp_path / f"{name}.json")
        assert r.returncode == 0, r.stderr
        fitted = json.loads((tmp_path / f"{name}.json").read_text())
        assert fitted["walk_fitted"] and 1e-3 < fitted["walk"] < 1e2
        long = [b for b in fitted["bins"] if b["lo"] >= 101]
        assert sum(b["n"] * b["nees_mean"] for b in long) / sum(b["n"] for b in long) == pytest.approx(1.0, rel=1e-3)
    assert fitted["walk"] == pytest.approx(model["walk"], rel=1e-9) and fitted["jitter"] == pytest.approx((1 - fitted["walk"]) / 2)
    # The edges as stated: the summary's closure_nees, the loop closer's heading rate included.
    r = _run("nees", run, "--walk", 1, "--jitter", 0, "--heading-drift", summary["config"]["loops"]["heading_drift_deg_per_m"],
             "--json", tmp_path / "stated.json")
    assert r.returncode == 0, r.stderr
    stated = json.loads((tmp_path / "stated.json").read_text())["bins"]
    assert [b["nees_mean"] for b in stated] == pytest.approx([b["nees_mean"] for b in summary["closure_nees"]], rel=1e-9)
    # benchmarks/chain_model.py reads the same run as the CLI does: the run's walk, and the relations' table under it.
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_chain_model", Path(__file__).resolve().parent.parent / "benchmarks" / "chain_model.py")
    bench_module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench_module)
    measure = bench_module.measure
    r = _run("nees", run, DATA / "intel.relations", "--json", tmp_path / "calibrated.json")
    assert r.returncode == 0, r.stderr
    cli = json.loads((tmp_path / "calibrated.json").read_text())
    bench = measure(run, DATA / "intel.relations", 10)
    assert bench["walk_closures"] == pytest.approx(model["walk"], abs=1e-4) and bench["relations"] == cli["relations"]
    assert [b["nees_mean"] for b in bench["calibrated"]["table"]] == pytest.approx([b["nees_mean"] for b in cli["bins"]], abs=1e-3)


def test_nees_without_relations_of_a_run_without_closures_is_one_error_line(tmp_path):
    (tmp_path / "graph.g2o").write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    r = _run("nees", tmp_path)
    assert r.returncode == 2 and "no loop closure" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_nees_of_a_graph_without_a_summary_takes_the_edges_as_stated_and_a_broken_summary_is_one_error_line(tmp_path):
    """A run folder without summary.json (a graph from elsewhere, or a run older than the calibration) is tested
    with its edges as stated; a summary.json that is not one is named in one error line, never skipped silently."""
    from slam.graph import write_g2o

    gt, g = _two_laps(40)
    for k in range(10):
        g.add_edge(k, k + 20, geo.relative(gt[k], gt[k + 20]), np.eye(3) * 100, "loop")
    write_g2o(g, tmp_path / "graph.g2o")
    r = _run("nees", tmp_path, "--json", tmp_path / "n.json")
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "n.json").read_text())
    assert out["model"] == "edges" and (out["walk"], out["jitter"]) == (1.0, 0.0) and out["closures"] == 10
    (tmp_path / "summary.json").write_text("{not json")
    r = _run("nees", tmp_path)
    assert r.returncode == 2 and "summary.json" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_nees_of_a_folder_that_is_no_run_is_one_error_line(tmp_path):
    r = _run("nees", tmp_path, tmp_path / "none.relations")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
