"""The run's self-check (no ground truth) and the NEES of the front end's chain covariance (ground truth)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from core import geometry as G
from evaluation.chain_model import Chain, calibrate, fit_walk
from evaluation.nees import (BIN_EDGES, bin_by_length, chain_nees, chain_sample, closure_nees, closure_sample, fuse_steps,
                             heading_by_path, heading_fit)
from slam.loops.types import LoopClosure
from slam.pipeline.self_check import SelfCheckConfig, _pair_violation, misplaced, self_check

from tests.loop_scenes import BOXES_FIRST, BOXES_SECOND, keyframes, room, room_with_a_wall_across, room_with_boxes


def _two_passes():
    """Two passes along the room's length, the second 12 keyframes after the first ends (different passes)."""
    first = [(x, 3.0, 0.0) for x in np.linspace(1.5, 10.5, 19)]
    away = [(10.5, 3.0 + 0.3 * k, np.pi / 2) for k in range(1, 13)]
    second = [(x, 3.2, np.pi) for x in np.linspace(10.5, 1.5, 19)]
    kfs = keyframes(room(), first + away + second, seed=7)
    return kfs, np.array([kf.odom_pose for kf in kfs])


def test_the_true_map_is_consistent_and_a_pass_moved_one_metre_is_suspect_where_it_was_moved():
    kfs, poses = _two_passes()
    cfg = SelfCheckConfig(exclude_recent_keyframes=5)
    good = self_check(kfs, poses, [], True, cfg)
    assert good.verdict == "consistent" and good.keyframes_checked > 20 and good.keyframes_contradicting == 0
    bad_poses = poses.copy()
    bad_poses[31:] = G.xytheta_to_matrix(0.0, 1.0, 0.0) @ poses[31:]  # the second pass 1 m across the room
    bad = self_check(kfs, bad_poses, [], True, cfg)
    assert bad.verdict == "suspect" and bad.keyframes_contradicting > 0.1 * bad.keyframes_checked
    flagged = {k for w in bad.where for k in range(w["first_keyframe"], w["last_keyframe"] + 1)}
    assert flagged & set(range(31, len(kfs)))


def test_a_wall_put_across_the_room_in_one_pass_is_not_a_wrong_map():
    """The second pass sees a wall across the room that the first did not (a door closed): its points lie in
    the first pass's free space, but not the other way round (the first pass's far walls are behind it).
    Only a misplaced scan contradicts both ways; the verdict stays consistent."""
    first = [(x, 3.0, 0.0) for x in np.linspace(1.5, 10.5, 19)]
    away = [(10.5, 3.0 + 0.3 * k, np.pi / 2) for k in range(1, 13)]
    second = [(x, 3.2, np.pi) for x in np.linspace(10.5, 6.5, 9)]  # stays east of the new wall at x = 6
    kfs = keyframes(room(), first + away, seed=7) + keyframes(room_with_a_wall_across(6.0), second, seed=8, first_id=31)
    poses = np.array([kf.odom_pose for kf in kfs])
    sc = self_check(kfs, poses, [], True, SelfCheckConfig(exclude_recent_keyframes=5))
    assert sc.keyframes_checked > 5 and sc.verdict == "consistent"


def test_boxes_moved_between_passes_are_a_changed_world_not_a_wrong_map():
    """Three boxes stand in the room during the first pass and three others during the second (cars parked
    for a while): their points lie in the other pass's free space both ways, as a misplaced scan's would,
    but no placement of the scans removes that, so the map is not blamed. The same second pass moved 1 m
    across the room is explained by a placement: suspect."""
    first = [(x, 3.0, 0.0) for x in np.linspace(1.5, 10.5, 19)]
    away = [(10.5, 3.0 + 0.3 * k, np.pi / 2) for k in range(1, 13)]
    second = [(x, 3.2, np.pi) for x in np.linspace(10.5, 1.5, 19)]
    kfs = (keyframes(room_with_boxes(BOXES_FIRST), first + away, seed=7)
           + keyframes(room_with_boxes(BOXES_SECOND), second, seed=8, first_id=31))
    poses = np.array([kf.odom_pose for kf in kfs])
    cfg = SelfCheckConfig(exclude_recent_keyframes=5)
    sc = self_check(kfs, poses, [], True, cfg)
    assert sc.keyframes_checked > 20 and sc.verdict == "consistent" and sc.keyframes_contradicting == 0
    assert sc.keyframes_changed > 0.1 * sc.keyframes_checked  # the boxes contradict both ways: seen, not blamed
    moved = poses.copy()
    moved[31:] = G.xytheta_to_matrix(0.0, 1.0, 0.0) @ poses[31:]
    bad = self_check(kfs, moved, [], True, cfg)
    assert bad.verdict == "suspect" and bad.keyframes_contradicting > 0.1 * bad.keyframes_checked
    # Past its budget of re-alignments the check counts every contradiction against the map, as before the rule.
    capped = self_check(kfs, poses, [], True, replace(cfg, max_realignments=0))
    assert capped.verdict == "suspect" and capped.keyframes_changed == 0


def test_a_contradiction_is_the_maps_when_a_placement_removes_it():
    """:func:`misplaced` on one pair: the second scan shifted 1 m (or turned 20°) from where it was taken is
    explained by the placement the search finds; the same scan at its true pose, taken while other boxes stood
    in the room, contradicts as much, and no placement explains that."""
    [a] = keyframes(room_with_boxes(BOXES_FIRST), [(3.0, 3.0, 0.5)], seed=1)
    [b] = keyframes(room_with_boxes(BOXES_FIRST), [(3.5, 3.0, 0.2)], seed=2, first_id=40)
    [c] = keyframes(room_with_boxes(BOXES_SECOND), [(3.5, 3.0, 0.2)], seed=3, first_id=40)
    cfg = SelfCheckConfig()
    true = G.relative(a.odom_pose, b.odom_pose)
    for error in (G.xytheta_to_matrix(1.0, 0.0, 0.0), G.xytheta_to_matrix(0.0, 0.0, np.radians(20.0))):
        v = _pair_violation(a, b, true @ error, cfg)
        assert v > cfg.scan_violation and misplaced(a, b, true @ error, v, cfg)
    v = _pair_violation(a, c, true, cfg)
    assert v > cfg.scan_violation and not misplaced(a, c, true, v, cfg)


def test_closures_the_solution_violates_are_counted_and_make_the_run_suspect():
    kfs, poses = _two_passes()
    cov = np.diag([1e-4, 1e-4, 1e-5])
    good = [LoopClosure(k, 49 - k, G.relative(poses[k], poses[49 - k]), cov, 1.0, 0.0, "spatial") for k in range(10)]
    sc = self_check(kfs, poses, good, True, SelfCheckConfig(exclude_recent_keyframes=5))
    assert sc.closures == 10 and sc.closures_violated == 0 and sc.verdict == "consistent"
    off = G.xytheta_to_matrix(0.5, 0.0, np.radians(2.0))
    wrong = [LoopClosure(lc.i, lc.j, lc.measurement @ off, cov, 1.0, 0.0, "spatial") for lc in good[:3]]
    sc = self_check(kfs, poses, good + wrong, True, SelfCheckConfig(exclude_recent_keyframes=5))
    assert sc.closures_violated == 3 and sc.closures_violated_20cm_1deg == 3 and sc.verdict == "suspect"


def _noisy_chain(rng, K: int, cov: np.ndarray):
    """True poses along a wandering path and one odometry edge per step, measured with noise ~ N(0, cov)."""
    steps = [G.xytheta_to_matrix(0.25, 0.0, t) for t in rng.normal(0, 0.1, K)]
    truth = [np.eye(4)]
    for s in steps[1:]:
        truth.append(truth[-1] @ s)
    truth = np.array(truth)
    edges = [(k - 1, k, G.relative(truth[k - 1], truth[k]) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), cov)), cov)
             for k in range(1, K)]
    return truth, edges


@pytest.mark.parametrize("scale, expect", [(1.0, 1.0), (4.0, 0.25)])
def test_nees_of_a_chain_with_the_right_covariance_is_one_per_dof_at_every_length(scale, expect):
    """Edges drawn with covariance Σ and evaluated with scale·Σ: NEES/dof averages 1/scale in every bin
    (Bar-Shalom et al. 2001 §5.4.2), within the sampling error of each bin."""
    rng = np.random.default_rng(11)
    K = 600
    cov = np.diag([0.01**2, 0.005**2, np.radians(0.3) ** 2])
    truth, edges = _noisy_chain(rng, K, cov)
    mu, C = fuse_steps(K, [(i, j, T, scale * S) for i, j, T, S in edges])
    pairs = np.array([(a, a + L) for L in (1, 2, 4, 8, 20, 60, 200, 500) for a in range(0, K - L, max(1, L // 4))])
    scan_kf = np.arange(K)
    rows = chain_nees(mu, C, scan_kf, truth, truth, pairs, G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]]))
    bins = bin_by_length(rows)
    assert [b.lo for b in bins] == [lo for lo in BIN_EDGES[:-1] if lo <= 500][: len(bins)]
    for b in bins:
        # The mean of n samples of χ²(3)/3 has standard deviation √(2/(3n)) (more with overlapping pairs).
        assert b.nees_mean == pytest.approx(expect, rel=0.3 + 4 * np.sqrt(2 / (3 * b.n))), b


@pytest.mark.parametrize("scale, expect", [(1.0, 1.0), (4.0, 0.25)])
def test_nees_against_closures_drawn_with_their_covariance_is_one_per_dof(scale, expect):
    """Closures as the reference: each drawn from the true relative pose with its own covariance (given in either
    direction), the chain's covariance plus the closure's explains the difference, NEES/dof 1/scale per bin."""
    rng = np.random.default_rng(5)
    K = 600
    cov = np.diag([0.01**2, 0.005**2, np.radians(0.3) ** 2])
    truth, edges = _noisy_chain(rng, K, cov)
    mu, C = fuse_steps(K, [(i, j, T, scale * S) for i, j, T, S in edges])
    lc = np.diag([0.02**2, 0.02**2, np.radians(0.5) ** 2])
    closures = []
    for L in (12, 40, 150, 450):
        for a in range(0, K - L, max(1, L // 6)):
            i, j = (a, a + L) if a % 2 else (a + L, a)  # half of them from the newer keyframe's side
            Z = G.relative(truth[i], truth[j]) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), lc))
            closures.append((i, j, Z, scale * lc))
    bins = bin_by_length(closure_nees(mu, C, closures))
    assert [b.lo for b in bins] == [11, 31, 101, 301]
    for b in bins:
        assert b.nees_mean == pytest.approx(expect, rel=0.3 + 4 * np.sqrt(2 / (3 * b.n))), b


def _jitter_chain(rng, K, J, W):
    """Truth, and the fused steps of a front end whose keyframes' scan-map poses each carry their own error
    (covariance *J*) and whose steps add a walk (*W*), each step stated with its whole covariance 2J + W."""
    steps = [G.xytheta_to_matrix(0.25, 0.0, t) for t in rng.normal(0, 0.1, K)]
    truth = [np.eye(4)]
    for s in steps[1:]:
        truth.append(truth[-1] @ s)
    truth = np.array(truth)
    scan = truth @ G.se2_exp(rng.multivariate_normal(np.zeros(3), J, K))  # each keyframe's scan-map pose
    edges = [(k - 1, k, G.relative(scan[k - 1], scan[k]) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), W)),
              2 * J + W) for k in range(1, K)]
    return truth, fuse_steps(K, edges)


def test_a_chain_of_jitter_is_consistent_only_with_the_jitter_at_its_ends():
    """Steps measured between scan-map poses that each carry their own error (e_k = j_k − j_(k−1) + w_k, the
    registration's jitter, docs/LOOP_CLOSURE.md): the model that compounds each step's whole covariance
    (2J + W) is conservative over long chains; the jitter at both ends plus the compounded walk is consistent
    at every length."""
    rng = np.random.default_rng(17)
    K = 800
    J = np.diag([0.01**2, 0.01**2, np.radians(0.2) ** 2])
    W = J / 20.0
    truth, (mu, C) = _jitter_chain(rng, K, J, W)
    pairs = np.array([(a, a + L) for L in (1, 2, 4, 8, 20, 60, 200, 500) for a in range(0, K - L, max(1, L // 4))])
    delta = G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]])
    share = np.trace(J) / np.trace(2 * J + W)  # J and W are proportional here, so the shares are exact

    def bins(**model):
        return bin_by_length(chain_nees(mu, C, np.arange(K), truth, truth, pairs, delta, **model))

    independent = bins()
    assert independent[0].nees_mean == pytest.approx(1.0, rel=0.3)  # one step: its whole covariance is right
    assert independent[-1].nees_mean < 0.2  # 500 steps: the jitter does not add up
    for b in bins(walk=1 - 2 * share, jitter=share):
        assert b.nees_mean == pytest.approx(1.0, rel=0.3 + 4 * np.sqrt(2 / (3 * b.n))), b
    # With the jitter known, the walk fitted to the long chains is the one they were drawn with.
    long = np.array([(a, a + L) for L in (120, 200, 300, 500) for a in range(0, K - L, 10)])
    truth_long = G.relative(truth[long[:, 0]], truth[long[:, 1]])
    fitted = fit_walk(chain_sample(mu, C, np.arange(K), truth, truth, long, truth_long), jitter=share)
    assert fitted is not None and fitted[1] >= 30
    assert fitted[0] == pytest.approx(1 - 2 * share, rel=0.3)


@pytest.mark.parametrize("walk_share", [0.05, 0.3])
def test_the_closures_calibrate_the_split_that_makes_every_chain_length_consistent(walk_share):
    """The run's calibration: closures (long ones, with their own covariance) fit the walk, the jitter is what keeps
    each step's stated covariance, and the model they give is the one the chains were drawn with: consistent against
    ground truth at every chain length, from one keyframe to hundreds."""
    rng = np.random.default_rng(23)
    K = 900
    Sigma = np.diag([0.012**2, 0.008**2, np.radians(0.25) ** 2])
    W, J = walk_share * Sigma, (1 - walk_share) / 2 * Sigma
    truth, (mu, C) = _jitter_chain(rng, K, J, W)
    lc = np.diag([0.02**2, 0.02**2, np.radians(0.3) ** 2])
    closures = []
    for L in (150, 300, 600):
        for a in range(0, K - L, 15):
            Z = G.relative(truth[a], truth[a + L]) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), lc))
            closures.append((a, a + L, Z, lc))
    model = calibrate(closure_sample(mu, C, closures))
    assert model is not None and model.long_chains == len(closures)
    assert model.walk == pytest.approx(walk_share, rel=0.35)
    assert model.jitter == pytest.approx((1 - model.walk) / 2)
    pairs = np.array([(a, a + L) for L in (1, 2, 4, 8, 20, 60, 200, 500) for a in range(0, K - L, max(1, L // 4))])
    delta = G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]])
    for b in bin_by_length(chain_sample(mu, C, np.arange(K), truth, truth, pairs, delta).rows(model.walk, model.jitter)):
        assert b.nees_mean == pytest.approx(1.0, rel=0.3 + 4 * np.sqrt(2 / (3 * b.n))), b
    # Too few long closures to fit: no model.
    assert calibrate(closure_sample(mu, C, closures[:20])) is None


def test_fused_parallel_edges_add_their_information_and_the_chain_compounds_them():
    rng = np.random.default_rng(3)
    T = G.xytheta_to_matrix(0.3, 0.1, 0.2)
    A, B = np.diag([1e-3, 2e-3, 1e-4]), np.diag([3e-3, 1e-3, 2e-4])
    mu, C = fuse_steps(2, [(0, 1, T, A), (0, 1, T, B)])
    assert np.allclose(mu[1], T) and np.allclose(C[1], np.linalg.inv(np.linalg.inv(A) + np.linalg.inv(B)))
    # An edge given backwards (1 → 0) is the same step.
    mu2, C2 = fuse_steps(2, [(1, 0, G.inverse(T), A @ np.eye(3))])
    assert np.allclose(mu2[1], T, atol=1e-12)
    # Chain.relative equals sequential compounding (Barfoot eq. 7.262).
    steps = [G.xytheta_to_matrix(*rng.normal(0, [0.5, 0.5, 0.3])) for _ in range(6)]
    covs = [np.diag(rng.uniform(1e-4, 1e-3, 3)) for _ in range(6)]
    ch = Chain(np.array([np.eye(4)] + steps[:5]), np.array([np.zeros((3, 3))] + covs[:5]))
    Tc, Sc = ch.relative(1, 5)
    T_seq, S_seq = np.eye(4), np.zeros((3, 3))
    for k in range(1, 5):
        S_seq = G.compound_covariance(S_seq, steps[k], covs[k])
        T_seq = T_seq @ steps[k]
    assert np.allclose(Tc, T_seq) and np.allclose(Sc, S_seq)
    with pytest.raises(ValueError, match="no edge between keyframes 1 and 2"):
        fuse_steps(3, [(0, 1, T, A)])


def test_slam_run_says_how_much_of_the_run_the_self_check_could_check(tmp_path, capsys):
    """The console's self-check line carries the verdict and how many keyframes overlapped another pass and
    were checked, both as in summary.json: a `consistent` over a handful of keyframes reads as what it is."""
    import json

    from tests.cli_helpers import corridor_log, slam

    log = tmp_path / "corridor.mcap"
    corridor_log(log, 300, seed=7)
    code, out, _ = slam(["run", log, "--out", tmp_path / "run", "--map", "none"], capsys)
    assert code == 0
    sc = json.loads((tmp_path / "run" / "summary.json").read_text())["self_check"]
    keyframes = json.loads((tmp_path / "run" / "summary.json").read_text())["keyframes"]
    line = next(ln for ln in out.splitlines() if ln.startswith("self_check:"))
    assert line.startswith(f"self_check: {sc['verdict']} ({sc['keyframes_checked']} of {keyframes} keyframes")
    assert 0 < sc["keyframes_checked"] <= keyframes


def test_a_heading_rate_in_the_odometry_is_consistent_only_with_the_drift_term():
    """Chains whose steps are all turned by one rate b ~ N(0, σ_b²) per metre, besides their independent
    noise: without the term the long chains' NEES/dof is far above 1 (the rate's error grows with the path,
    the edges' σ with its square root); with it, every bin averages 1 within its sampling error."""
    rng = np.random.default_rng(7)
    K, rate = 400, np.radians(0.05)
    cov = np.diag([0.01**2, 0.005**2, np.radians(0.1) ** 2])
    with_term, without = [], []
    for _chain in range(60):
        truth, edges = _noisy_chain(rng, K, cov)
        b = rng.normal(0.0, rate)
        tilted = [(i, j, T @ G.xytheta_to_matrix(0.0, 0.0, b * np.linalg.norm(T[:2, 3])), S) for i, j, T, S in edges]
        mu, C = fuse_steps(K, tilted)
        pairs = np.array([(a, a + L) for L in (1, 4, 20, 100, 350) for a in range(0, K - L, max(1, L))])
        args = (mu, C, np.arange(K), truth, truth, pairs, G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]]))
        with_term.append(chain_nees(*args, drift_rad_per_m=rate))
        without.append(chain_nees(*args))
    binned = bin_by_length(np.concatenate(with_term))
    plain = {b.lo: b for b in bin_by_length(np.concatenate(without))}
    for b in binned:
        # 60 independent rates: the bins of long chains average 60 χ²(3)/3 at most (pairs share their rate).
        assert b.nees_mean == pytest.approx(1.0, rel=0.45), b
    assert plain[301].nees_mean > 2.0 and plain[31].nees_mean > 1.3 and plain[1].nees_mean == pytest.approx(binned[0].nees_mean, rel=0.05)


def test_a_scale_error_of_the_rotation_is_consistent_only_with_its_term():
    """A robot circling one way (0.03 rad per 0.25 m step on average) whose every turn is scaled by (1 + k),
    k ~ N(0, σ_k²) per chain, besides independent noise: without the term the long chains are overconfident
    (the error grows with the summed turn); with it every bin averages 1 within its sampling error."""
    rng = np.random.default_rng(4)
    K, sigma_k = 400, 0.01
    cov = np.diag([0.01**2, 0.005**2, np.radians(0.1) ** 2])
    with_term, without = [], []
    for _chain in range(60):
        turns = rng.normal(0.03, 0.05, K)
        truth = np.array([np.eye(4)] + [np.eye(4)] * (K - 1))
        for k in range(1, K):
            truth[k] = truth[k - 1] @ G.xytheta_to_matrix(0.25, 0.0, turns[k])
        scale = rng.normal(0.0, sigma_k)
        edges = [(k - 1, k, G.xytheta_to_matrix(0.25, 0.0, turns[k] * (1 + scale)) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), cov)), cov)
                 for k in range(1, K)]
        mu, C = fuse_steps(K, edges)
        pairs = np.array([(a, a + L) for L in (1, 4, 20, 100, 350) for a in range(0, K - L, max(1, L))])
        args = (mu, C, np.arange(K), truth, truth, pairs, G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]]))
        with_term.append(chain_nees(*args, drift_per_turn=sigma_k))
        without.append(chain_nees(*args))
    plain = {b.lo: b for b in bin_by_length(np.concatenate(without))}
    for b in bin_by_length(np.concatenate(with_term)):
        assert b.nees_mean == pytest.approx(1.0, rel=0.45), b
    assert plain[301].nees_mean > 2.0 and plain[31].nees_mean > 1.3


def test_a_heading_rate_and_a_rotation_scale_error_read_back_from_the_fit_together():
    """One chain whose every step is turned by b·ℓ and every turn scaled by (1 + k), with little noise: the fit
    of the long chains' signed heading error on path and signed turn returns b and k, and its residual is far
    below the rate-only fit's (the scale error is what the rate alone cannot explain)."""
    rng = np.random.default_rng(9)
    K, rate, scale = 2000, np.radians(0.03), 0.012
    turns = rng.normal(0.02, 0.08, K)  # circling one way on average, weaving: path and turn not collinear
    truth = np.array([np.eye(4)] * K)
    for k in range(1, K):
        truth[k] = truth[k - 1] @ G.xytheta_to_matrix(0.25, 0.0, turns[k])
    cov = np.diag([1e-8, 1e-8, 1e-10])
    edges = [(k - 1, k, G.xytheta_to_matrix(0.25, 0.0, turns[k] * (1 + scale) + rate * 0.25) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), cov)), cov)
             for k in range(1, K)]
    mu, C = fuse_steps(K, edges)
    pairs = np.array([(a, a + L) for L in (250, 500, 900) for a in range(0, K - L, 37)])
    rows = chain_nees(mu, C, np.arange(K), truth, truth, pairs, G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]]))
    np.testing.assert_allclose(rows[:, 3], np.abs(rows[:, 7]))
    fit = heading_fit(rows)
    assert fit is not None and fit.n == len(pairs)
    assert fit.rate_deg_per_m == pytest.approx(0.03, rel=0.05)
    assert fit.scale_rad_per_rad == pytest.approx(scale, rel=0.05)
    assert fit.rms_deg < 0.1 * fit.rms_rate_only_deg
    assert heading_fit(rows[:5]) is None


def test_a_constant_heading_rate_reads_back_from_the_heading_table_at_every_path_length():
    rng = np.random.default_rng(2)
    K, rate_deg = 3000, 0.05
    cov = np.diag([1e-8, 1e-8, 1e-10])
    truth, edges = _noisy_chain(rng, K, cov)
    tilted = [(i, j, T @ G.xytheta_to_matrix(0.0, 0.0, np.radians(rate_deg) * np.linalg.norm(T[:2, 3])), S) for i, j, T, S in edges]
    mu, C = fuse_steps(K, tilted)
    pairs = np.array([(a, a + L) for L in (300, 600, 1200, 2400) for a in range(0, K - L, 97)])
    rows = chain_nees(mu, C, np.arange(K), truth, truth, pairs, G.relative(truth[pairs[:, 0]], truth[pairs[:, 1]]))
    bins = heading_by_path(rows)
    assert [b.lo_m for b in bins] == [50.0, 100.0, 200.0, 400.0]  # steps of 0.25 m: 75, 150, 300, 600 m
    for b in bins:
        assert b.rate_median_deg_per_m == pytest.approx(rate_deg, rel=0.05), b
        assert b.error_median_deg == pytest.approx(rate_deg * np.median(rows[(rows[:, 6] >= b.lo_m) & (rows[:, 6] < b.hi_m), 6]), rel=0.05)


def _relations_of(truth: np.ndarray, pairs, sigma_m: float, sigma_rad: float, rng):  # type: ignore[no-untyped-def]
    """Relations a_T_b of a trajectory, each with independent noise N(0, diag(σ², σ², σ_θ²)), stamps = indices."""
    from evaluation.relations import Relations

    deltas = np.array([G.relative(truth[a], truth[b]) @ G.se2_exp(rng.normal(0, [sigma_m, sigma_m, sigma_rad]))
                       for a, b in pairs])
    return Relations(np.array([float(a) for a, _ in pairs]), np.array([float(b) for _, b in pairs]), deltas)


def test_the_relations_own_noise_is_read_from_the_triangles_they_close():
    """Relations of one trajectory with independent errors of σ per axis and σ_θ: the closures of their
    triangles give σ back (to the sampling error of a few hundred triangles); exact relations give 0; too
    few triangles give no estimate."""
    from evaluation.relations import reference_noise

    rng = np.random.default_rng(5)
    truth, _ = _noisy_chain(rng, 400, np.eye(3) * 1e-6)
    pairs = [(a, a + L) for a in range(0, 390, 2) for L in (1, 2, 3)]
    est = reference_noise(_relations_of(truth, pairs, 0.02, np.radians(0.3), rng))
    assert est.triangles > 150
    assert est.sigma_translation_m == pytest.approx(0.02, rel=0.15)
    assert est.sigma_rotation_rad == pytest.approx(np.radians(0.3), rel=0.15)
    exact = reference_noise(_relations_of(truth, pairs, 0.0, 0.0, rng))
    assert exact.sigma_translation_m < 1e-12 and exact.sigma_rotation_rad < 1e-12
    assert reference_noise(_relations_of(truth, [(a, a + 1) for a in range(100)], 0.02, 0.01, rng)) is None


def test_a_noisy_reference_is_consistent_only_with_its_own_covariance_added():
    """A consistent chain scored against relations that carry their own error: NEES/dof above 1 on short
    chains without the reference's covariance, ≈ 1 with it (the test is of e ~ N(0, Σ_chain + Σ_ref))."""
    from evaluation.relations import reference_noise

    rng = np.random.default_rng(12)
    K = 600
    cov = np.diag([0.005**2, 0.003**2, np.radians(0.1) ** 2])
    truth, edges = _noisy_chain(rng, K, cov)
    mu, C = fuse_steps(K, edges)
    pairs = [(a, a + L) for a in range(0, K - 3, 2) for L in (1, 2, 3)]
    rel = _relations_of(truth, pairs, 0.02, np.radians(0.3), rng)
    noise = reference_noise(rel)
    P = np.array(pairs)
    without = bin_by_length(chain_nees(mu, C, np.arange(K), truth, truth, P, rel.deltas))
    with_ref = bin_by_length(chain_nees(mu, C, np.arange(K), truth, truth, P, rel.deltas, reference_cov=noise.covariance()))
    assert all(b.nees_mean > 3.0 for b in without)
    for b in with_ref:
        assert b.nees_mean == pytest.approx(1.0, rel=0.3), b
