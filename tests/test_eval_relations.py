"""Kümmerle et al. 2009 relation metric: constructed cases with known answers, published numbers, Intel odometry."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core import geometry as geo
from core import pose_formats
from core.trajectory import Trajectory, write_tum
from evaluation.published import DATASET_NAMES, METRIC_KEYS, PUBLISHED, recognise_dataset
from evaluation.relations import Relations, evaluate_relations, read_relations
from tests.conftest import DATA, shared_path


def _gt(rng, n=40) -> Trajectory:
    steps = geo.se2_exp(np.column_stack([rng.uniform(0.2, 0.5, n), rng.normal(0, 0.05, n), rng.normal(0, 0.3, n)]))
    poses = np.empty((n, 4, 4))
    acc = np.eye(4)
    for k in range(n):
        acc = acc @ steps[k]
        poses[k] = acc
    return Trajectory(100.0 + 0.37 * np.arange(n), poses)


def _relations_from(gt: Trajectory, i1, i2) -> Relations:
    i1, i2 = np.asarray(i1), np.asarray(i2)
    return Relations(gt.stamps[i1], gt.stamps[i2], geo.relative(gt.poses[i1], gt.poses[i2]))


def _write_relations(path: Path, rel: Relations) -> None:
    rpy = pose_formats.rotation_to_rpy(rel.deltas[:, :3, :3])
    with open(path, "w") as fh:
        for a, b, D, r in zip(rel.t1, rel.t2, rel.deltas, rpy):
            fh.write(" ".join(repr(float(v)) for v in (a, b, *D[:3, 3], *r)) + "\n")


def test_exact_trajectory_has_zero_error(rng, tmp_path):
    """The ground truth itself (through a written-and-read relations file) scores zero on every statistic."""
    gt = _gt(rng)
    i1 = rng.integers(0, 40, 60)
    i2 = rng.integers(0, 40, 60)
    _write_relations(tmp_path / "r.relations", _relations_from(gt, i1, i2))
    res = evaluate_relations(gt, read_relations(tmp_path / "r.relations"))
    assert res.n_used == 60 and res.n_missing == 0
    assert res.trans_mean < 1e-12 and res.rot_mean_deg < 1e-9


def test_invariant_to_global_transform(rng):
    """Relations are relative: a trajectory moved by any rigid transform scores exactly the same (zero)."""
    gt = _gt(rng)
    rel = _relations_from(gt, np.arange(39), np.arange(1, 40))
    moved = Trajectory(gt.stamps, geo.xytheta_to_matrix(5.0, -3.0, 2.0) @ gt.poses)
    res = evaluate_relations(moved, rel)
    assert res.trans_mean < 1e-12 and res.rot_mean_deg < 1e-9


def test_one_perturbed_pose_gives_closed_form_errors(rng):
    """Perturbing x_k → x_k·D: relation (k−1→k) has e = D; relation (k→k+1) has e = A⁻¹D⁻¹A (A = δ*), so
    |rot(e)| = angle(D) for both and |trans(e)| = ‖t_D‖ resp. ‖R_Dᵀ(t_A − t_D) − t_A‖; others are zero."""
    gt = _gt(rng)
    k = 17
    rel = _relations_from(gt, np.arange(39), np.arange(1, 40))
    D = geo.xytheta_to_matrix(0.3, -0.4, np.radians(7.0))
    est = gt.poses.copy()
    est[k] = est[k] @ D
    res = evaluate_relations(Trajectory(gt.stamps, est), rel)
    A = rel.deltas[k]
    t_second = np.linalg.norm(D[:3, :3].T @ (A[:3, 3] - D[:3, 3]) - A[:3, 3])
    expected_trans = np.zeros(39)
    expected_trans[k - 1] = 0.5
    expected_trans[k] = t_second
    expected_rot = np.zeros(39)
    expected_rot[[k - 1, k]] = 7.0
    np.testing.assert_allclose(res.trans_errors, expected_trans, atol=1e-12)
    np.testing.assert_allclose(res.rot_errors_deg, expected_rot, atol=1e-9)
    assert res.trans_mean == pytest.approx(expected_trans.mean(), abs=1e-12)
    assert res.trans_std == pytest.approx(expected_trans.std(), abs=1e-12)
    assert res.trans_sq_mean == pytest.approx((expected_trans**2).mean(), abs=1e-12)
    assert res.rot_mean_deg == pytest.approx(14.0 / 39, abs=1e-9)
    assert res.rot_sq_mean == pytest.approx(2 * 49.0 / 39, abs=1e-8)
    assert res.rot_sq_std == pytest.approx((expected_rot**2).std(), abs=1e-8)


def test_missing_stamps_are_counted_not_dropped(rng):
    """Relations whose stamps the trajectory lacks are counted in n_missing; stamps within 1e-3 s still match."""
    gt = _gt(rng)
    rel = _relations_from(gt, np.arange(39), np.arange(1, 40))
    jittered = Trajectory(gt.stamps + 5e-4, gt.poses)
    assert evaluate_relations(jittered, rel).n_missing == 0
    res = evaluate_relations(gt.subset(np.arange(30)), rel)  # stamps 30..39 absent
    assert res.n_missing == 39 - 29 and res.n_used == 29
    assert evaluate_relations(Trajectory(gt.stamps + 2e-3, gt.poses), rel).n_used == 0


def test_published_table_matches_published_results_md():
    """Every number in evaluation.published equals Hess et al. 2016 Table II as transcribed in PUBLISHED_RESULTS.md."""
    text = shared_path("PUBLISHED_RESULTS.md").read_text()
    for key, name in DATASET_NAMES.items():
        for mkey, (label, _, _) in METRIC_KEYS.items():
            m = re.search(rf"^\| {re.escape(name)} \| {re.escape(label)}[^|]*\| ([\d.]+) ± ([\d.]+) \| ([\d.]+) ± ([\d.]+) \|", text, re.M)
            assert m, (name, label)
            c, g = PUBLISHED[key]["cartographer"][mkey], PUBLISHED[key]["graph_mapping"][mkey]
            assert (c[0], c[1], g[0], g[1]) == tuple(float(x) for x in m.groups()), (name, label)


def test_dataset_recognised_from_file_name():
    """Benchmark file names map to their dataset keys; unknown names give None."""
    assert recognise_dataset("x/intel.relations") == "intel"
    assert recognise_dataset("fr-clinic_robotlaser.clf.bz2") == "fr-clinic"
    assert recognise_dataset("mit-csail.relations") == "mit-csail"
    assert recognise_dataset("traj.tum") is None


def _intel_paths() -> tuple[Path, Path]:
    log = DATA / "intel.clf.bz2"
    rel = DATA / "intel.relations"
    if not (log.exists() and rel.exists()):
        log = shared_path("slam2d_kummerle_benchmark", "intel.clf.bz2")
        rel = shared_path("slam2d_kummerle_benchmark", "intel.relations")
    return log, rel


def test_intel_raw_odometry_is_far_worse_than_published(tmp_path):
    """Raw wheel odometry of the Intel log matches every relation stamp and is far (>3×) worse than both
    published SLAM results (Cartographer 0.0229 m, Graph Mapping 0.031 m mean translational error)."""
    pytest.importorskip("slam.logs.carmen")
    from slam.logs import open_log

    log, rel_path = _intel_paths()
    stamps, poses = [], []
    for f in open_log(log).frames():
        if f.odom is not None:
            stamps.append(f.stamp)
            poses.append(f.odom)
    traj = Trajectory(np.array(stamps), np.array(poses), "intel-odometry")
    rel = read_relations(rel_path)
    res = evaluate_relations(traj, rel)
    assert res.n_missing == 0 and res.n_used == len(rel) == 2984
    pub = PUBLISHED["intel"]
    assert res.trans_mean > 3 * max(pub["cartographer"]["trans"][0], pub["graph_mapping"]["trans"][0])
    assert res.rot_mean_deg > 3 * max(pub["cartographer"]["rot"][0], pub["graph_mapping"]["rot"][0])
    # the same through the CLI, which prints the published numbers side by side
    write_tum(tmp_path / "odom.tum", traj)
    out = subprocess.run([str(Path(sys.executable).parent / "slam"), "eval", "relations", str(tmp_path / "odom.tum"), str(rel_path)],
                         check=True, capture_output=True, text=True).stdout
    printed = dict(line.split(": ", 1) for line in out.splitlines() if line.count(": ") == 1)
    assert float(printed["trans_mean"]) == pytest.approx(res.trans_mean, rel=1e-9)
    assert float(printed["rot_mean_deg"]) == pytest.approx(res.rot_mean_deg, rel=1e-9)
    assert "Cartographer" in out and "0.0229 ± 0.0239" in out
