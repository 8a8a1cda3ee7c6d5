"""The robot's recent path, matched as one cloud on the old place (2D): a group's last word, and a closure's
uniqueness where its own scan is ambiguous.

A group of closures the estimate cannot vouch for agrees with itself even when it is an alias: along a
corridor whose doors repeat, each scan of a return fits the old pass a few metres along as well as at the
truth, and consecutive keyframes agree on the same wrong shift, so neither the uniqueness of one closure
(:meth:`~slam.loops.verify.Verifier.unique`, within its ±3 floor windows) nor the group's pairwise
consistency can tell. The path that led there can: the corner it came round, the doors behind it. So,
before such a group is accepted, the keyframes of the last ``group_context_path_m`` of path up to its
newest member (since its newest old keyframe) are placed by the estimate relative to that member and
matched as one cloud, by the correlative search, on the old place's surroundings: the keyframes within as
much path either side of the group's old keyframes, none of them part of the recent path. The search spans
± ``group_context_window_m`` and ± ``window_floor_deg`` round the group's own pose. The group stands when
the best pose lies within a floor window of its own, or its own pose scores at least ``ambiguity_ratio``
of the best — the uniqueness test of one closure, on the evidence of a whole path — and the estimate's own
placement of the path (each refined within a floor window) does not fit it better: the estimate and the group
are two hypotheses, and the path is the evidence between them. Matching the larger
context where a single scan is ambiguous is Olson's argument for place recognition (E. Olson,
"Recognizing places using spectrally clustered local matches", Robotics and Autonomous Systems 57(12),
2009: a match must be locally unambiguous and globally sufficient); Cartographer matches scans against
submaps for the same reason (Hess et al., ICRA 2016).

The same evidence works the other way (:func:`path_unique`): a closure whose scan fits the old pass as
well a few metres along (it fails the verifier's uniqueness test, and was dropped) is unique when the
recent path, placed as the closure says, is: nothing within the verifier's ±3 floor windows at any heading
scores ``ambiguity_ratio`` of it. Such a closure may then wait for a group like any unique one, and the
group still faces every other test, this one's :func:`context_agrees` among them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from core.errors import DegenerateInputError
from registration import correlative
from registration.voxel import voxel_keys
from slam.keyframes import Keyframe

from .config import LoopConfig
from .types import LoopClosure
from .verify import PYRAMID_LEVELS, UNIQUE_RADIUS_CELLS, UNIQUE_RADIUS_RAD, UNIQUE_WINDOW_FLOORS

Array = NDArray[np.float64]

_MIN_OWN_PATH = 0.25  # a recent path shorter than this fraction of group_context_path_m adds nothing to the group


def _cloud(keyframes: list[Keyframe], poses: Array, ref: int, members: list[int]) -> Array:
    """The *members*' scan points (x, y) in keyframe *ref*'s base frame, placed by the estimate *poses*."""
    inv = G.inverse(poses[ref])
    return np.vstack([G.transform_points(inv @ poses[m] @ keyframes[m].base_T_sensor, keyframes[m].points)[:, :2]
                      for m in members])


def _path_and_surroundings(j: int, lo: int, hi: int, path_m: Array, reach: float
                           ) -> tuple[list[int], list[int]] | None:
    """The recent path (keyframes of the last *reach* m of path up to *j*, none older than *hi*) and the old
    place's surroundings (the keyframes within *reach* m of path either side of *lo* … *hi*, older than the
    recent path); None when the recent path is too short to add anything or there are no surroundings."""
    recent = [m for m in range(j, hi, -1) if path_m[j] - path_m[m] <= reach]
    if len(recent) < 2 or path_m[j] - path_m[recent[-1]] < _MIN_OWN_PATH * reach:
        return None
    old = [m for m in range(recent[-1]) if path_m[lo] - reach <= path_m[m] <= path_m[hi] + reach]
    return None if len(old) < 2 else (recent, old)


def _path_match(keyframes: list[Keyframe], poses: Array, j: int, i: int, lo: int, hi: int, path_m: Array,
                config: LoopConfig, resolution_m: float | None = None
                ) -> tuple[Array, correlative.LikelihoodPyramid] | None:
    """The recent path up to *j* as one cloud in *j*'s base frame (a point a cell), and the likelihood field of
    the old place's surroundings (round *lo* … *hi*) in *i*'s base frame, at *resolution_m* (cell and σ; None:
    ``correlative_resolution_m``); None when there is nothing to match (:func:`_path_and_surroundings`). Raises
    :class:`DegenerateInputError` for too few points."""
    if config.group_context_path_m is None:
        return None
    found = _path_and_surroundings(j, lo, hi, path_m, config.group_context_path_m)
    if found is None:
        return None
    recent, old = found
    res = config.correlative_resolution_m if resolution_m is None else resolution_m
    query = _cloud(keyframes, poses, j, recent)
    query = query[np.unique(voxel_keys(query, res), return_index=True)[1]]  # a point a cell, in the cells' order
    return query, correlative.LikelihoodPyramid(_cloud(keyframes, poses, i, old), res, res, levels=PYRAMID_LEVELS)


def _planar(T: Array) -> Array:
    return G.xytheta_to_matrix(G.matrix_to_xytheta(T))


def _group_path_match(group: list[LoopClosure], keyframes: list[Keyframe], poses: Array, path_m: Array,
                      config: LoopConfig) -> tuple[LoopClosure, Array, correlative.LikelihoodPyramid] | None:
    """The *group*'s newest member with :func:`_path_match`'s clouds for it (its recent path, the surroundings of
    all the group's old keyframes); None without a group or anything to match. Raises
    :class:`DegenerateInputError` for too few points."""
    if not group:
        return None
    newest = max(group, key=lambda lc: lc.j)
    clouds = _path_match(keyframes, poses, newest.j, newest.i, min(lc.i for lc in group), max(lc.i for lc in group),
                         path_m, config)
    return None if clouds is None else (newest, *clouds)


def _group_path_match_or_none(group: list[LoopClosure], keyframes: list[Keyframe], poses: Array, path_m: Array,
                              config: LoopConfig) -> tuple[LoopClosure, Array, correlative.LikelihoodPyramid] | None:
    """:func:`_group_path_match`, None also where the clouds hold too few points."""
    try:
        return _group_path_match(group, keyframes, poses, path_m, config)
    except DegenerateInputError:
        return None


def context_agrees(group: list[LoopClosure], keyframes: list[Keyframe], poses: Array, path_m: Array,
                   config: LoopConfig, min_score: float = 0.0) -> bool:
    """Whether the recent path up to the *group*'s newest keyframe, matched as a whole on the old place, lands
    where the group says (see the module docstring), and does not fit about as well (``ambiguity_ratio``) where
    the estimate puts it (:func:`_estimate_fits_as_well`). *path_m*: cumulative odometry path (m) at each keyframe.
    True when the test has nothing to add: off, no recent path of its own, no surroundings, or a best pose
    that scores below *min_score* (a path the estimate blurred, or surroundings that hold little of it: no
    pose explains it, and which explains it least badly says nothing) — except against the estimate's own
    placement (:func:`_estimate_fits_as_well`), which is asked first."""
    c = config
    try:
        matched = _group_path_match(group, keyframes, poses, path_m, c)
        if matched is None:
            return True
        newest, query, pyramid = matched
        guess = _planar(newest.measurement)
        found = correlative.match(query, pyramid, guess, c.group_context_window_m, np.radians(c.window_floor_deg))
    except DegenerateInputError:
        return True
    if _estimate_fits_as_well(query, pyramid, guess, _planar(G.relative(poses[newest.i], poses[newest.j])), c):
        return False
    if found.score < min_score:
        return True
    d = G.matrix_to_xytheta(G.relative(guess, found.transform))
    near = bool(np.hypot(d[0], d[1]) <= c.window_floor_m and abs(d[2]) <= np.radians(c.window_floor_deg))
    return near or found.guess_score >= c.ambiguity_ratio * found.score


def _estimate_fits_as_well(query: Array, pyramid: correlative.LikelihoodPyramid, group_T: Array, estimate_T: Array,
                           config: LoopConfig) -> bool:
    """Whether the recent path fits the old place where the estimate puts it about as well as where the group
    does, or better: each placement refined within a floor window, the two more than a floor window apart, the
    estimate's scoring at least ``ambiguity_ratio`` of the group's. Two hypotheses, one evidence: a group that
    moves the robot off a placement its own path fits better is the alias (a T-junction's side corridor seen
    from a new arm, which the old place's map does not hold, so the ratio above passes it), while a group that
    corrects a drifted estimate moves the path from a worse fit to a clearly better one. A near tie is an
    ambiguity the path cannot resolve, as in every uniqueness test here, and the estimate, which the group
    would move by more than a floor window, keeps its place. Asked even where no pose fits the path well
    (below the bar of :func:`context_agrees`): which of two placements fits it better is still evidence between
    them, where the best of a whole window is not (measured over the recorded group decisions of 21 logs,
    docs/LOOP_CLOSURE.md)."""
    floor_rad = np.radians(config.window_floor_deg)
    mine = correlative.match(query, pyramid, group_T, config.window_floor_m, floor_rad)
    theirs = correlative.match(query, pyramid, estimate_T, config.window_floor_m, floor_rad)
    d = G.matrix_to_xytheta(G.relative(mine.transform, theirs.transform))
    return bool(np.hypot(d[0], d[1]) > config.window_floor_m and theirs.score >= config.ambiguity_ratio * mine.score)


def path_overrules(group: list[LoopClosure], keyframes: list[Keyframe], poses: Array, path_m: Array,
                   config: LoopConfig) -> bool:
    """Whether the recent path, matched on the old place from where the estimate puts it (within a floor
    window), moves where the *group* says: its best pose lies within the uniqueness radius (a few cells and
    degrees) of the group's and farther from the estimate's. A group the estimate vouched against claims the
    estimate is off by more than it knows; the path's own match, started from the estimate, is the second
    measurement of that correction. False when there is nothing to match."""
    matched = _group_path_match_or_none(group, keyframes, poses, path_m, config)
    if matched is None:
        return False
    newest, query, pyramid = matched
    mine, theirs = _planar(newest.measurement), _planar(G.relative(poses[newest.i], poses[newest.j]))
    found = correlative.match(query, pyramid, theirs, config.window_floor_m, np.radians(config.window_floor_deg))
    to_group = G.matrix_to_xytheta(G.relative(mine, found.transform))
    to_estimate = G.matrix_to_xytheta(G.relative(theirs, found.transform))
    radius = UNIQUE_RADIUS_CELLS * pyramid.resolution
    near = np.hypot(to_group[0], to_group[1]) <= radius and abs(to_group[2]) <= UNIQUE_RADIUS_RAD
    return bool(near and np.hypot(to_group[0], to_group[1]) < np.hypot(to_estimate[0], to_estimate[1]))


def path_score(group: list[LoopClosure], keyframes: list[Keyframe], poses: Array, path_m: Array,
               config: LoopConfig) -> float | None:
    """The correlative score (0–1) of the recent path up to the *group*'s newest keyframe, placed as that member
    says, on the old place's surroundings — how well the path that led there fits where the group puts it;
    None when there is nothing to match (as in :func:`context_agrees`)."""
    matched = _group_path_match_or_none(group, keyframes, poses, path_m, config)
    if matched is None:
        return None
    newest, query, pyramid = matched
    return correlative.score_at(query, pyramid, _planar(newest.measurement))


def path_unique(closure: LoopClosure, keyframes: list[Keyframe], poses: Array, path_m: Array, config: LoopConfig,
                min_score: float) -> bool:
    """Whether a *closure* whose own scan is ambiguous is unique on the evidence of the path that led there:
    the recent path up to its new keyframe, placed as the closure says on the old place's surroundings,
    scores at least *min_score*, and no pose within ``UNIQUE_WINDOW_FLOORS`` floor windows at any heading
    (beyond a few cells and degrees of it) scores ``ambiguity_ratio`` of that — the uniqueness test of one
    scan (:meth:`~slam.loops.verify.Verifier.unique`), asked of the whole path. False when there is nothing
    to match (the scan's ambiguity stands). The search runs at ``global_resolution_m`` (the coarser cell of the
    searches over wide windows): ±3 m at every heading of a 20 m path is one, and at the spatial cell it took a
    sixth of a dense indoor log's run time (measured in docs/LOOP_CLOSURE.md)."""
    c = config
    try:
        clouds = _path_match(keyframes, poses, closure.j, closure.i, closure.i, closure.i, path_m, c,
                             c.global_resolution_m)
        if clouds is None:
            return False
        query, pyramid = clouds
        T = _planar(closure.measurement)
        own = correlative.score_at(query, pyramid, T)
        if own <= 0.0 or own < min_score:
            return False
        other = correlative.best_elsewhere(query, pyramid, T, UNIQUE_WINDOW_FLOORS * c.window_floor_m, np.pi, T,
                                           UNIQUE_RADIUS_CELLS * pyramid.resolution, UNIQUE_RADIUS_RAD,
                                           c.ambiguity_ratio * own, first=True)
    except DegenerateInputError:
        return False
    return other is None
