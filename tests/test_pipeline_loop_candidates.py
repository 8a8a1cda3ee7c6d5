"""Loop candidates and their search windows sized by each keyframe's uncertainty relative to the new one."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from registration import geometry as G
from slam.pipeline.config import LoopConfig
from slam.pipeline.loop_closure import LoopCloser
from slam.pipeline.uncertainty import NodeUncertainty


def _scene():
    """Keyframe 99 at the origin; keyframes 50–70 (a recent pass) 0.3–1.3 m away and well linked;
    keyframes 5–10 (the first pass) 9–10 m away and linked only through a long chain."""
    K = 100
    pos = np.full((K, 3), 50.0)
    pos[99] = pos[50:71] = pos[5:11] = 0.0
    pos[50:71, 0] = np.linspace(0.3, 1.3, 21)
    pos[5:11, 1] = np.linspace(9.0, 10.0, 6)
    var = np.full(K, 1e-4)
    var[:40] = 9.0  # σ = 3 m
    return pos, NodeUncertainty(var, np.full(K, 1e-4))


def test_graph_far_keyframes_get_their_own_candidate_slot_and_a_wider_radius():
    cfg = LoopConfig()
    closer = LoopCloser(cfg, planar=True)
    pos, unc = _scene()
    radii = closer.search_radii(unc)
    assert radii[60] == cfg.search_radius_m + cfg.radius_sigma_factor * 0.01
    assert radii[5] == min(cfg.far_max_radius_m, cfg.search_radius_m + cfg.radius_sigma_factor * 3.0)
    far = np.sqrt(unc.position_var) > cfg.far_sigma_m
    kf = SimpleNamespace(id=99)
    chosen = closer.spatial_candidates(kf, pos, radii, far)
    near_part, far_part = chosen[: cfg.max_candidates], chosen[cfg.max_candidates:]
    assert len(near_part) == cfg.max_candidates and all(50 <= i <= 70 for i in near_part)
    assert far_part == [5]  # the nearest of the first pass
    # Without the far pool the first pass is crowded out by the recent one.
    assert all(50 <= i <= 70 for i in closer.spatial_candidates(kf, pos, radii))
    # With the old fixed cap (max_radius_m) the first pass would not even be in range.
    assert 5 not in closer.spatial_candidates(kf, pos, np.minimum(radii, cfg.max_radius_m), far)


def test_correlative_window_follows_the_relative_uncertainty_within_its_caps():
    cfg = LoopConfig()
    closer = LoopCloser(cfg, planar=True)
    deg = np.radians
    # Well-linked: the configured window.
    w, r = closer._window("spatial", np.diag([1e-4, 1e-4, 1e-6]))
    assert w == cfg.correlative_window_m and r == deg(cfg.correlative_window_deg)
    # Uncertain in heading (7°), not in position: 3σ in heading only.
    w, r = closer._window("spatial", np.diag([0.1, 0.1, deg(7.0) ** 2]))
    assert w == cfg.correlative_window_m and np.isclose(r, deg(21.0))
    # Graph-far (σ 1.2 m per axis): 3σ in translation.
    w, r = closer._window("spatial", np.diag([1.44, 1.44, 1e-6]))
    assert np.isclose(w, 3.6) and r == deg(cfg.correlative_window_deg)
    # Graph-far and very uncertain: capped at the far radius and the angular maximum.
    w, r = closer._window("spatial", np.diag([50.0, 50.0, 1.0]))
    assert w == cfg.far_max_radius_m and r == deg(cfg.correlative_max_window_deg)
    # Descriptor candidates keep their own window.
    assert closer._window("descriptor", None) == (cfg.descriptor_window_m, deg(cfg.descriptor_window_deg))


def _return_after_drift(rng, drift, loop: bool = True):
    """True poses of old keyframes 0–4 and new ones 30–34 (a revisit of the same corridor stretch); with
    *loop*, keyframes 5–29 go round a 10 m-radius circle (a 63 m loop), else they pace 6 m along the
    corridor and back. The estimate has the new ones moved by *drift* (the loop's accumulated error), and closures
    measured from the truth with 1 cm / 0.1° noise."""
    from slam.pipeline.loop_closure import LoopClosure

    truth = np.array([G.xytheta_to_matrix(0.5 * k, 0.0, 0.0) for k in range(40)])
    if loop:
        a = np.linspace(-np.pi / 2, 1.5 * np.pi, 27)[1:-1]  # 25 keyframes round the circle
        truth[5:30] = [G.xytheta_to_matrix(2.5 + 10 * np.cos(t), 10 + 10 * np.sin(t), t + np.pi / 2) for t in a]
    else:
        xs = np.concatenate([2.5 + 0.5 * np.arange(1, 13), 8.5 - 0.5 * np.arange(1, 14)])
        truth[5:30] = [G.xytheta_to_matrix(x, 0.0, 0.0 if k < 12 else np.pi) for k, x in enumerate(xs)]
    truth[30:35] = [G.xytheta_to_matrix(0.5 * (k - 30) + 0.2, 0.3, 0.05) for k in range(30, 35)]
    est = truth.copy()
    est[30:35] = drift @ truth[30:35]
    closures = []
    for j, i in zip(range(30, 35), range(0, 5)):
        noise = G.xytheta_to_matrix(*rng.normal(0, [0.01, 0.01, np.radians(0.1)]))
        closures.append(LoopClosure(i, j, G.relative(truth[i], truth[j]) @ noise, np.eye(3) * 1e-4, 0.9, 0.02, "spatial"))
    return est, closures


def test_closures_that_agree_with_each_other_but_not_the_drifted_estimate_are_accepted_together():
    """After a 2 m / 12° drift every closure of the return fails the test against the estimate; as a
    group they agree (their cycles through the estimate's local relative poses close), so they are
    accepted once three keyframes have one, and not before."""

    rng = np.random.default_rng(4)
    est, closures = _return_after_drift(rng, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)))
    closer = LoopCloser(LoopConfig(), planar=True)
    D = LoopConfig().group_delay_keyframes
    closer._pending = closures[:2]
    assert closer._consistent_group(est, 31 + D) == []
    closer._pending = closures[:3]
    assert closer._consistent_group(est, 32 + D - 1) == []  # the newest member is not group_delay_keyframes old yet
    group = closer._consistent_group(est, 32 + D)
    assert sorted(lc.j for lc in group) == [30, 31, 32]
    assert closer._pending == [] and closer.stats.accepted_as_group == 3


def test_closures_that_disagree_with_each_other_are_not_accepted():
    """Three closures each off by its own wrong corridor slide (0.5 m apart) form no group."""

    rng = np.random.default_rng(5)
    est, closures = _return_after_drift(rng, G.xytheta_to_matrix(2.0, -0.5, np.radians(12)))
    for k, lc in enumerate(closures[:3]):
        lc.measurement = lc.measurement @ G.xytheta_to_matrix(0.5 * k, 0.0, 0.0)
    closer = LoopCloser(LoopConfig(), planar=True)
    closer._pending = closures[:3]
    assert closer._consistent_group(est, 32 + closer.config.group_delay_keyframes) == []


def test_a_group_waits_so_that_a_later_closure_accepted_on_its_own_can_contradict_it():
    """MIT CSAIL's alias: keyframes 30–32 offer a group (the drifted return) while the next keyframe, 33, closes on
    its own with old keyframe 3 exactly as the estimate has it. Without the delay the group is accepted at 32,
    before 33 is seen; with it the group is still pending at 33 and refused at 35. Without keyframe 33's closure
    the same group is accepted at 35."""
    from slam.pipeline.loop_closure import LoopClosure

    est, closures = _return_after_drift(np.random.default_rng(4), G.xytheta_to_matrix(2.0, -0.5, np.radians(12)))
    alone = LoopClosure(3, 33, G.relative(est[3], est[33]), np.eye(3) * 1e-4, 0.9, 0.02, "spatial")
    eager = LoopCloser(LoopConfig(group_delay_keyframes=0), planar=True)
    eager._pending = closures[:3]
    assert len(eager._consistent_group(est, 32)) == 3
    for contradicted in (True, False):
        closer = LoopCloser(LoopConfig(group_delay_keyframes=3), planar=True)
        closer._pending = closures[:3]
        assert closer._consistent_group(est, 32) == [] and closer._consistent_group(est, 33) == []
        closer._recent = [alone] if contradicted else []
        assert len(closer._consistent_group(est, 35)) == (0 if contradicted else 3)
        assert closer.stats.groups_contradicted == int(contradicted)


def test_information_gain_is_the_gaussian_mutual_information_at_the_covariance_floor():
    """½ log det(I + Σ_rel Σ_floor⁻¹) with Σ_rel split evenly over the axes: the mutual information of a
    closure with noise Σ_floor about a relative pose with prior Σ_rel; 0 for a pose already known exactly."""
    rng = np.random.default_rng(0)
    for planar, d, r in ((True, 2, 1), (False, 3, 3)):
        cfg = LoopConfig(covariance_floor_m=0.02, covariance_floor_rad=0.01)
        pv, rv = rng.uniform(0, 0.5, 6), rng.uniform(0, 0.05, 6)
        pv[0] = rv[0] = 0.0
        gain = LoopCloser(cfg, planar).information_gain(NodeUncertainty(pv, rv))
        for k in range(6):
            P = np.diag([pv[k] / d] * d + [rv[k] / r] * r)
            R = np.diag([0.02**2] * d + [0.01**2] * r)
            assert np.isclose(gain[k], 0.5 * np.linalg.slogdet(np.eye(d + r) + P @ np.linalg.inv(R))[1])
        assert gain[0] == 0.0


def test_candidates_the_graph_already_ties_closely_are_not_verified():
    """With min_information_gain, the recent pass (σ 1 cm relative to the new keyframe) is skipped and
    counted; the first pass (σ 3 m) is still verified."""

    pos, unc = _scene()
    poses = np.array([G.xytheta_to_matrix(x, y, 0.0) for x, y, _ in pos])
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 2))) for k in range(100)]
    for gain, expect_recent in ((0.0, True), (3.0, False)):
        closer = LoopCloser(LoopConfig(min_information_gain=gain, use_descriptor=False), planar=True)
        verified: list[int] = []
        closer.verify = lambda kfs, P, i, j, *a, **k: verified.append(i)  # type: ignore[method-assign]
        closer.detect(keyframes, poses, 99, unc)
        assert 5 in verified
        assert any(50 <= i <= 70 for i in verified) == expect_recent
        assert closer.stats.skipped_low_gain == (0 if expect_recent else closer.stats.candidates - len(verified))


def test_descriptor_closure_far_from_a_confident_estimate_is_rejected_and_not_pooled():
    """A descriptor match (an aliased corridor 9 m along, as on the hospital log) against a graph sure to
    5 cm where the two keyframes are: rejected as inconsistent and kept out of the group pool, while the
    same match is accepted when the estimate agrees, when the estimate's uncertainty covers the 9 m, or
    with the check off. (3D keyframes: the ICP result is stubbed, so there are no scans to check for free
    space; the test is the gate's arithmetic.)"""

    T = G.se3_exp([0.1, 0.0, 0.0, 0.0, 0.0, 0.02])  # what ICP found: j almost on top of i
    res = SimpleNamespace(converged=True, accepted=True, fitness=0.9, rmse=0.01, degenerate=False,
                          transform=T, covariance=np.diag([1e-4] * 3 + [1e-6] * 3))  # 1 cm, 0.06°
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 3))) for k in range(2)]
    far_off = G.se3_exp([9.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    sure, unsure = np.eye(6) * 0.05**2, np.diag([30.0] * 3 + [0.1] * 3)
    for estimate, limit, accepted in (((far_off, sure), 15.0, False), ((T, sure), 15.0, True),
                                      ((far_off, unsure), 15.0, True), ((far_off, sure), None, True)):
        closer = LoopCloser(LoopConfig(descriptor_max_mahalanobis=limit), planar=False)
        closer._align = lambda *a, **k: res  # type: ignore[method-assign]
        lc, reason = closer._attempt(keyframes, 0, 1, None, T, np.eye(4), None, "descriptor", estimate)
        assert (lc is not None) == accepted
        if not accepted:
            assert reason == "rejected_consistency" and closer._pending == []


def test_closure_whose_rotation_the_scans_barely_constrain_is_rejected():
    """The rotation-σ gate reads the ICP covariance's rotation block only, by its largest axis: a match
    with σ_θ = 0.3° fails a 0.2° limit whatever its translation σ, one with 0.05° passes even with a
    metre of translation σ, and without a limit both pass. The ICP result is stubbed (3D, no scans)."""
    T = np.eye(4)
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 3))) for k in range(2)]

    def result(rot_sigma_deg: float, trans_sigma_m: float):
        # A rotated rotation block: the gate must not depend on the axes the covariance is expressed in.
        R = G.so3_exp([0.3, -0.2, 0.5])
        rot = R @ np.diag([np.radians(rot_sigma_deg) ** 2, 1e-12, 1e-12]) @ R.T
        cov = np.zeros((6, 6))
        cov[:3, :3], cov[3:, 3:] = np.eye(3) * trans_sigma_m**2, rot
        return SimpleNamespace(converged=True, accepted=True, fitness=0.9, rmse=0.01, degenerate=False,
                               transform=T, covariance=cov)

    for limit, rot_sd, trans_sd, accepted in ((0.2, 0.3, 0.001, False), (0.2, 0.05, 1.0, True),
                                              (0.2, 0.19, 0.0, True), (None, 0.3, 0.001, True)):
        closer = LoopCloser(LoopConfig(max_rotation_sigma_deg=limit), planar=False)
        closer._align = lambda *a, _r=result(rot_sd, trans_sd), **k: _r  # type: ignore[method-assign]
        lc, reason = closer._attempt(keyframes, 0, 1, None, T, np.eye(4), None, "spatial")
        assert (lc is not None) == accepted, (limit, rot_sd, trans_sd)
        if not accepted:
            assert reason == "rejected_heading_sigma"


def test_a_group_implying_implausible_drift_is_not_accepted():
    """The 2 m / 12° return of the test above, after a 63 m loop (3 % drift): a group. The same mutually
    consistent closures after pacing 6 m of corridor and back (an aliased, door-periodic corridor; > 10 %): no
    group, unless the drift check is off."""
    for loop, limit, expect in ((True, 0.05, 3), (False, 0.05, 0), (False, None, 3)):
        est, closures = _return_after_drift(np.random.default_rng(4), G.xytheta_to_matrix(2.0, -0.5, np.radians(12)), loop)
        closer = LoopCloser(LoopConfig(group_max_drift_fraction=limit), planar=True)
        drift = [closer._implied_drift(est, lc) for lc in closures[:3]]
        assert all((0.02 < d < 0.05) if loop else (d > 0.1) for d in drift), drift
        closer._pending = closures[:3]
        assert len(closer._consistent_group(est, 32 + closer.config.group_delay_keyframes)) == expect


def test_a_group_contradicted_by_a_nearby_closure_accepted_on_its_own_is_not_accepted():
    """The drifted return's group, once a closure between the same stretches (old keyframe 5, new 31)
    has been accepted on its own as the estimate has it: the estimate is right there, so the group is
    an alias and is refused (its members leave the pool). A closure accepted elsewhere (old keyframe 20,
    outside the group window of every member) leaves the group alone."""
    from slam.pipeline.loop_closure import LoopClosure

    for i_alone, expect in ((5, 0), (20, 3)):
        est, closures = _return_after_drift(np.random.default_rng(4), G.xytheta_to_matrix(2.0, -0.5, np.radians(12)))
        odd = closures[3]  # a pooled closure that agrees with none of the group
        odd.measurement = odd.measurement @ G.xytheta_to_matrix(0.5, 0.0, 0.0)
        closer = LoopCloser(LoopConfig(), planar=True)
        closer._pending = closures[:4]
        closer._recent = [LoopClosure(i_alone, 31, G.relative(est[i_alone], est[31]), np.eye(3) * 1e-4, 0.9, 0.02, "spatial")]
        assert len(closer._consistent_group(est, 33 + closer.config.group_delay_keyframes)) == expect
        assert closer.stats.groups_contradicted == (expect == 0)
        # Accepted: the pool is emptied. Refused: only the group's members leave it.
        assert closer._pending == ([] if expect else [odd])


def test_global_search_looks_only_at_anchor_places_beyond_the_far_search():
    """Places for the global search: every far_submap_keyframes-th keyframe older than the exclusion
    window, whose position σ relative to the new keyframe exceeds global_min_sigma_m and whose estimate
    lies within base + factor·σ (≤ global_max_radius_m). The hospital's return: 45 m off with σ 24 m."""
    cfg = LoopConfig()
    closer = LoopCloser(cfg, planar=True)
    K, j, stride = 400, 399, cfg.far_submap_keyframes
    poses = np.tile(np.eye(4), (K, 1, 1))
    var = np.full(K, 1e-4)
    cases = {  # anchor: (distance from keyframe j (m), σ (m), expected)
        0: (45.0, 24.0, True),    # the hospital's return
        25: (45.0, 2.0, False),   # confident estimate: 45 m is out of reach
        50: (3.0, 0.5, False),    # graph-near: the spatial search's
        75: (10.0, 3.0, False),   # within the far search (σ below global_min_sigma_m)
        100: (90.0, 40.0, True),
        125: (150.0, 80.0, False),  # beyond global_max_radius_m
    }
    for i, (d, sd, _) in cases.items():
        poses[i, 0, 3] = d
        var[i] = sd**2
    poses[26, 0, 3], var[26] = 45.0, 24.0**2  # not an anchor
    poses[390, 0, 3], var[390] = 45.0, 24.0**2  # recent (and not an anchor)
    poses[375, 0, 3], var[375] = 20.0, 24.0**2  # the youngest anchor older than the exclusion window (≤ 384)
    unc = NodeUncertainty(var, np.full(K, 1e-4))
    got = set(closer.global_places(poses, j, unc).tolist())
    assert got == {i for i, (_, _, ok) in cases.items() if ok} | {375}
    assert all(i % stride == 0 and i <= j - cfg.exclude_recent_keyframes for i in got)
    assert closer.global_places(poses, 10, unc).size == 0  # nothing older than the window


def test_a_spatial_closure_the_estimate_cannot_vouch_for_is_held_like_a_global_one():
    """A spatial candidate whose position σ relative to the new keyframe exceeds global_min_sigma_m passes the
    consistency test with almost any alignment; its closure is held as a global hypothesis instead of being
    accepted alone. The same closure at σ below the limit, agreeing with the estimate, is accepted."""
    poses = np.array([G.se3_exp([1.0 * k, 0.0, 0.0, 0.0, 0.0, 0.0]) for k in range(40)])
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 3))) for k in range(40)]
    T = G.relative(poses[0], poses[30])
    res = SimpleNamespace(converged=True, accepted=True, fitness=0.9, rmse=0.01, degenerate=False,
                          transform=T, covariance=np.diag([1e-4] * 3 + [1e-6] * 3))
    for sigma, accepted in ((1.0, True), (5.0, False)):
        closer = LoopCloser(LoopConfig(), planar=False)
        closer._align = lambda *a, **k: res  # type: ignore[method-assign]
        rel_cov = np.diag([sigma**2 / 3] * 3 + [1e-4] * 3)  # trace of the position block = σ²
        lc, reason = closer._attempt(keyframes, 0, 30, None, T, T, rel_cov, "spatial")
        assert (lc is not None) == accepted
        if not accepted:
            assert reason == "global_pending" and [(h.i, h.j) for h in closer._hypotheses] == [(0, 30)]
            assert [p.source for p in closer._pending] == ["global"]


def test_a_global_closure_is_never_accepted_alone_only_as_a_group_that_agrees():
    """A global-search closure passing every test is held back (and becomes a hypothesis); three of them
    from consecutive keyframes that agree with each other — the same 30 m / 20° correction of the
    estimate — are accepted together; three that disagree are not. ICP is stubbed (3D, no scans)."""
    K = 40
    poses = np.array([G.se3_exp([1.0 * k, 0.0, 0.0, 0.0, 0.0, 0.01 * k]) for k in range(K)])
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 3))) for k in range(K)]
    correction = G.se3_exp([30.0, -12.0, 0.0, 0.0, 0.0, np.radians(20.0)])

    def run(offsets):
        closer = LoopCloser(LoopConfig(group_max_drift_fraction=None), planar=False)
        for j, off in zip((30, 31, 32), offsets):
            T = correction @ G.relative(poses[0], poses[j]) @ off
            res = SimpleNamespace(converged=True, accepted=True, fitness=0.9, rmse=0.01, degenerate=False,
                                  transform=T, covariance=np.diag([1e-4] * 3 + [1e-6] * 3))
            closer._align = lambda *a, _r=res, **k: _r  # type: ignore[method-assign]
            lc, reason = closer._attempt(keyframes, 0, j, None, T, T, None, "global")
            assert lc is None and reason == "global_pending"
            assert [(h.i, h.j) for h in closer._hypotheses] == [(0, j)]  # the latest renews the hypothesis
        return closer._consistent_group(poses, 32 + closer.config.group_delay_keyframes)

    agreeing = run([np.eye(4)] * 3)
    assert sorted(lc.j for lc in agreeing) == [30, 31, 32] and all(lc.source == "global" for lc in agreeing)
    assert run([np.eye(4), G.se3_exp([1.5, 0.0, 0, 0, 0, 0]), G.se3_exp([0, 0, 0, 0, 0, 0.2])]) == []


def test_a_keyframe_that_closed_nothing_retries_old_opposite_views_against_their_larger_map_and_holds_them():
    """When no closure came out, the spatial candidates seen from the opposite direction (relative heading
    beyond 90°) that are old enough are verified again against their ±far_submap_keyframes map, with
    hold=True (a closure only in a group); same-direction, too-recent or graph-far ones are not, and nothing
    is retried when a closure was accepted."""
    K = 400
    pos = np.zeros((K, 2))
    pos[:, 0] = 100.0 + np.arange(K)  # elsewhere, well apart
    heading = np.zeros(K)
    for k, (x, th) in {10: (0.2, np.pi), 20: (0.4, 0.1), 350: (0.6, np.pi), 30: (0.8, np.pi)}.items():
        pos[k] = (x, 0.0)
        heading[k] = th
    pos[399] = 0.0
    poses = np.array([G.xytheta_to_matrix(x, y, th) for (x, y), th in zip(pos, heading)])
    var = np.full(K, 1e-4)
    var[30] = 4.0  # graph-far: the far search already used its large map
    unc = NodeUncertainty(var, np.full(K, 1e-4))
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 2))) for k in range(K)]
    for accept_first, expect in ((False, [(10, True)]), (True, [])):
        closer = LoopCloser(LoopConfig(use_descriptor=False, global_search=False), planar=True)
        calls: list[tuple[int, bool, bool]] = []

        def verify(kfs, P, i, j, guess, cov, source, far=False, estimate=None, hold=False, _acc=accept_first):
            calls.append((i, bool(far), bool(hold)))
            return SimpleNamespace(i=i, j=j, source=source) if (_acc and not hold and i == 20) else None

        closer.verify = verify  # type: ignore[method-assign]
        closer._consistent_group = lambda P, j: []  # type: ignore[method-assign]
        closer.detect(keyframes, poses, 399, unc)
        first = [c for c in calls if not c[2]]
        assert sorted(i for i, _, _ in first) == [10, 20, 30, 350]  # the usual pass, each candidate once
        assert [(i, far) for i, far, hold in calls if hold] == expect  # 20 same way, 350 recent, 30 graph-far


def test_a_held_closure_waits_for_a_group_and_an_inconsistent_one_is_not_held():
    """verify(hold=True): a closure passing every test is pending, not returned or counted as accepted; one
    failing the consistency test with the estimate (opposite_max_mahalanobis, or a turn of its relative
    heading beyond opposite_max_heading_deg) is dropped, not pooled (the retry vouches for nothing the
    estimate rules out)."""
    poses = np.array([G.se3_exp([1.0 * k, 0.0, 0.0, 0.0, 0.0, 0.0]) for k in range(40)])
    keyframes = [SimpleNamespace(id=k, base_T_sensor=np.eye(4), points=np.zeros((0, 3))) for k in range(40)]
    T = G.relative(poses[0], poses[30])
    sure, loose_heading = np.diag([0.1**2] * 3 + [1e-4] * 3), np.diag([0.1**2] * 3 + [np.radians(5.0)**2] * 3)
    turned = T @ G.se3_exp([0, 0, 0, 0, 0, np.radians(3.0)])  # within 1 σ of the heading, beyond 1.5°
    for found, rel_cov, pooled in ((T, sure, True), (T @ G.se3_exp([3.0, 0, 0, 0, 0, 0]), sure, False),
                                   (turned, loose_heading, False)):
        res = SimpleNamespace(converged=True, accepted=True, fitness=0.9, rmse=0.01, degenerate=False,
                              transform=found, covariance=np.diag([1e-4] * 3 + [1e-6] * 3))
        closer = LoopCloser(LoopConfig(), planar=False)
        closer._align = lambda *a, _r=res, **k: _r  # type: ignore[method-assign]
        closer._target = lambda *a, **k: (None, None)  # type: ignore[method-assign]
        assert closer.verify(keyframes, poses, 0, 30, T, rel_cov, "spatial", far=True, hold=True) is None
        assert closer.stats.accepted == 0
        assert [(lc.i, lc.j) for lc in closer._pending] == ([(0, 30)] if pooled else [])
        assert closer.stats.opposite_pending == int(pooled) and closer.stats.rejected_consistency == int(not pooled)
