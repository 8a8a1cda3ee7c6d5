"""APE / RPE equal evo's (run as a test-only reference, never copied) to 1e-6 on generated trajectories."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from core import geometry as geo
from core.trajectory import Trajectory, read_tum, write_tum
from evaluation.ape_rpe import evaluate_ape, evaluate_rpe, rpe_pairs, statistics
from evaluation.trajectory import associate, align_trajectory, umeyama

evo_file = pytest.importorskip("evo.tools.file_interface")
from evo.core import metrics as evo_metrics  # noqa: E402
from evo.core import sync as evo_sync  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402

TOL = 1e-6


def _make_pair(rng: np.random.Generator, n: int = 300, planar: bool = False) -> tuple[Trajectory, Trajectory]:
    """A smooth reference and an estimate = noisy copy in another frame, scale 1.3, jittered stamps."""
    stamps = 1000.0 + 0.1 * np.arange(n)
    if planar:
        xi = np.column_stack([rng.normal(0.3, 0.05, n), rng.normal(0, 0.02, n), rng.normal(0.02, 0.05, n)])
        steps = geo.se2_exp(xi)
    else:
        xi = np.column_stack([rng.normal(0.3, 0.05, n), rng.normal(0, 0.03, (n, 2)), rng.normal(0, 0.04, (n, 3))])
        steps = geo.se3_exp(xi)
    ref = np.empty((n, 4, 4))
    acc = np.eye(4)
    for k in range(n):  # building a test trajectory: a short sequential composition
        acc = acc @ steps[k]
        ref[k] = acc
    noise = geo.se2_exp(rng.normal(0, [0.05, 0.05, 0.01], (n, 3))) if planar else geo.se3_exp(rng.normal(0, 0.03, (n, 6)))
    est = ref @ noise
    G = geo.xytheta_to_matrix(3.0, -2.0, 0.7) if planar else geo.se3_exp(np.array([3.0, -2.0, 1.0, 0.2, -0.1, 0.7]))
    est = G @ est
    est[:, :3, 3] *= 1.3
    est_stamps = stamps + rng.uniform(-0.004, 0.004, n)
    # drop a few reference poses so that association matters
    keep = np.ones(n, bool)
    keep[rng.choice(n, 20, replace=False)] = False
    return Trajectory(est_stamps, est, "est"), Trajectory(stamps[keep], ref[keep], "ref")


def _evo_pair(tmp_path: Path, est: Trajectory, ref: Trajectory):
    write_tum(tmp_path / "est.tum", est)
    write_tum(tmp_path / "ref.tum", ref)
    e = evo_file.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    r = evo_file.read_tum_trajectory_file(str(tmp_path / "ref.tum"))
    r, e = evo_sync.associate_trajectories(r, e, max_diff=0.01)
    return e, r


def _assert_stats(ours: dict, theirs: dict) -> None:
    for k in ("rmse", "mean", "median", "std", "min", "max", "sse"):
        assert ours[k] == pytest.approx(theirs[k], abs=TOL, rel=TOL), k


@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("align", ["none", "se3", "sim3"])
@pytest.mark.parametrize("relation", ["trans", "rot_deg"])
def test_ape_equals_evo(tmp_path, rng, planar, align, relation):
    """APE statistics (rmse, mean, median, std, min, max, sse) equal evo_ape's to 1e-6 for every alignment mode."""
    est, ref = _make_pair(rng, planar=planar)
    e, r = _evo_pair(tmp_path, est, ref)
    rel = {"trans": evo_metrics.PoseRelation.translation_part, "rot_deg": evo_metrics.PoseRelation.rotation_angle_deg}[relation]
    theirs = evo_ape(copy.deepcopy(r), copy.deepcopy(e), rel, align=align != "none", correct_scale=align == "sim3")
    ours = evaluate_ape(read_tum(tmp_path / "est.tum"), read_tum(tmp_path / "ref.tum"), align=align, relation=relation)
    assert ours.n_matched == len(r.timestamps)
    _assert_stats(ours.stats, theirs.stats)
    np.testing.assert_allclose(ours.errors, theirs.np_arrays["error_array"], atol=TOL)


@pytest.mark.parametrize(
    "delta,unit,all_pairs,align",
    [(1, "frames", False, "none"), (7, "frames", False, "se3"), (5, "frames", True, "none"),
     (2.0, "m", False, "none"), (2.0, "m", False, "sim3"), (3.0, "m", True, "none")],
)
@pytest.mark.parametrize("relation", ["trans", "rot_deg"])
def test_rpe_equals_evo(tmp_path, rng, delta, unit, all_pairs, align, relation):
    """RPE by frame delta and by travelled distance equals evo_rpe's statistics and per-pair errors to 1e-6."""
    est, ref = _make_pair(rng)
    e, r = _evo_pair(tmp_path, est, ref)
    rel = {"trans": evo_metrics.PoseRelation.translation_part, "rot_deg": evo_metrics.PoseRelation.rotation_angle_deg}[relation]
    evo_unit = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
    theirs = evo_rpe(copy.deepcopy(r), copy.deepcopy(e), rel, delta=delta, delta_unit=evo_unit, all_pairs=all_pairs,
                     align=align != "none", correct_scale=align == "sim3")
    ours = evaluate_rpe(read_tum(tmp_path / "est.tum"), read_tum(tmp_path / "ref.tum"), delta=delta, delta_unit=unit,
                        relation=relation, align=align, all_pairs=all_pairs)
    assert len(ours.errors) == len(theirs.np_arrays["error_array"]) > 5
    _assert_stats(ours.stats, theirs.stats)
    np.testing.assert_allclose(ours.errors, theirs.np_arrays["error_array"], atol=TOL)


def test_cli_equals_evo_cli(tmp_path, rng):
    """`slam eval ape/rpe` print the same rmse/mean/median/max as the evo_ape/evo_rpe command lines (defaults)."""
    est, ref = _make_pair(rng, n=120)
    write_tum(tmp_path / "est.tum", est)
    write_tum(tmp_path / "ref.tum", ref)
    bindir = Path(sys.executable).parent
    for tool, sub in (("evo_ape", "ape"), ("evo_rpe", "rpe")):
        z = tmp_path / f"{tool}.zip"
        subprocess.run([str(bindir / tool), "tum", str(tmp_path / "ref.tum"), str(tmp_path / "est.tum"),
                        "--save_results", str(z), "--no_warnings"], check=True, capture_output=True)
        with zipfile.ZipFile(z) as zf:
            theirs = json.loads(zf.read("stats.json"))
        out = subprocess.run([str(bindir / "slam"), "eval", sub, str(tmp_path / "est.tum"), str(tmp_path / "ref.tum")],
                             check=True, capture_output=True, text=True).stdout
        printed = dict(line.split(": ", 1) for line in out.splitlines() if ": " in line)
        for k in ("rmse", "mean", "median", "max"):
            assert float(printed[k]) == pytest.approx(theirs[k], abs=TOL, rel=TOL), (tool, k)


def test_umeyama_recovers_known_similarity(rng):
    """Umeyama returns exactly the similarity that generated noise-free points (R, t, s recovered)."""
    X = rng.normal(size=(50, 3))
    R = geo.so3_exp(np.array([0.3, -0.5, 1.1]))
    t = np.array([1.0, 2.0, -3.0])
    Y = 2.5 * X @ R.T + t
    R_, t_, s_ = umeyama(X, Y, with_scale=True)
    np.testing.assert_allclose(R_, R, atol=1e-12)
    np.testing.assert_allclose(t_, t, atol=1e-12)
    assert s_ == pytest.approx(2.5, abs=1e-12)


def test_planar_alignment_stays_about_z(rng):
    """With z noise, the 2D-aware alignment of planar trajectories keeps the rotation about z."""
    est, ref = _make_pair(rng, planar=True)
    e, r = associate(est, ref)
    _, al = align_trajectory(e, r, "se3")
    assert al.planar
    np.testing.assert_allclose(al.transform[2], [0, 0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(al.transform[:3, 2], [0, 0, 1], atol=1e-15)


def test_rpe_pairs_frames_are_consecutive_non_overlapping():
    """Frame-delta pairs are (0,Δ),(Δ,2Δ),…; all-pairs gives every (i, i+Δ)."""
    t = Trajectory(np.arange(10.0), np.tile(np.eye(4), (10, 1, 1)))
    assert rpe_pairs(t, 3).tolist() == [[0, 3], [3, 6], [6, 9]]
    assert rpe_pairs(t, 3, all_pairs=True).tolist() == [[i, i + 3] for i in range(7)]


def test_statistics_closed_form():
    """rmse, mean, median, std, sse of [3, 4] are sqrt(12.5), 3.5, 3.5, 0.5, 25."""
    s = statistics(np.array([3.0, 4.0]))
    assert s["rmse"] == pytest.approx(np.sqrt(12.5)) and s["mean"] == 3.5 and s["median"] == 3.5
    assert s["std"] == 0.5 and s["sse"] == 25.0 and s["min"] == 3.0 and s["max"] == 4.0


def test_metric_pairs_equal_evo_with_stops(rng):
    """Travelled-distance pairs (consecutive and all-pairs) equal evo's pair filter on paths with standstills,
    where ties between equal path distances must resolve to the earliest pose."""
    from evo.core.filters import filter_pairs_by_path

    for _ in range(20):
        n = int(rng.integers(2, 200))
        steps = rng.uniform(0, 1, (n, 3)) * (rng.uniform(0, 1, (n, 1)) > 0.3)
        P = np.tile(np.eye(4), (n, 1, 1))
        P[:, :3, 3] = np.cumsum(steps, 0)
        t = Trajectory(np.arange(float(n)), P)
        for delta in (0.5, 2.0, 7.0):
            for all_pairs in (False, True):
                theirs = [list(p) for p in filter_pairs_by_path(list(P), delta, 0.1 * delta, all_pairs=all_pairs)]
                assert rpe_pairs(t, delta, "m", all_pairs=all_pairs).tolist() == theirs


def test_aligned_ape_and_rpe_are_invariant_to_a_rigid_motion_of_the_estimate(rng):
    """Moving the estimate by any rigid transform changes neither the SE(3)-aligned APE nor the RPE
    (Umeyama recovers the motion; relative poses do not see it)."""
    est, ref = _make_pair(rng, n=150)
    for _ in range(5):
        G = geo.se3_exp(rng.normal(0, [10, 10, 10, 2, 2, 2]))
        moved = Trajectory(est.stamps, G @ est.poses)
        a0, a1 = evaluate_ape(est, ref, align="se3"), evaluate_ape(moved, ref, align="se3")
        np.testing.assert_allclose(a1.errors, a0.errors, atol=1e-9)
        r0, r1 = evaluate_rpe(est, ref, delta=3), evaluate_rpe(moved, ref, delta=3)
        np.testing.assert_allclose(r1.errors, r0.errors, atol=1e-9)


def test_sim3_alignment_removes_a_pure_similarity():
    """An estimate that is exactly s·R·ref + t has zero APE after Sim(3) alignment but not after SE(3)."""
    n = 50
    ref = Trajectory(np.arange(n, dtype=float), geo.se3_exp(np.column_stack([np.linspace(0, 20, n), np.sin(np.arange(n)),
                                                                             np.zeros(n), np.zeros((n, 2)), np.linspace(0, 3, n)])))
    G = geo.xytheta_to_matrix(2.0, -1.0, 0.4)
    P = G @ ref.poses
    P[:, :3, 3] *= 0.5
    est = Trajectory(ref.stamps, P)
    assert evaluate_ape(est, ref, align="sim3").stats["max"] < 1e-9
    assert evaluate_ape(est, ref, align="se3").stats["max"] > 1.0
