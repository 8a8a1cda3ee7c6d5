"""Loop-closure stages on their own: candidate windows and sources, the acceptance stage's χ² gate and
pairwise-consistent groups, the chain variance the groups use."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2

from core import geometry as G
from slam.loops import candidates as C
from slam.loops.accept import Acceptance, mahalanobis2, to_closure
from slam.loops.config import LoopConfig
from slam.loops.types import Candidate, LoopClosure, LoopStats, Rejection, Source, Verified, Window
from slam.loops.uncertainty import NodeUncertainty, RelativeUncertainty


def _keyframes(K: int, dim: int = 2):
    return [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, dim)), odom_pose=np.eye(4))
            for k in range(K)]


def _line(K: int) -> np.ndarray:
    """An estimate of *K* keyframes 0.5 m apart along x (for acceptance tests that do not read it)."""
    return np.array([G.xytheta_to_matrix(0.5 * k, 0.0, 0.0) for k in range(K)])


# ---------------------------------------------------------------------------------------- windows


def test_windows_span_three_sigma_per_axis_above_their_floors_and_vouch_only_at_the_floor():
    cfg = LoopConfig()
    sd_xy = np.array([0.01, 0.5, 2.0, 5.0])  # per axis
    sd_th = np.radians([0.1, 1.0, 4.0, 90.0])
    unc = NodeUncertainty(2 * sd_xy**2, sd_th**2)  # traces: 2 axes of position, 1 of heading
    win_xy, win_th, sd = C.windows(unc, cfg, planar=True)
    assert np.allclose(sd, sd_xy)
    assert np.allclose(win_xy, np.maximum(cfg.window_sigmas * sd_xy, cfg.window_floor_m))
    expect_th = np.minimum(np.maximum(cfg.window_sigmas * sd_th, np.radians(cfg.window_floor_deg)), np.pi)
    assert np.allclose(win_th, expect_th)
    assert win_th[3] == pytest.approx(np.pi)  # never beyond the whole circle
    vouched = [win_xy[k] <= cfg.window_floor_m and win_th[k] <= np.radians(cfg.window_floor_deg) for k in range(4)]
    assert vouched == [True, False, False, False]


def test_the_heading_rate_widens_spatial_windows_up_to_the_spatial_limit_and_no_further():
    """Three places with the same independent noise (σ 0.1 m, 0.5°) and a growing heading-rate part: the
    window follows the total σ, is capped at ``max_window_m`` while the independent noise alone would be
    searched spatially, and is the independent noise's when that alone exceeds it (a global place stays
    one, and no place becomes one through the rate)."""
    cfg = LoopConfig()
    noise_xy = np.array([0.1, 0.1, 0.1, 4.0])  # per axis; the last alone is beyond max_window_m / 3
    drift_xy = np.array([0.0, 1.0, 8.0, 8.0])
    noise_th, drift_th = np.radians(0.5), np.radians([0.0, 3.0, 20.0, 20.0])
    unc = NodeUncertainty(2 * (noise_xy**2 + drift_xy**2), noise_th**2 + drift_th**2, 2 * drift_xy**2, drift_th**2)
    win_xy, win_th, sd = C.windows(unc, cfg, planar=True)
    total_xy = np.sqrt(noise_xy**2 + drift_xy**2)
    assert win_xy[0] == pytest.approx(cfg.window_floor_m)  # no rate: the floor, vouched
    assert win_xy[1] == pytest.approx(cfg.window_sigmas * total_xy[1])
    assert win_xy[2] == pytest.approx(cfg.max_window_m)  # capped: still a spatial candidate, searched widest
    assert win_xy[3] == pytest.approx(cfg.window_sigmas * noise_xy[3])  # beyond: the global search's, by its noise
    assert np.allclose(sd, total_xy)  # reach follows the total
    floor_th = np.radians(cfg.window_floor_deg)
    assert np.allclose(win_th, np.minimum(np.maximum(cfg.window_sigmas * np.sqrt(noise_th**2 + drift_th**2), floor_th), np.pi))
    poses = np.array([G.xytheta_to_matrix(0.0, 0.0, 0.0)] * 4)
    assert C.global_places(poses, 3, unc, cfg.model_copy(update={"exclude_recent_keyframes": 1}), True, 1.0, 1).tolist() == []
    assert unc.without_drift().position_var == pytest.approx(2 * noise_xy**2)


def _scene(K: int = 100):
    """Keyframe 99 at the origin; 50–70 a recent, well-tied pass 0.3–1.3 m away; 5–10 an old pass
    3 m away with σ 1.5 m per axis; 20 a place 30 m away with σ 15 m (beyond any spatial window)."""
    pos = np.full((K, 2), 500.0)
    pos[99] = 0.0
    pos[50:71, 0] = np.linspace(0.3, 1.3, 21)
    pos[50:71, 1] = 0.0
    pos[5:11] = [0.0, 3.0]
    pos[20] = [30.0, 0.0]
    sd = np.full(K, 0.01)
    sd[5:11] = 1.5
    sd[20] = 15.0
    poses = np.array([G.xytheta_to_matrix(x, y, 0.0) for x, y in pos])
    return poses, NodeUncertainty(2 * sd**2, np.full(K, 1e-6))


def test_spatial_candidates_take_the_nearest_and_keep_a_slot_for_an_uncertain_old_pass():
    cfg = LoopConfig(near_candidates=3, uncertain_candidates=1)
    poses, unc = _scene()
    found = C.spatial(_keyframes(100), poses, 99, unc, cfg, True, radius_m=2.0, path_m=np.arange(100.0))
    cands = list(found)
    ids = [c.i for c in cands]
    assert all(50 <= i <= 70 for i in ids[:3]) and ids[3] in range(5, 11)
    assert [c.i for c in found.near] == ids[:3] and [c.i for c in found.uncertain] == ids[3:]
    assert all(abs(a - b) > cfg.local_map_keyframes for a, b in itertools.combinations(ids, 2))  # maps spread
    old = cands[3]
    assert not old.vouched and old.window.xy_m == pytest.approx(cfg.window_sigmas * 1.5)
    assert all(c.vouched and c.window.xy_m == cfg.window_floor_m for c in cands[:3])
    assert 20 not in ids  # its window would exceed max_window_m: the global search's
    # Without the uncertain slot the old pass is crowded out by the recent one.
    assert all(50 <= c.i <= 70 for c in C.spatial(_keyframes(100), poses, 99, unc, cfg.model_copy(
        update={"uncertain_candidates": 0}), True, radius_m=2.0, path_m=np.arange(100.0)))


@pytest.mark.parametrize("near_closures, accepting, expect", [
    (2, True, ["n0", "n1", "u0", "u1"]),  # two nearest accepted: the other two nearest are not verified
    (None, True, ["n0", "n1", "n2", "n3", "u0", "u1"]),  # no bound: every candidate
    (2, False, ["n0", "n1", "n2", "n3", "u0", "u1"]),  # nothing accepted: every nearest place is tried
])
def test_the_nearest_candidates_are_verified_until_enough_closures_are_accepted(monkeypatch, near_closures, accepting, expect):
    """The nearest places are verified nearest first until ``near_closures`` closures of the new keyframe are
    accepted; the most uncertain places are verified whatever the nearest gave (an old pass is what they are for)."""
    from slam.loops.closer import LoopCloser

    K = 60
    cfg = LoopConfig(near_closures=near_closures, global_search=False, descriptor=False, overlap_radius_m=5.0)
    ru = RelativeUncertainty(planar=True)
    for k in range(1, K):
        ru.add_edge(k - 1, k, np.eye(3) * 1e-4, 0.5)
    closer = LoopCloser(cfg, True, ru)
    kfs = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.ones((10, 2)), odom_pose=np.eye(4)) for k in range(K)]
    names = {}

    def cand(i: int, name: str) -> Candidate:
        names[i] = name
        return Candidate(i, K - 1, Source.SPATIAL, np.eye(4), Window(1.0, 0.1), None, True)

    found = C.SpatialCandidates([cand(i, f"n{k}") for k, i in enumerate((40, 32, 24, 16))],
                                [cand(i, f"u{k}") for k, i in enumerate((8, 0))])
    assert [c.i for c in found] == [40, 32, 24, 16, 8, 0]  # iterated nearest first, then the uncertain
    monkeypatch.setattr(C, "spatial", lambda *a: found)
    monkeypatch.setattr(closer.verifier, "reference", lambda *a: None)
    verified: list[str] = []

    def run(c, keyframes, poses, ref, out, held=None):
        verified.append(names[c.i])
        if accepting:
            out.append(LoopClosure(c.i, c.j, np.eye(4), np.eye(3) * 1e-4, 1.0, 0.01, "spatial"))

    monkeypatch.setattr(closer, "_run", run)
    closer.detect(kfs, _line(K), K - 1, ru.from_node(K - 1, _line(K)[:, :2, 3]))
    assert verified == expect


def test_places_of_the_same_pass_are_not_candidates():
    """A keyframe the robot passed 5 m ago along a straight path is the odometry's business (the path between is
    not longer than their distance plus twice the overlap radius); the same place after a 40 m detour is not."""
    K = 100
    poses = np.array([G.xytheta_to_matrix(0.25 * k, 0.0, 0.0) for k in range(K)])
    poses[40] = G.xytheta_to_matrix(0.25 * 99 - 1.0, 0.5, np.pi)  # came back after a detour
    path = 0.25 * np.arange(K)
    path[41:] += 40.0
    unc = NodeUncertainty(np.full(K, 1e-4), np.full(K, 1e-6))
    cands = C.spatial(_keyframes(K), poses, 99, unc, LoopConfig(near_candidates=8), True, radius_m=2.0, path_m=path)
    assert [c.i for c in cands] == [40]
    assert C.other_pass(path, np.full(99, 1.0), 99, 2.0)[40] and not C.other_pass(path, np.full(99, 1.0), 99, 2.0)[80]


def test_global_places_are_those_within_reach_whose_window_no_spatial_search_covers():
    cfg = LoopConfig()
    poses, unc = _scene()
    places = C.global_places(poses, 99, unc, cfg, True, radius_m=2.0, spacing=10)
    assert places.tolist() == [20]  # within 2 m + 3·15 m, window 45 m > max_window_m
    assert C.global_places(poses, 10, unc, cfg, True, 2.0, 10).size == 0  # nothing older than the exclusion window


def test_the_heading_rate_puts_a_far_drifted_place_within_the_global_search_s_reach():
    """A place 60 m from the estimate whose independent noise is 5 m per axis (4 σ beyond the radius: out of
    reach) but whose heading-rate term adds 25 m (within 3 σ of the whole) is the global search's."""
    cfg = LoopConfig()
    K = 30
    poses = np.array([G.xytheta_to_matrix(500.0, 0.0, 0.0)] * K)
    poses[29] = np.eye(4)
    poses[0] = G.xytheta_to_matrix(60.0, 0.0, 0.0)
    noise, drift = np.full(K, 0.01), np.zeros(K)
    noise[0], drift[0] = 5.0, 25.0
    unc = NodeUncertainty(2 * (noise**2 + drift**2), np.full(K, 1e-4), 2 * drift**2, np.zeros(K))
    assert C.global_places(poses, 29, unc, cfg, True, radius_m=2.0, spacing=1).tolist() == [0]
    assert C.global_places(poses, 29, unc.without_drift(), cfg, True, radius_m=2.0, spacing=1).size == 0


def test_the_global_search_takes_the_most_alike_place_not_searched_since_the_robot_moved_a_radius():
    places = np.array([0, 20, 40, 60])
    searched = {20: 95.0, 40: 80.0}  # path (m) at their last global search
    fresh = C.unsearched(places, searched, here_m=100.0, radius_m=10.0)
    assert fresh.tolist() == [0, 40, 60]  # 20 was searched 5 m of path ago; 40, 20 m ago, may be again
    alike = np.array([0.6, 0.3, 0.3])
    sigmas = np.array([0.5, 4.0, 2.0])
    assert C.next_global_place(fresh, alike, sigmas) == 60  # as alike as 40, nearer in σ
    assert C.next_global_place(fresh, np.array([0.6, 0.2, 0.3]), sigmas) == 40  # appearance before the estimate
    assert C.unsearched(places, {}, 0.0, 10.0).tolist() == places.tolist()


def test_a_global_candidate_searches_the_whole_local_map_and_every_heading():
    cfg = LoopConfig()
    poses, unc = _scene()
    lo, hi = np.array([-4.0, -1.0]), np.array([6.0, 3.0])
    c = C.global_candidate(_keyframes(100), poses, 20, 99, unc, cfg, (lo, hi))
    assert c.source is Source.GLOBAL and not c.vouched
    assert c.window.xy_m == pytest.approx(5.0) and c.window.theta_rad == pytest.approx(np.pi)
    assert np.allclose(G.matrix_to_xytheta(c.guess)[:2], [1.0, 1.0])


def test_the_overlap_radius_is_the_upper_quartile_of_the_scan_ranges_unless_configured():
    r = np.linspace(1.0, 9.0, 81)
    kf = SimpleNamespace(points=np.column_stack([r, np.zeros_like(r)]))
    assert C.overlap_radius(kf, LoopConfig()) == pytest.approx(np.percentile(r, 75))
    assert C.overlap_radius(kf, LoopConfig(overlap_radius_m=2.5)) == 2.5


# ---------------------------------------------------------------------------------------- chain variance


def test_chain_variance_fuses_parallel_steps_and_carries_heading_over_the_lever_arm():
    """Steps 0→1→2→3 each with a registration edge (vt 4e-4, vr 1e-4) and a wheel edge (vt 4e-4, vr 3e-4):
    fused per block by information, vt = 2e-4, vr = 7.5e-5; along the chain the rotation variance of
    each step is carried to the end keyframe over its lever arm."""
    ru = RelativeUncertainty(planar=True)
    for k in range(1, 4):
        ru.add_edge(k - 1, k, np.diag([2e-4, 2e-4, 1e-4]))
        ru.add_edge(k - 1, k, np.diag([2e-4, 2e-4, 3e-4]))
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    vt, vr = ru.chain_variance(0, 3, pos)
    fused_r = 1e-4 * 3e-4 / (1e-4 + 3e-4)
    lever2 = np.array([2.5, 1.5, 0.5]) ** 2  # step centres 0.5, 1.5, 2.5 m from keyframe 3
    assert vr == pytest.approx(3 * fused_r)
    assert vt == pytest.approx(3 * 2e-4 + fused_r * lever2.sum())
    assert ru.chain_variance(3, 0, pos)[1] == pytest.approx(vr)  # order of the ends does not matter
    assert ru.chain_variance(2, 2, pos) == (0.0, 0.0)


def test_chain_variance_without_a_step_edge_is_the_limit():
    ru = RelativeUncertainty(planar=True, limit_m2=99.0)
    ru.add_edge(0, 1, np.eye(3) * 1e-4)
    ru.add_edge(2, 3, np.eye(3) * 1e-4)
    assert ru.chain_variance(0, 3, np.zeros((4, 2))) == (99.0, 99.0)


# ---------------------------------------------------------------------------------------- acceptance


def _verified(i: int, j: int, T: np.ndarray, est: np.ndarray | None, est_cov: np.ndarray | None, vouched: bool,
              cov: np.ndarray | None = None, source: Source = Source.SPATIAL) -> Verified:
    cand = Candidate(i, j, source, T if est is None else est, Window(1.0, 0.1),
                     None if est is None else (est, est_cov), vouched,
                     plausible=None if est is None else Window(1.0, np.radians(5.0)))
    return Verified(cand, T, np.diag([1e-4, 1e-4, 1e-5]) if cov is None else cov, 0.9, 0.02, 0.8, 3)


def _acceptance(cfg: LoopConfig | None = None, K: int = 60, step_cov: float = 1e-6):
    ru = RelativeUncertainty(planar=True)
    for k in range(1, K):
        ru.add_edge(k - 1, k, np.eye(3) * step_cov)
    return Acceptance(cfg or LoopConfig(), True, ru, LoopStats())


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_a_vouched_alignment_is_accepted_exactly_when_it_passes_the_chi2_gate(scale):
    """The gate is the consistency_probability quantile of χ²(3) on the Mahalanobis distance under the sum
    of both covariances: an offset just inside is accepted alone, just outside rejected (without the closer's
    overrule hook, no group may overturn an estimate that vouches). Where the run's closures scaled the closer's
    variances (``loops.window_calibration``; the candidate then carries the scaled covariance) the gate is still
    the model's as stated: the scale widens where the closer looks and what may wait for a group, not how far
    one closure moves the estimate on its own."""
    cfg = LoopConfig()
    gate = chi2.ppf(cfg.consistency_probability, 3)
    est = G.xytheta_to_matrix(2.0, 0.0, 0.0)
    est_cov = np.diag([0.01, 0.01, 1e-4])
    cov = np.diag([1e-4, 1e-4, 1e-5])
    s = np.sqrt(0.01 + 1e-4)
    for factor, accepted in ((0.98, True), (1.02, False)):
        T = est @ G.se2_exp([factor * s * np.sqrt(gate), 0.0, 0.0])
        acc = _acceptance(cfg)
        acc.uncertainty.scale = scale
        if scale > 1:
            assert mahalanobis2(est, scale * est_cov, T, cov, True) < gate  # inside the widened gate either way
        lc = acc.consider(_verified(0, 30, T, est, scale * est_cov, True, cov), _keyframes(60), _line(60),
                          lambda v: True)
        assert (lc is not None) == accepted
        assert acc.stats.accepted == int(accepted) and acc.pending == []
        assert acc.stats.rejections[Rejection.INCONSISTENT] == int(not accepted)
        assert mahalanobis2(est, est_cov, T, cov, True) == pytest.approx(factor**2 * gate, rel=1e-6)
    # Outside the window the estimate would have searched (a corridor turned round): rejected, not held for a group.
    acc = _acceptance(cfg)
    flipped = est @ G.xytheta_to_matrix(0.0, 0.0, np.pi)
    assert acc.consider(_verified(0, 30, flipped, est, est_cov, True, cov), _keyframes(60), _line(60), lambda v: True) is None
    assert acc.pending == [] and acc.stats.rejections[Rejection.INCONSISTENT] == 1


def test_a_global_match_is_held_pending_only_within_its_chi2_gate_of_the_estimate():
    """A global search is not bounded by the estimate (whole local map, every heading): its match goes on to
    the group stage only within the ``GLOBAL_PLAUSIBLE_PROBABILITY`` quantile of χ²(3) of the estimate's
    covariance; just outside it is rejected, as a match turned round 80° from an estimate sure to 10° is."""
    gate = chi2.ppf(C.GLOBAL_PLAUSIBLE_PROBABILITY, 3)
    est = G.xytheta_to_matrix(30.0, 5.0, 0.3)
    est_cov = np.diag([400.0, 400.0, np.radians(10.0) ** 2])  # σ 20 m per axis, 10°
    cov = np.diag([1e-4, 1e-4, 1e-5])
    s = np.sqrt(est_cov[2, 2] + cov[2, 2])
    for factor, kept in ((0.98, True), (1.02, False)):
        T = est @ G.se2_exp([0.0, 0.0, factor * s * np.sqrt(gate)])
        cand = Candidate(0, 30, Source.GLOBAL, est, Window(25.0, np.pi), (est, est_cov), False,
                         max_mahalanobis2=float(gate))
        acc = _acceptance()
        assert acc.consider(Verified(cand, T, cov, 0.9, 0.02, 0.8, 3), _keyframes(60), _line(60), lambda v: True) is None
        assert len(acc.pending) == int(kept)
        assert acc.stats.rejections[Rejection.INCONSISTENT] == int(not kept)
    poses, unc = _scene()
    c = C.global_candidate(_keyframes(100), poses, 20, 99, unc, LoopConfig(), (np.zeros(2), np.ones(2)))
    assert c.max_mahalanobis2 == pytest.approx(gate)


def test_a_descriptor_match_the_estimate_cannot_vouch_for_is_held_to_the_global_gate():
    """A descriptor picks a place by its looks, as the global search does: where the estimate cannot vouch for
    the pair, its match goes on to the group stage only within the same χ² gate of the estimate (an alias at a
    place that looks alike, 27 m from an estimate right to 2 m, was 8.9 σ out and still inside the
    three-window box); where the estimate vouches, its own consistency gate decides as before."""
    gate = chi2.ppf(C.GLOBAL_PLAUSIBLE_PROBABILITY, 3)
    poses, unc = _scene()
    far, near = C.descriptor([(20, 0.0), (60, 0.0)], _keyframes(100), poses, 99, unc, LoopConfig(), True, 10.0, 0.1)
    assert not far.vouched and far.max_mahalanobis2 == pytest.approx(gate)
    assert far.corroborated_mahalanobis2 == pytest.approx(chi2.ppf(C.GLOBAL_CORROBORATED_PROBABILITY, 3))
    assert near.vouched and near.max_mahalanobis2 is None and near.corroborated_mahalanobis2 is None
    far3, _ = C.descriptor([(20, 0.0), (60, 0.0)], _keyframes(100, 3), poses, 99, unc, LoopConfig(), False, 10.0, 0.1)
    assert far3.max_mahalanobis2 == pytest.approx(chi2.ppf(C.GLOBAL_PLAUSIBLE_PROBABILITY, 6))  # a 6-dof pose in 3D
    est, est_cov = far.estimate
    cov = np.diag([1e-4, 1e-4, 1e-5])
    s = np.sqrt(est_cov[0, 0] + cov[0, 0])
    for factor, kept in ((0.98, True), (1.02, False)):
        T = est @ G.se2_exp([factor * s * np.sqrt(gate), 0.0, 0.0])
        assert mahalanobis2(est, est_cov, T, cov, True) == pytest.approx(factor**2 * gate, rel=1e-3)
        acc = _acceptance()
        assert acc.consider(Verified(far, T, cov, 0.9, 0.02, 0.8, 3), _keyframes(100), poses, lambda v: True) is None
        assert len(acc.pending) == int(kept)
        assert acc.stats.rejections[Rejection.INCONSISTENT] == int(not kept)


def _drifted_return(K: int = 300):
    """Truth: 0–99 an old pass along x (0.5 m apart), 200–299 its revisit 0.2 m beside it. The estimate puts the
    revisit 2 m / 1 m off and turned by 3° (a heading drift the covariance did not know)."""
    truth = np.array([G.xytheta_to_matrix(0.5 * k, 0.0, 0.0) for k in range(K)])
    truth[100:200] = [G.xytheta_to_matrix(50.0, 0.5 * (k - 100), np.pi / 2) for k in range(100, 200)]
    truth[200:] = [G.xytheta_to_matrix(0.5 * (k - 200) + 0.1, 0.2, 0.0) for k in range(200, K)]
    est = truth.copy()
    est[200:] = G.xytheta_to_matrix(2.0, 1.0, np.radians(3.0)) @ truth[200:]
    return truth, est


def _global_match(truth, est, i, j, m2, offset=None):
    """A global match of *j* on place *i* (map half 20), measured from *truth* (× *offset*), whose estimate's
    covariance puts it at squared Mahalanobis distance *m2* from the estimate."""
    Z = G.relative(truth[i], truth[j]) @ (np.eye(4) if offset is None else offset)
    E = G.relative(est[i], est[j])
    e = G.se2_log(G.inverse(E) @ Z)
    cov = np.eye(3) * 1e-8
    est_cov = np.eye(3) * float(e @ e) / m2 - cov
    cand = Candidate(i, j, Source.GLOBAL, E, Window(25.0, np.pi), (E, est_cov), False,
                     max_mahalanobis2=float(chi2.ppf(C.GLOBAL_PLAUSIBLE_PROBABILITY, 3)),
                     corroborated_mahalanobis2=float(chi2.ppf(C.GLOBAL_CORROBORATED_PROBABILITY, 3)))
    return Verified(cand, Z, cov, 0.9, 0.02, 0.8, 20)


def test_a_global_match_beyond_its_gate_waits_for_a_group_only_when_an_independent_one_agrees():
    """A return after a heading drift the model does not know lies a few σ beyond the global gate (χ² 20 > 16.3).
    One such match is rejected; a second, against old structure that shares no keyframe with the first's
    local map (±20), that agrees with it — the same correction of the estimate — is held for a group. Not so
    against the same structure, nor when the two disagree (one slid 2 m along the corridor), nor beyond the
    looser limit (χ² 35 > 30.7), nor when it is not unique, nor when the odometry (σ 3 cm, 1.8° a step) is
    too unsure to compare them."""
    truth, est = _drifted_return()
    kfs = _keyframes(300)

    def run(second_place, m2=20.0, offset=None, unique=True, step_cov=1e-6):
        acc = _acceptance(K=300, step_cov=step_cov)
        first = acc.consider(_global_match(truth, est, 10, 210, m2), kfs, est, lambda v: True)
        assert first is None and acc.pending == []
        second = _global_match(truth, est, second_place, 200 + second_place, m2, offset)
        assert acc.consider(second, kfs, est, lambda v: unique) is None
        return acc

    acc = run(60)
    assert [(p.closure.i, p.closure.j) for p in acc.pending] == [(60, 260)] and acc.stats.corroborated == 1
    assert acc.stats.rejections[Rejection.INCONSISTENT] == 1  # the first, alone
    for acc in (run(25), run(60, offset=G.xytheta_to_matrix(2.0, 0.0, 0.0)), run(60, m2=35.0), run(60, unique=False),
                run(60, step_cov=1e-3)):
        assert acc.pending == [] and acc.stats.corroborated == 0
        assert acc.stats.rejections[Rejection.INCONSISTENT] == 2


def test_an_alignment_held_pending_must_be_unique_and_one_the_estimate_vouches_for_is_not_asked():
    est = G.xytheta_to_matrix(2.0, 0.0, 0.0)
    asked: list[int] = []

    def unique(v):
        asked.append(v.candidate.j)
        return False

    acc = _acceptance()
    acc.consider(_verified(0, 30, est, est, np.eye(3) * 1e-2, True), _keyframes(60), _line(60), unique)  # vouched, consistent
    acc.consider(_verified(0, 31, est, None, None, False), _keyframes(60), _line(60), unique)  # unvouched: ambiguous → dropped
    assert asked == [31] and acc.pending == [] and acc.stats.rejections[Rejection.AMBIGUOUS] == 1


def _return(truth: np.ndarray, correction: np.ndarray, rng, offsets=None):
    """Closures of keyframes 30–34 with places 0–4 (the same corridor stretch), measured from *truth*
    (1 cm, 0.1° noise, plus per-closure *offsets*), while the estimate has the new keyframes moved by
    *correction*."""
    est = truth.copy()
    est[30:35] = correction @ truth[30:35]
    out = []
    for n, (i, j) in enumerate(zip(range(5), range(30, 35))):
        noise = G.xytheta_to_matrix(*rng.normal(0, [0.01, 0.01, np.radians(0.1)]))
        T = G.relative(truth[i], truth[j]) @ noise
        if offsets is not None:
            T = T @ offsets[n]
        out.append(_verified(i, j, T, None, None, False))
    return est, out


def _corridor_truth(K: int = 60) -> np.ndarray:
    """0–4 and 30–34 along one corridor (0.5 m apart); 5–29 a 63 m loop round a 10 m circle in between."""
    truth = np.array([G.xytheta_to_matrix(0.5 * k, 0.0, 0.0) for k in range(K)])
    a = np.linspace(-np.pi / 2, 1.5 * np.pi, 27)[1:-1]
    truth[5:30] = [G.xytheta_to_matrix(2.5 + 10 * np.cos(t), 10 + 10 * np.sin(t), t + np.pi / 2) for t in a]
    truth[30:35] = [G.xytheta_to_matrix(0.5 * (k - 30) + 0.2, 0.3, 0.05) for k in range(30, 35)]
    return truth


def test_agreeing_pending_closures_are_accepted_as_a_group_once_their_window_has_passed():
    """After a 2 m / 12° drift none of the return's closures can be vouched for; the five agree pairwise
    (their cycles through the estimate's short stretches close), so they are accepted together when the
    group window after the first has passed — and not before."""
    rng = np.random.default_rng(4)
    truth = _corridor_truth()
    est, verified = _return(truth, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)), rng)
    cfg = LoopConfig()
    acc = _acceptance(cfg, step_cov=1e-5)
    for v in verified:
        assert acc.consider(v, _keyframes(60), _line(60), lambda v: True) is None
    W = cfg.group_window_keyframes
    assert acc.decide(30 + W - 2, est) == []  # the window after keyframe 30 is not complete
    group = acc.decide(30 + W - 1, est)
    assert sorted(lc.j for lc in group) == [30, 31, 32, 33, 34] and all(lc.group for lc in group)
    assert acc.pending == [] and acc.stats.accepted_as_group == 5
    assert acc.relocalises(group, est)  # 2 m off: beyond what a kernel lets a closure pull


def test_a_window_still_open_when_the_log_ends_is_decided_on_the_evidence_it_has():
    """A return to the start at the very end of a log: its closures arrive in the last keyframes, and the
    group window after them never passes. At the end the open window is decided as it stands (the same
    group a completed window would accept), and then nothing is pending."""
    rng = np.random.default_rng(7)
    truth = _corridor_truth(35)
    est, verified = _return(truth, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)), rng)
    acc = _acceptance(step_cov=1e-5, K=35)
    for v in verified:
        acc.consider(v, _keyframes(35), _line(35), lambda v: True)
    assert acc.decide(34, est) == []  # the last keyframe: the window after keyframe 30 is not complete
    group = acc.decide_open_window(est)
    assert sorted(lc.j for lc in group) == [30, 31, 32, 33, 34] and all(lc.group for lc in group)
    assert acc.pending == [] and acc.decide_open_window(est) is None


def test_a_search_decided_at_once_keeps_its_closures_out_of_the_pending_pool():
    """Closures held for one search (the keyframes sought again after a relocalisation) are decided together at
    once: the five agreeing ones of a drifted return as a group, five that each slid along the corridor not at
    all; the pool whose windows close keyframe by keyframe never sees them."""
    truth = _corridor_truth()
    for offsets, accepted in ((None, 5), ([G.xytheta_to_matrix(0.5 * k, 0.0, 0.0) for k in range(5)], 0)):
        est, verified = _return(truth, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)), np.random.default_rng(4), offsets)
        acc = _acceptance(step_cov=1e-5)
        held: list = []
        for v in verified:
            assert acc.consider(v, _keyframes(60), est, lambda v: True, held) is None
        assert acc.pending == [] and len(held) == 5
        group = acc.decide_held(held, est)
        assert len(group) == accepted and all(lc.group for lc in group)
        assert acc.stats.accepted_as_group == accepted and acc.stats.pending_expired == 5 - accepted


def test_refused_global_matches_are_remembered_until_taken_the_newest_kept():
    """A unique global match refused beyond the gate is remembered (where the estimate was off by more than it
    knew); one beyond the looser limit, or not unique, is not. Taking them empties the memory, which keeps the
    newest ``_REFUSED_KEPT``."""
    from slam.loops import accept as A

    truth, est = _drifted_return()
    kfs = _keyframes(300)
    acc = _acceptance(K=300)
    acc.consider(_global_match(truth, est, 10, 210, 20.0), kfs, est, lambda v: True)
    acc.consider(_global_match(truth, est, 60, 260, 35.0), kfs, est, lambda v: True)
    acc.consider(_global_match(truth, est, 80, 280, 20.0), kfs, est, lambda v: False)
    assert acc.take_refused() == [210] and acc.take_refused() == []
    for j in range(201, 201 + A._REFUSED_KEPT + 5):
        acc.consider(_global_match(truth, est, 0, j, 20.0), kfs, est, lambda v: True)  # one place: none corroborates
    assert acc.refused == list(range(206, 201 + A._REFUSED_KEPT + 5))


def test_after_a_relocalisation_the_moved_keyframes_around_refused_matches_are_sought_again(monkeypatch):
    """Seeking again covers ± group_window_keyframes around each refused match, older than the newest keyframe,
    and only keyframes the relocalisation moved; each under its own uncertainty, with the corrected estimate."""
    from slam.loops.closer import LoopCloser

    K = 120
    cfg = LoopConfig()
    ru = RelativeUncertainty(planar=True)
    for k in range(1, K):
        ru.add_edge(k - 1, k, np.eye(3) * 1e-4, 0.5)
    closer = LoopCloser(cfg, True, ru)
    closer._path_m = list(0.5 * np.arange(K))
    kfs = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.ones((10, 2)), odom_pose=np.eye(4)) for k in range(K)]
    poses = _line(K)
    sought: list[int] = []

    def spatial(keyframes, p, k, unc, *args):
        assert p is poses and unc.position_var[k] == 0.0  # the uncertainty relative to k itself
        sought.append(k)
        return []

    monkeypatch.setattr(C, "spatial", spatial)
    monkeypatch.setattr(closer.verifier, "reference", lambda *a: None)
    closer.acceptance.refused = [30, 35, 112]
    moved = np.ones(K, dtype=bool)
    moved[38:] = False
    moved[112:] = True
    assert closer.refused
    closures, relocalise = closer.reseek(kfs, poses, moved, ru)
    W = cfg.group_window_keyframes
    assert closures == [] and not relocalise and not closer.refused
    assert sought == list(range(30 - W, 38)) + list(range(112, K - 1))
    assert closer.stats.reseeks == len(sought)


def test_closures_that_disagree_form_no_group_and_expire():
    """Five closures, each slid along the corridor by its own 0.5 m: no three agree."""
    rng = np.random.default_rng(5)
    truth = _corridor_truth()
    offsets = [G.xytheta_to_matrix(0.5 * k, 0.0, 0.0) for k in range(5)]
    est, verified = _return(truth, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)), rng, offsets)
    acc = _acceptance(step_cov=1e-5)
    for v in verified:
        acc.consider(v, _keyframes(60), _line(60), lambda v: True)
    assert acc.decide(30 + LoopConfig().group_window_keyframes - 1, est) == []
    assert acc.stats.pending_expired == 5 and acc.pending == []


def test_a_group_contradicted_by_a_closure_accepted_alone_nearby_is_refused():
    """The group says the new keyframes are 2 m along; keyframe 31 was meanwhile closed on its own with place
    1 where the estimate had it: the estimate was right there, the group is an alias."""
    rng = np.random.default_rng(6)
    truth = _corridor_truth()
    alias = G.xytheta_to_matrix(2.0, 0.0, 0.0)
    est = truth.copy()
    _, verified = _return(truth, np.eye(4), rng, [alias] * 5)
    acc = _acceptance(step_cov=1e-5)
    alone = _verified(1, 31, G.relative(est[1], est[31]), G.relative(est[1], est[31]), np.eye(3) * 1e-2, True)
    assert acc.consider(alone, _keyframes(60), _line(60), lambda v: True) is not None
    for v in verified:
        acc.consider(v, _keyframes(60), _line(60), lambda v: True)
    assert acc.decide(30 + LoopConfig().group_window_keyframes - 1, est) == []
    assert acc.stats.groups_contradicted == 1


def test_an_agreeing_group_its_context_check_refuses_expires_and_is_counted():
    """The acceptance stage's last word goes to its ``confirm`` hook (the closer's context check): the same
    five agreeing closures as above are refused when it says no — with the group it was handed — and accepted
    when it says yes."""
    truth = _corridor_truth()
    for verdict in (False, True):
        rng = np.random.default_rng(4)
        est, verified = _return(truth, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)), rng)
        acc = _acceptance(step_cov=1e-5)
        asked: list[list[int]] = []
        acc.confirm = lambda group, poses, verdict=verdict: asked.append(sorted(lc.j for lc in group)) or verdict
        for v in verified:
            acc.consider(v, _keyframes(60), _line(60), lambda v: True)
        group = acc.decide(30 + LoopConfig().group_window_keyframes - 1, est)
        assert asked == [[30, 31, 32, 33, 34]]
        assert len(group) == (5 if verdict else 0)
        assert acc.stats.groups_out_of_context == (0 if verdict else 1)
        assert acc.stats.pending_expired == (0 if verdict else 5)


def test_a_group_the_estimate_vouched_against_stands_only_when_its_recent_path_bears_it_out():
    """Where the estimate vouches and disagrees (0.3 m and 1° off, sure to 1 cm and 0.06°), a unique closure is
    held for a group instead of dropped; the group then needs the ``overrule`` hook's word (the closer's
    path_overrules) besides every other test: refused and counted when it says no, accepted when it says yes.
    Without the hook such closures are rejected as before."""
    truth = _corridor_truth()
    est = truth.copy()
    est[30:35] = G.xytheta_to_matrix(0.3, 0.0, np.radians(1.0)) @ truth[30:35]
    est_cov, cov = np.diag([1e-4, 1e-4, 1e-6]), np.diag([1e-4, 1e-4, 1e-5])
    W = LoopConfig().group_window_keyframes
    for verdict in (None, False, True):
        rng = np.random.default_rng(5)
        acc = _acceptance(step_cov=1e-5)
        acc.confirm = lambda group, poses: True
        if verdict is not None:
            acc.overrule = lambda group, poses, verdict=verdict: verdict
        for i, j in zip(range(5), range(30, 35)):
            T = G.relative(truth[i], truth[j]) @ G.xytheta_to_matrix(*rng.normal(0, [0.01, 0.01, np.radians(0.1)]))
            e = G.relative(est[i], est[j])
            assert mahalanobis2(e, est_cov, T, cov, True) > acc.gate
            assert acc.consider(_verified(i, j, T, e, est_cov, True, cov), _keyframes(60), _line(60), lambda v: True) is None
        assert len(acc.pending) == (0 if verdict is None else 5)
        assert acc.stats.rejections[Rejection.INCONSISTENT] == (5 if verdict is None else 0)
        group = acc.decide(30 + W - 1, est)
        assert len(group) == (5 if verdict else 0)
        assert acc.stats.groups_not_overruling == int(verdict is False)
        assert acc.pending == []  # decided: none is left waiting


def _two_passes_truth(K: int = 60) -> np.ndarray:
    """Keyframes 0–4, 20–24 and 30–34 pass one corridor stretch (0.5 m apart); 5–19 and 25–29 loop round a 10 m
    circle in between."""
    truth = _corridor_truth(K)
    a = np.linspace(-np.pi / 2, 1.5 * np.pi, 17)[1:-1]
    truth[5:20] = [G.xytheta_to_matrix(2.5 + 10 * np.cos(t), 10 + 10 * np.sin(t), t + np.pi / 2) for t in a]
    truth[20:25] = [G.xytheta_to_matrix(0.5 * (k - 20) + 0.1, 0.2, 0.02) for k in range(20, 25)]
    b = np.linspace(-np.pi / 2, 1.5 * np.pi, 7)[1:-1]
    truth[25:30] = [G.xytheta_to_matrix(2.5 + 10 * np.cos(t), 10 + 10 * np.sin(t), t + np.pi / 2) for t in b]
    return truth


def _closures(truth: np.ndarray, pairs, rng, offset: np.ndarray | None = None) -> list[Verified]:
    """Unvouched closures of keyframe pairs measured from *truth* (1 cm, 0.1° noise), moved by *offset*."""
    out = []
    for i, j in pairs:
        T = G.relative(truth[i], truth[j]) @ G.xytheta_to_matrix(*rng.normal(0, [0.01, 0.01, np.radians(0.1)]))
        out.append(_verified(i, j, T if offset is None else T @ offset, None, None, False))
    return out


def test_a_return_to_two_passes_the_graph_misplaced_gives_a_group_against_each():
    """The return (30–34) meets the corridor's first pass (0–4) and its second (20–24), which the graph holds
    2.5 m and 8° from the first — farther than the 20 keyframes between them can vouch for. Both sets of closures
    are right; each agrees within itself and disagrees with the other through the graph's wrong stretch. The
    larger set does not refute the smaller: both are accepted, once each. Closures against the first pass that
    put the return 2 m along it (an alias of that same place, which the stretch 0–4 does vouch for) are refused
    with the group they contradict standing."""
    W = LoopConfig().group_window_keyframes
    truth = _two_passes_truth()
    est = truth.copy()
    est[20:25] = G.xytheta_to_matrix(2.5, 0.5, np.radians(8)) @ truth[20:25]
    est[30:35] = G.xytheta_to_matrix(2.0, -0.5, np.radians(12)) @ truth[30:35]
    rng = np.random.default_rng(8)
    first = _closures(truth, zip(range(5), range(30, 35)), rng)
    second = _closures(truth, zip(range(20, 23), range(30, 33)), rng)
    acc = _acceptance(step_cov=1e-4)
    assert not C.vouches(*acc.uncertainty.chain_variance(0, 20, est[:, :2, 3]), LoopConfig(), True)
    assert not acc.pairwise.consistent(to_closure(first[0], _keyframes(60), True), to_closure(second[0], _keyframes(60), True), est)
    for v in first + second:
        acc.consider(v, _keyframes(60), _line(60), lambda v: True)
    group = acc.decide(30 + W - 1, est)
    assert sorted((lc.i, lc.j) for lc in group) == sorted([(i, j) for i, j in zip(range(5), range(30, 35))]
                                                          + [(i, j) for i, j in zip(range(20, 23), range(30, 33))])
    assert acc.stats.accepted_as_group == 8 and acc.stats.pending_expired == 0

    acc = _acceptance(step_cov=1e-4)
    alias = _closures(truth, zip(range(1, 4), range(30, 33)), rng, G.xytheta_to_matrix(2.0, 0.0, 0.0))
    for v in _closures(truth, zip(range(5), range(30, 35)), rng) + alias:
        acc.consider(v, _keyframes(60), _line(60), lambda v: True)
    group = acc.decide(30 + W - 1, est)
    assert sorted(lc.i for lc in group) == [0, 1, 2, 3, 4]
    assert acc.stats.pending_expired == 3


def test_closures_against_a_place_the_chain_cannot_compare_count_in_their_own_group_not_in_this_one():
    """The return (30–34) meets the corridor's first pass (0–4) five times, right; twice (30, 31) it also meets the
    second pass (20, 21), 0.6 m off. The 20 keyframes between the passes carry 1.4 dm of translation σ a step, so
    the pairwise test between the two sets passes whatever they say: the wrong pair agrees with every right
    closure without being compared with any. It counts in its own place's group — two keyframes, one short —
    and expires; the five stand. (Before, the clique took all seven.)"""
    W = LoopConfig().group_window_keyframes
    truth = _two_passes_truth()
    rng = np.random.default_rng(11)
    right = _closures(truth, zip(range(5), range(30, 35)), rng)
    wrong = _closures(truth, zip(range(20, 22), range(30, 32)), rng, G.xytheta_to_matrix(0.6, 0.0, 0.0))
    ru = RelativeUncertainty(planar=True)
    for k in range(1, 60):
        ru.add_edge(k - 1, k, np.diag([1e-2, 1e-2, 1e-6]))
    acc = Acceptance(LoopConfig(), True, ru, LoopStats())
    pos = truth[:, :2, 3]
    assert C.vouches(*ru.chain_variance(0, 4, pos), LoopConfig(), True)
    assert not C.vouches(*ru.chain_variance(0, 20, pos), LoopConfig(), True)
    kfs = _keyframes(60)
    assert all(acc.pairwise.consistent(to_closure(a, kfs, True), to_closure(b, kfs, True), truth) for a in right for b in wrong)
    for v in right + wrong:
        acc.consider(v, kfs, _line(60), lambda v: True)
    group = acc.decide(30 + W - 1, truth)
    assert sorted((lc.i, lc.j) for lc in group) == list(zip(range(5), range(30, 35)))
    assert acc.stats.pending_expired == 2 and acc.stats.left_to_their_place == 2
    assert acc.stats.as_dict()["left_to_their_place"] == 2


def test_of_two_rival_groups_at_one_place_the_one_whose_path_fits_better_is_taken():
    """A return along a corridor whose doors repeat: three closures place it right, five (against more old
    keyframes) 2 m along, each set consistent, the two at odds through the short, sure stretch 0–4. The larger
    was taken; now the one whose recent path fits the old place better (the ``fit`` hook, the closer's path
    score) is, and counted. Without a fit, or when the larger fits better, the larger stands."""
    W = LoopConfig().group_window_keyframes
    truth = _corridor_truth()
    est = truth.copy()
    est[30:35] = G.xytheta_to_matrix(2.0, -0.5, np.radians(12)) @ truth[30:35]

    def rivals(rng):
        right = _closures(truth, zip(range(3), range(30, 33)), rng)
        alias = _closures(truth, zip(range(5), range(30, 35)), rng, G.xytheta_to_matrix(2.0, 0.0, 0.0))
        return right, alias

    def is_right(group) -> bool:
        return all(np.linalg.norm(G.relative(G.relative(truth[lc.i], truth[lc.j]), lc.measurement)[:2, 3]) < 0.1
                   for lc in group)

    for fit, expect_right in ((lambda g, P: 0.6 if is_right(g) else 0.5, True),
                              (lambda g, P: 0.5 if is_right(g) else 0.6, False), (None, False)):
        acc = _acceptance(step_cov=1e-5)
        acc.fit = fit
        right, alias = rivals(np.random.default_rng(9))
        for v in right + alias:
            acc.consider(v, _keyframes(60), _line(60), lambda v: True)
        group = acc.decide(30 + W - 1, est)
        assert len(group) == (3 if expect_right else 5) and is_right(group) == expect_right
        assert acc.stats.groups_by_path == int(expect_right)


def test_the_maximum_consistent_set_is_the_maximum_clique():
    """On random consistency graphs the exact search finds a clique as large as brute force does."""
    rng = np.random.default_rng(0)
    acc = _acceptance()
    for trial in range(30):
        n = int(rng.integers(3, 10))
        adj = rng.random((n, n)) < 0.5
        adj = np.triu(adj, 1)
        adj = adj | adj.T
        closures = [LoopClosure(0, 100 + k, np.eye(4), np.eye(3), 1.0, 0.0, "spatial") for k in range(n)]
        index = {id(c): k for k, c in enumerate(closures)}
        acc.pairwise.matrix = lambda cs, P, _adj=adj, _ix=index: np.array(  # type: ignore[method-assign]
            [[a is b or bool(_adj[_ix[id(a)], _ix[id(b)]]) for b in cs] for a in cs])
        got = acc.pairwise.largest_set(closures, np.zeros((1, 4, 4)))
        best = max(len(s) for r in range(1, n + 1) for s in itertools.combinations(range(n), r)
                   if all(adj[a, b] for a, b in itertools.combinations(s, 2)))
        members = [index[id(c)] for c in got]
        assert len(got) == best
        assert all(adj[a, b] for a, b in itertools.combinations(members, 2))


def test_the_consistency_matrix_is_the_pairwise_test():
    """The matrix the clique search reads (relative poses and chain variances computed once per keyframe pair)
    holds exactly what :meth:`PairwiseConsistency.consistent` says of each pair: closures from a few new keyframes to a
    few old ones, with random offsets some of which break the cycle."""
    rng = np.random.default_rng(3)
    acc = _acceptance(K=60, step_cov=1e-4)
    poses = _line(60)
    closures = []
    for _ in range(14):
        i, j = int(rng.integers(0, 6)), int(rng.integers(50, 55))
        T = G.relative(poses[i], poses[j]) @ G.se2_exp(rng.normal(0.0, [0.05, 0.05, 0.01]) * rng.choice([1.0, 20.0]))
        closures.append(LoopClosure(i, j, T, np.diag([1e-4, 1e-4, 1e-5]), 1.0, 0.0, "spatial"))
    ok = acc.pairwise.matrix(closures, poses)
    pairwise = np.array([[a is b or acc.pairwise.consistent(a, b, poses) for b in closures] for a in closures])
    assert np.array_equal(ok, pairwise) and 0 < ok.sum() < ok.size


def test_to_closure_carries_the_alignment_and_its_covariance_through_the_sensor_mounts():
    """i_base_T_j_base = B_i T B_j⁻¹, and the covariance of a right perturbation of T maps by Ad(B_j)."""
    Bi, Bj = G.xytheta_to_matrix(0.3, 0.0, 0.1), G.xytheta_to_matrix(0.3, 0.0, 0.1)
    kfs = _keyframes(40)
    kfs[0].base_T_sensor, kfs[30].base_T_sensor = Bi, Bj
    T = G.xytheta_to_matrix(1.0, 2.0, 0.5)
    cov = np.diag([1e-3, 2e-3, 1e-4])
    lc = to_closure(_verified(0, 30, T, None, None, False, cov), kfs, True)
    assert np.allclose(lc.measurement, Bi @ T @ G.inverse(Bj))
    A = G.adjoint(Bj, planar=True)
    assert np.allclose(lc.covariance, A @ cov @ A.T)
    # Monte Carlo: perturbing T on the right by δ ~ N(0, cov) perturbs the base closure by Ad(B_j) δ, so its
    # normalised squared error under lc.covariance averages 3 (standard error of the mean √(6/n) = 0.04).
    rng = np.random.default_rng(1)
    d = rng.multivariate_normal(np.zeros(3), cov, 4000)
    e = np.array([G.se2_log(G.relative(lc.measurement, Bi @ T @ G.se2_exp(x) @ G.inverse(Bj))) for x in d])
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(lc.covariance, e.T).T)
    assert nees.mean() == pytest.approx(3.0, abs=0.15)
