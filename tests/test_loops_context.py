"""The group's last word (slam/loops/context.py): the recent path, matched as a whole on the old place."""

from __future__ import annotations

import numpy as np

from core import geometry as G
from slam.loops.config import LoopConfig
from registration import correlative
from slam.loops.context import context_agrees, path_overrules, path_unique
from slam.loops.types import LoopClosure

from tests.loop_scenes import bays_round_a_corner, keyframes


def _route(east_to: float) -> list[tuple[float, float, float]]:
    """Down the side corridor heading south, round the corner, east along the bays to *east_to* (0.5 m steps)."""
    down = [(1.0, y, -np.pi / 2) for y in np.arange(18.0, 1.0, -0.5)]
    turn = [(1.0, 1.0, -np.pi / 4)]
    east = [(x, 1.0, 0.0) for x in np.arange(1.5, east_to + 1e-9, 0.5)]
    return down + turn + east


def _scene(world=None, old_to: float = 36.0, new_to: float = 14.0):
    """An old pass round the corner and east to *old_to*, a new one to *new_to* (keyframes, true poses, the
    cumulative path in m, the old pass's (x, y, θ))."""
    world = bays_round_a_corner() if world is None else world
    old_xyt, new_xyt = _route(old_to), _route(new_to)
    kfs = keyframes(world, old_xyt, seed=1) + keyframes(world, new_xyt, seed=2, first_id=len(old_xyt))
    poses = np.array([k.odom_pose for k in kfs])
    step = np.r_[0.0, np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1)]
    step[len(old_xyt)] = 50.0  # the robot went elsewhere between the passes
    return kfs, poses, np.cumsum(step), np.array(old_xyt)


def _group(kfs, poses, old_xyt, shift_m: float) -> list[LoopClosure]:
    """Closures of the last three keyframes, each to the old keyframe 5 m farther east, that place the new
    keyframe *shift_m* east of where it is (0: the truth; 5: the bays' alias, where each scan fits as well)."""
    out = []
    for j in range(len(kfs) - 3, len(kfs)):
        x = poses[j][0, 3] + 5.0
        i = int(np.argmin(np.hypot(old_xyt[:, 0] - x, old_xyt[:, 1] - 1.0)))
        claimed = G.xytheta_to_matrix(poses[j][0, 3] + shift_m, poses[j][1, 3], 0.0)
        out.append(LoopClosure(i, j, G.relative(poses[i], claimed), np.eye(3) * 1e-4, 0.9, 0.02, "spatial", True))
    return out


def test_a_group_along_repeating_bays_stands_only_where_the_way_in_fits_too():
    """A return along a corridor of bays every 5 m, entered round the same corner as the old pass. A group that
    puts it 5 m along (each scan fits the bays there as well as at the truth) is refused: the 20 m of path that
    led there, matched as one cloud on the old place, fits best 5 m back, where its corner meets the old
    corner. The group at the truth stands; with the test off, so does the alias."""
    kfs, poses, path, old_xyt = _scene()
    cfg = LoopConfig()
    assert context_agrees(_group(kfs, poses, old_xyt, 0.0), kfs, poses, path, cfg)
    assert not context_agrees(_group(kfs, poses, old_xyt, 5.0), kfs, poses, path, cfg)
    assert context_agrees(_group(kfs, poses, old_xyt, 0.3), kfs, poses, path, cfg)  # within a floor window
    off = cfg.model_copy(update={"group_context_path_m": None})
    assert context_agrees(_group(kfs, poses, old_xyt, 5.0), kfs, poses, path, off)


def test_a_group_is_refused_where_the_estimates_own_placement_fits_its_path_better():
    """The estimate and the group are two hypotheses about where the recent path lies; the path decides. With the
    ratio test made toothless (any pose within 1 % of the best passes it), the bays' alias 5 m along is still
    refused when the estimate is right, since the path fits better where the estimate puts it; the group at the
    truth stands when the estimate has drifted 2 m along the corridor, since the drifted placement fits worse."""
    kfs, poses, path, old_xyt = _scene()
    lenient = LoopConfig(ambiguity_ratio=0.01)
    assert not context_agrees(_group(kfs, poses, old_xyt, 5.0), kfs, poses, path, lenient)
    assert not context_agrees(_group(kfs, poses, old_xyt, 5.0), kfs, poses, path, lenient, min_score=2.0)  # no abstaining
    assert context_agrees(_group(kfs, poses, old_xyt, 0.0), kfs, poses, path, lenient)
    drifted = poses.copy()
    n_old = len(old_xyt)
    drifted[n_old:, 0, 3] += 2.0  # the new pass, placed 2 m east of the truth by the estimate
    truth = [LoopClosure(lc.i, lc.j, G.relative(drifted[lc.i], poses[lc.j]), lc.covariance, lc.fitness, lc.rmse,
                         lc.source, True) for lc in _group(kfs, poses, old_xyt, 0.0)]
    assert context_agrees(truth, kfs, drifted, path, lenient)
    assert context_agrees(truth, kfs, drifted, path, LoopConfig())


def test_a_group_the_path_fits_hardly_better_than_the_estimates_placement_is_refused():
    """Bays every 5 m along 60 m of corridor, the last 20 m of the new pass all among them, so the path fits each
    bay alike. The estimate has drifted 1.2 m east along the corridor. A group at the bays' alias 5 m east fits
    the path better than the estimate's own placement, refined within a floor window, but by less than the
    ambiguity ratio: a near tie the path cannot resolve, and the group, which would move the estimate by more than
    a floor window, is refused. The group at the truth fits clearly better (beyond the ratio) and stands."""
    kfs, poses, path, old_xyt = _scene(bays_round_a_corner(length=60.0), 56.0, 40.0)
    drifted = poses.copy()
    drifted[len(old_xyt):, 0, 3] += 1.2
    cfg = LoopConfig()

    def group(shift_m: float) -> list[LoopClosure]:
        """The last three keyframes placed *shift_m* east of the truth, against old keyframes 5 m apart round there."""
        out = []
        for j, off in zip(range(len(kfs) - 3, len(kfs)), (-5.0, 0.0, 5.0)):
            x = poses[j][0, 3] + shift_m + off
            i = int(np.argmin(np.hypot(old_xyt[:, 0] - x, old_xyt[:, 1] - 1.0)))
            claimed = G.xytheta_to_matrix(poses[j][0, 3] + shift_m, poses[j][1, 3], 0.0)
            out.append(LoopClosure(i, j, G.relative(drifted[i], claimed), np.eye(3) * 1e-4, 0.9, 0.02, "spatial", True))
        return out

    def ratio(g: list[LoopClosure]) -> float:
        """The estimate's refined placement's score over the group's, on the old pass round the group's old keyframes."""
        newest = max(g, key=lambda lc: lc.j)
        first, last = min(lc.i for lc in g), max(lc.i for lc in g)
        old_map = np.vstack([G.transform_points(G.relative(drifted[newest.i], drifted[m]), kfs[m].points)[:, :2]
                             for m in range(max(0, first - 40), min(len(old_xyt), last + 41))])
        recent = [m for m in range(newest.j, len(old_xyt), -1) if path[newest.j] - path[m] <= cfg.group_context_path_m]
        cloud = np.vstack([G.transform_points(G.relative(drifted[newest.j], drifted[m]), kfs[m].points)[:, :2]
                           for m in recent])
        field = correlative.LikelihoodPyramid(old_map, 0.1, 0.1, levels=5)
        floor = np.radians(cfg.window_floor_deg)
        mine = correlative.match(cloud, field, newest.measurement, cfg.window_floor_m, floor).score
        theirs = correlative.match(cloud, field, G.relative(drifted[newest.i], drifted[newest.j]), cfg.window_floor_m,
                                   floor).score
        return theirs / mine

    alias, truth = group(5.0), group(0.0)
    assert ratio(alias) < 1.0  # the path fits the alias better than the estimate's placement (the old rule passed it)
    assert not context_agrees(alias, kfs, drifted, path, cfg)
    assert context_agrees(truth, kfs, drifted, path, cfg)


def test_a_group_overrules_the_estimate_only_where_the_path_matched_from_the_estimate_moves_to_it():
    """The estimate puts the return 0.6 m east of the truth. The path, matched on the old place from there (±1 m),
    moves to the truth: a group at the truth overrules it. Where the estimate is right, a group 0.6 m east does
    not (the path stays), nor one 0.2 m east (within the match's resolution, the path stays nearer the estimate),
    nor any group with the context off."""
    kfs, poses, path, old_xyt = _scene()
    cfg = LoopConfig()
    drifted = poses.copy()
    drifted[len(old_xyt):, 0, 3] += 0.6
    truth = [LoopClosure(lc.i, lc.j, G.relative(drifted[lc.i], poses[lc.j]), lc.covariance, lc.fitness, lc.rmse,
                         lc.source, True) for lc in _group(kfs, poses, old_xyt, 0.0)]
    assert path_overrules(truth, kfs, drifted, path, cfg)
    assert not path_overrules(_group(kfs, poses, old_xyt, 0.6), kfs, poses, path, cfg)
    assert not path_overrules(_group(kfs, poses, old_xyt, 0.2), kfs, poses, path, cfg)
    assert not path_overrules(truth, kfs, drifted, path, cfg.model_copy(update={"group_context_path_m": None}))


def test_a_group_with_no_path_of_its_own_since_the_old_place_is_left_to_the_other_tests():
    """When the newest old keyframe lies within the last quarter of the context path (a short loop), the recent
    path holds the old place itself: the test has nothing to add and agrees, alias or not."""
    kfs, poses, path, old_xyt = _scene()
    short = [LoopClosure(len(kfs) - 4, j, G.relative(poses[len(kfs) - 4], poses[j]) @ G.xytheta_to_matrix(5.0, 0.0, 0.0),
                         np.eye(3) * 1e-4, 0.9, 0.02, "spatial", True) for j in range(len(kfs) - 3, len(kfs))]
    assert context_agrees(short, kfs, poses, path, LoopConfig())


def test_a_closure_its_scan_cannot_place_along_repeating_bays_is_unique_on_the_path_that_led_there():
    """Bays every 2.5 m: the newest scan, 9 m past the corner (a 180° laser looking ahead), fits the old pass 2.5 m along almost as well as at
    the truth (its own uniqueness test fails), but its last 20 m of path, round the corner, fits only at the
    truth. A closure at the truth is unique on the path; one at the alias is not, nor is any closure with the
    test off or a path that scores below the bar a scan must clear."""
    kfs, poses, path, old_xyt = _scene(bays_round_a_corner(period=2.5), 36.0, 10.0)
    j = len(kfs) - 1
    i = int(np.argmin(np.hypot(old_xyt[:, 0] - 10.0, old_xyt[:, 1] - 1.0)))
    scan = kfs[j].points[:, :2]
    old_map = np.vstack([G.transform_points(G.relative(poses[i], poses[m]), kfs[m].points)[:, :2]
                         for m in range(i - 6, i + 7)])
    field = correlative.LikelihoodPyramid(old_map, 0.1, 0.1, levels=5)
    truth = G.relative(poses[i], poses[j])
    own = correlative.score_at(scan, field, truth)
    rival = correlative.best_elsewhere(scan, field, truth, 3.0, np.pi, truth, 0.3, np.radians(3.0), 0.9 * own)
    assert rival is not None  # the scan alone is ambiguous: the verifier's uniqueness test refuses it
    cfg = LoopConfig()

    def closure(shift_m: float) -> LoopClosure:
        return LoopClosure(i, j, truth @ G.xytheta_to_matrix(shift_m, 0.0, 0.0), np.eye(3) * 1e-4, 0.9, 0.02, "spatial")

    assert path_unique(closure(0.0), kfs, poses, path, cfg, 0.5 * own)
    assert not path_unique(closure(2.5), kfs, poses, path, cfg, 0.5 * own)
    assert not path_unique(closure(0.0), kfs, poses, path, cfg.model_copy(update={"group_context_path_m": None}), 0.0)
    assert not path_unique(closure(0.0), kfs, poses, path, cfg, 2.0)
