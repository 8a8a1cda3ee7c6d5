"""The verifier on scans simulated in small worlds: a true revisit is found from a guess off by half a
metre and a few degrees; a wrong place is rejected; a featureless corridor's match is not unique;
negative information sees through walls but not through beams that returned nothing."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as G
from registration import correlative
from slam.loops.config import LoopConfig
from slam.loops.local_map import LocalMaps
from slam.loops.types import Candidate, Rejection, Source, Verified, Window
from slam.loops.verify import Verifier, free_space_violation, free_space_violation_both

from tests.loop_scenes import corridor, corridor_with_bays, keyframes, room


def _path_and_revisit(world, path, revisit):
    """Keyframes along *path* (the first pass) then one at *revisit*; true poses as the estimate."""
    kfs = keyframes(world, list(path) + [revisit], seed=3)
    poses = np.array([kf.odom_pose for kf in kfs])
    return kfs, poses


def _room_pass():
    xs = np.linspace(1.5, 10.5, 19)
    path = [(x, 4.0, 0.0) for x in xs]
    return path


def test_a_true_revisit_is_found_from_a_guess_half_a_metre_and_three_degrees_off():
    path = _room_pass()
    revisit = (5.2, 4.3, np.radians(20.0))  # near keyframe 8 (x = 5.5), seen from another heading
    kfs, poses = _path_and_revisit(room(), path, revisit)
    j, i = len(kfs) - 1, 8
    truth = G.relative(poses[i], poses[j])
    guess = truth @ G.xytheta_to_matrix(0.4, -0.3, np.radians(3.0))
    v = Verifier(LoopConfig(), True, LocalMaps())
    cand = Candidate(i, j, Source.SPATIAL, guess, Window(1.0, np.radians(5.0)), None, False)
    res = v.verify(cand, kfs, poses, 3, v.reference(kfs, poses, j))
    assert isinstance(res, Verified)
    d = G.relative(truth, res.transform)
    assert np.linalg.norm(d[:2, 3]) < 0.03 and abs(G.matrix_to_xytheta(d)[2]) < np.radians(0.3)
    assert v.unique(res, kfs, poses, 3)  # the room's boxes make it unique
    sd = np.sqrt(np.diag(res.covariance))
    assert sd[0] >= LoopConfig().covariance_floor_m and sd[2] >= np.radians(LoopConfig().covariance_floor_deg)


def test_a_wrong_place_is_rejected():
    """The new keyframe stands at the room's east end; the candidate is the west end, guessed as if the same place."""
    path = _room_pass()
    kfs, poses = _path_and_revisit(room(), path, (10.2, 4.2, np.radians(170.0)))
    j = len(kfs) - 1
    v = Verifier(LoopConfig(), True, LocalMaps())
    guess = G.xytheta_to_matrix(0.0, 0.2, np.radians(170.0))
    cand = Candidate(1, j, Source.SPATIAL, guess, Window(1.0, np.radians(5.0)), None, False)
    assert isinstance(v.verify(cand, kfs, poses, 3, v.reference(kfs, poses, j)), Rejection)


def test_a_match_in_a_featureless_corridor_is_verified_but_not_unique():
    """Along a corridor without features every offset along it scores alike: the alignment passes the fit
    tests (it is a corridor), but the acceptance stage could not trust it without the estimate."""
    path = [(x, 1.0, 0.0) for x in np.linspace(5.0, 14.0, 19)]
    kfs, poses = _path_and_revisit(corridor(), path, (9.6, 1.05, np.radians(2.0)))
    j = len(kfs) - 1
    v = Verifier(LoopConfig(), True, LocalMaps())
    truth = G.relative(poses[9], poses[j])
    cand = Candidate(9, j, Source.SPATIAL, truth @ G.xytheta_to_matrix(0.3, 0.0, 0.0), Window(1.0, np.radians(5.0)),
                     None, False)
    res = v.verify(cand, kfs, poses, 3, v.reference(kfs, poses, j))
    assert isinstance(res, Verified)
    assert not v.unique(res, kfs, poses, 3)


def test_a_match_away_from_the_estimate_must_outscore_the_stretch_back_to_it():
    """Bays every 5 m along a corridor: a match one bay along the right pose has no rival within the
    uniqueness radius (three floor windows, ±3 m). When the estimate puts the robot at the right pose, that
    pose lies on the stretch between the match and the estimate and scores as well: not unique. Without an
    estimate, with one at the match itself, in a global search (which looks where the estimate may be
    wrong), or with an estimate turned by more than the heading floor (no guide to the way back), the radius
    alone decides: unique."""
    path = [(x, 1.0, 0.0) for x in np.linspace(20.0, 60.0, 81)]
    kfs, poses = _path_and_revisit(corridor_with_bays(5.0, 80.0), path, (40.1, 1.05, np.radians(1.0)))
    j, i = len(kfs) - 1, 40  # keyframe 40 stands at x = 40
    truth = G.relative(poses[i], poses[j])
    alias = G.xytheta_to_matrix(5.0, 0.0, 0.0) @ truth  # one bay on, along the corridor
    cfg = LoopConfig(correlative_max_range_m=12.0)  # what both placements see lies inside the old pass's map
    v = Verifier(cfg, True, LocalMaps())
    pts = kfs[j].points[np.hypot(kfs[j].points[:, 0], kfs[j].points[:, 1]) <= 12.0]
    pyr = v.maps.pyramid(v.maps.get(kfs, poses, i, 40), cfg.correlative_resolution_m, 6)
    assert correlative.score_at(pts, pyr, alias) > 0.9 * correlative.score_at(pts, pyr, truth)  # a true alias
    cov = np.diag([4.0, 4.0, 0.01])
    off = G.xytheta_to_matrix(0.4, 0.1, np.radians(1.0))  # the estimate a little off the right pose
    # (max_mahalanobis2 set: a search the estimate's covariance does not bound, as the global search marks it)
    turned = G.xytheta_to_matrix(0.4, 0.1, np.radians(10.0))  # an estimate whose heading drifted beyond the floor
    for estimate, bound, unique in ((truth @ off, None, False), (None, None, True), (alias @ off, None, True),
                                    (truth @ off, 16.3, True), (truth @ turned, None, True)):
        # a window of ±4 m round the match: the right pose, 5 m away, lies outside what was searched
        cand = Candidate(i, j, Source.SPATIAL, alias, Window(4.0, np.radians(5.0)),
                         None if estimate is None else (estimate, cov), False, max_mahalanobis2=bound)
        assert v.unique(Verified(cand, alias, np.eye(3) * 1e-4, 0.9, 0.02, 0.8, 40), kfs, poses, 40) is unique


def test_a_match_is_not_unique_when_its_own_search_window_holds_a_rival():
    """The same bays: a search window of ±8 m round the guess holds both the alias it returned and the right
    pose one bay back, beyond the ±3 m uniqueness box round the match. Every pose of a window the estimate's
    uncertainty sized is as likely a priori, so the near-tie there makes the match ambiguous — with an
    estimate that gives no guide back (none, at the match, or turned past the heading floor) too. A global
    search (max_mahalanobis2 set) is held to the estimate afterwards, and a window that the bays' period does
    not fit into (±4 m) holds no rival."""
    path = [(x, 1.0, 0.0) for x in np.linspace(20.0, 60.0, 81)]
    kfs, poses = _path_and_revisit(corridor_with_bays(5.0, 80.0), path, (40.1, 1.05, np.radians(1.0)))
    j, i = len(kfs) - 1, 40
    truth = G.relative(poses[i], poses[j])
    alias = G.xytheta_to_matrix(5.0, 0.0, 0.0) @ truth
    v = Verifier(LoopConfig(correlative_max_range_m=12.0), True, LocalMaps())
    cov = np.diag([4.0, 4.0, 0.01])
    turned = G.xytheta_to_matrix(0.4, 0.1, np.radians(10.0))
    guess = alias @ G.xytheta_to_matrix(-1.0, 0.0, 0.0)  # where the search was centred: between the two
    for estimate, bound, window, unique in ((None, None, 8.0, False), (alias, None, 8.0, False),
                                            (truth @ turned, None, 8.0, False), (None, 16.3, 8.0, True),
                                            (None, None, 3.5, True)):
        cand = Candidate(i, j, Source.SPATIAL, guess, Window(window, np.radians(5.0)),
                         None if estimate is None else (estimate, cov), False, max_mahalanobis2=bound)
        assert v.unique(Verified(cand, alias, np.eye(3) * 1e-4, 0.9, 0.02, 0.8, 40), kfs, poses, 40) is unique


def test_best_elsewhere_is_the_brute_force_maximum_outside_the_excluded_neighbourhood():
    rng = np.random.default_rng(2)
    kfs = keyframes(room(), [(4.0, 3.0, 0.3), (4.5, 3.2, 0.2)], seed=1)
    pyr = correlative.LikelihoodPyramid(kfs[0].points, 0.1, 0.1, levels=4)
    pts = kfs[1].points
    guess = G.xytheta_to_matrix(*(G.matrix_to_xytheta(G.relative(kfs[0].odom_pose, kfs[1].odom_pose))
                                  + rng.normal(0, [0.1, 0.1, 0.02])))
    win, win_th = 0.6, np.radians(4.0)
    best = correlative.match(pts, pyr, guess, win, win_th)
    g = correlative.search_grid(pts, pyr, guess, win, win_th)
    ex_m, ex_rad = 0.25, np.radians(1.5)
    scores = []
    for r, th in enumerate(g.thetas):
        for ox in range(-g.w, g.w + 1):
            for oy in range(-g.w, g.w + 1):
                T = G.xytheta_to_matrix(g.x0 + ox * 0.1, g.y0 + oy * 0.1, th)
                dx, dy = T[0, 3] - best.transform[0, 3], T[1, 3] - best.transform[1, 3]
                step = g.thetas[1] - g.thetas[0]
                r_best = int(round((G.matrix_to_xytheta(best.transform)[2] - g.thetas[0]) / step))
                if abs(r - r_best) <= int(np.ceil(ex_rad / step)) and max(abs(dx), abs(dy)) <= int(np.ceil(ex_m / 0.1)) * 0.1 + 1e-9:
                    continue
                scores.append(correlative.score_at(pts, pyr, T))
    got = correlative.best_elsewhere(pts, pyr, guess, win, win_th, best.transform, ex_m, ex_rad, 0.0)
    assert got == pytest.approx(max(scores), abs=1e-9)
    assert correlative.best_elsewhere(pts, pyr, guess, win, win_th, best.transform, ex_m, ex_rad, 1.01) is None
    # Stopping at the first pose above the bar answers "is there one?" exactly as the full search does, at
    # every bar, and the score it stops at is one of the poses' and above the bar.
    for bar in np.quantile(scores, [0.0, 0.5, 0.9, 0.99]).tolist() + [max(scores), max(scores) + 1e-3]:
        first = correlative.best_elsewhere(pts, pyr, guess, win, win_th, best.transform, ex_m, ex_rad, bar, first=True)
        full = correlative.best_elsewhere(pts, pyr, guess, win, win_th, best.transform, ex_m, ex_rad, bar)
        assert (first is None) == (full is None) == (max(scores) <= bar - 1e-12)
        if first is not None:
            assert bar - 1e-12 < first <= full + 1e-12
            assert min(abs(np.array(scores) - first)) < 1e-9


def test_negative_information_sees_through_walls_but_not_through_beams_that_returned_nothing():
    kfs = keyframes(room(), [(6.0, 4.0, 0.0), (6.0, 4.0, 0.0)], seed=5)
    a, b = kfs
    assert free_space_violation(b.frame.points, a) < 0.02  # the same place: consistent
    moved = G.transform_points(G.xytheta_to_matrix(-1.0, 0.0, 0.0), b.frame.points)
    assert free_space_violation(moved, a) > 0.1  # the east wall pulled 1 m into the room
    # A beam that returned nothing says nothing: with every beam dropped, no point is contradicted.
    blind = type(a)(a.id, a.scan_index, a.stamp, a.odom_pose, a.base_T_sensor, a.points,
                    type(a.frame)(a.frame.stamp, a.frame.points, 0, a.frame.angles, np.full_like(a.frame.ranges, np.inf),
                                  np.ones_like(a.frame.no_return), max_range=30.0))
    assert free_space_violation(moved, blind) == 0.0
    # Beams left out by a reader (angles not uniform) leave their points unjudged, not misjudged.
    keep = np.ones(len(a.frame.angles), dtype=bool)
    keep[::2] = False
    sparse = type(a.frame)(a.frame.stamp, a.frame.points, 0, a.frame.angles[keep], a.frame.ranges[keep],
                           a.frame.no_return[keep], max_range=30.0)
    ka = type(a)(a.id, a.scan_index, a.stamp, a.odom_pose, a.base_T_sensor, a.points, sparse)
    assert free_space_violation(b.frame.points, ka) < 0.02
    assert free_space_violation(moved, ka) > 0.1
    assert free_space_violation_both(np.eye(4), b, a) < 0.02


def test_the_backward_check_of_a_true_closure_closes():
    """Keyframe i's scan aligned onto the new keyframe's own local map lands where the closure says."""
    path = _room_pass()
    kfs, poses = _path_and_revisit(room(), path, (5.4, 4.1, np.radians(10.0)))
    j = len(kfs) - 1
    v = Verifier(LoopConfig(), True, LocalMaps())
    ref = v.reference(kfs, poses, j)
    truth = G.relative(poses[8], poses[j])
    d = v.backward(truth, kfs[8], ref)
    assert np.linalg.norm(d[:2, 3]) < 0.03 and abs(G.matrix_to_xytheta(d)[2]) < np.radians(0.3)
    wrong = truth @ G.xytheta_to_matrix(0.0, 0.0, np.radians(2.0))
    d2 = v.backward(wrong, kfs[8], ref)
    assert abs(G.matrix_to_xytheta(d2)[2]) > np.radians(1.5)  # the scans disagree with a 2° error
