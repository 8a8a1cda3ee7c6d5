"""Solver cross-check: objectives are gauge invariant, pose differences have closed-form values."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core import geometry as geo
from core import pose_formats

pytest.importorskip("slam.graph")
from slam.backends.crosscheck import crosscheck  # noqa: E402
from slam.graph import PoseGraph, write_g2o  # noqa: E402


def _graph(rng, n=60) -> tuple[PoseGraph, np.ndarray]:
    th = np.cumsum(rng.normal(0.1, 0.05, n))
    xy = np.cumsum(np.column_stack([np.cos(th), np.sin(th)]) * 0.5, axis=0)
    gt = geo.xytheta_to_matrix(xy[:, 0], xy[:, 1], th)
    g = PoseGraph(2)
    for k in range(n):
        g.add_node(k, gt[k])
    info = np.array([[50.0, 5.0, 0.0], [5.0, 80.0, 0.0], [0.0, 0.0, 300.0]])
    noise = geo.se2_exp(rng.normal(0, [0.03, 0.03, 0.01], (n, 3)))
    for k in range(n - 1):
        g.add_edge(k, k + 1, geo.relative(gt[k], gt[k + 1]) @ noise[k], info)
    for k in range(0, n - 20, 7):
        g.add_edge(k, k + 20, geo.relative(gt[k], gt[k + 20]) @ noise[k + 1], info)
    return g, gt


def test_gauge_transform_changes_raw_but_not_objectives_or_aligned(rng):
    """B = G·A (G a pure translation by (3, 4)): objectives equal, raw position diff = 5 m everywhere,
    rotation diff 0, aligned diffs 0."""
    g, A = _graph(rng)
    B = geo.xytheta_to_matrix(3.0, 4.0, 0.0) @ A
    out = crosscheck(g, A, B, ("a", "b"))
    assert out["a"]["sesync_objective"] == pytest.approx(out["b"]["sesync_objective"], rel=1e-9)
    assert out["objective_rel_diff"] < 1e-9
    assert out["raw"]["max_position_diff_m"] == pytest.approx(5.0) and out["raw"]["rms_position_diff_m"] == pytest.approx(5.0)
    assert out["raw"]["max_rotation_diff_deg"] < 1e-6
    assert out["aligned"]["max_position_diff_m"] < 1e-9
    json.dumps(out)  # JSON-ready


def test_sesync_objective_closed_form_one_edge():
    """One edge, nodes at the identity, measurement (1, 0, θ): f = τ·1 + κ·4(1 − cos θ) with the SE-Sync
    weights τ = 2/tr(I_tt⁻¹), κ = I_θθ (PUBLISHED_RESULTS.md §2)."""
    g = PoseGraph(2)
    g.add_node(0, np.eye(4))
    g.add_node(1, np.eye(4))
    info = np.diag([4.0, 1.0, 9.0])
    g.add_edge(0, 1, geo.xytheta_to_matrix(1.0, 0.0, 0.3), info)
    out = crosscheck(g, g.poses, g.poses)
    tau = 2.0 / (0.25 + 1.0)
    assert out["a"]["sesync_objective"] == pytest.approx(tau + 9.0 * 4 * (1 - np.cos(0.3)), rel=1e-12)


def test_gtsam_chi2_matches_direct_gtsam(rng):
    """The reported GTSAM error equals NonlinearFactorGraph.error of Pose2 between-factors built here."""
    pytest.importorskip("slam.backends.gtsam_backend")
    import gtsam

    g, A = _graph(rng, 20)
    A = A @ geo.se2_exp(rng.normal(0, 0.05, (20, 3)))
    out = crosscheck(g, A, A)
    fg = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    for k, T in enumerate(A):
        vals.insert(k, pose_formats.to_gtsam_pose2(T))
    for e in g.edges():
        fg.add(gtsam.BetweenFactorPose2(e.i, e.j, pose_formats.to_gtsam_pose2(e.measurement), gtsam.noiseModel.Gaussian.Information(e.information)))
    assert out["a"]["gtsam_error"] == pytest.approx(fg.error(vals), rel=1e-9)
    assert out["a"]["chi2"] == pytest.approx(2 * fg.error(vals), rel=1e-9)


def test_cli_writes_json(tmp_path, rng):
    """`slam eval crosscheck GRAPH A B --json` writes the same objectives it prints."""
    from core.trajectory import Trajectory, write_tum

    g, A = _graph(rng, 30)
    write_g2o(g, tmp_path / "g.g2o")
    write_tum(tmp_path / "b.tum", Trajectory(np.arange(30.0), geo.xytheta_to_matrix(1.0, 0.0, 0.2) @ A))
    r = subprocess.run([str(Path(sys.executable).parent / "slam"), "eval", "crosscheck", str(tmp_path / "g.g2o"),
                        str(tmp_path / "g.g2o"), str(tmp_path / "b.tum"), "--json", str(tmp_path / "x.json")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    data = json.loads((tmp_path / "x.json").read_text())
    assert data["aligned"]["max_position_diff_m"] < 1e-9
    assert json.loads(r.stdout)["a"]["sesync_objective"] == pytest.approx(data["a"]["sesync_objective"])
