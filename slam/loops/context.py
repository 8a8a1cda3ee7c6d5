"""A group's last word: the robot's recent path, matched as one cloud on the old place (2D).

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
of the best — the uniqueness test of one closure, on the evidence of a whole path. Matching the larger
context where a single scan is ambiguous is Olson's argument for place recognition (E. Olson,
"Recognizing places using spectrally clustered local matches", Robotics and Autonomous Systems 57(12),
2009: a match must be locally unambiguous and globally sufficient); Cartographer matches scans against
submaps for the same reason (Hess et al., ICRA 2016).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from core.errors import DegenerateInputError
from registration import correlative
from slam.keyframes import Keyframe

from .config import LoopConfig
from .types import LoopClosure

Array = NDArray[np.float64]

_PYRAMID_LEVELS = 5  # as the verifier's: 2^5 cells per top block
_MIN_OWN_PATH = 0.25  # a recent path shorter than this fraction of group_context_path_m adds nothing to the group


def _cloud(keyframes: list[Keyframe], poses: Array, ref: int, members: list[int]) -> Array:
    """The *members*' scan points (x, y) in keyframe *ref*'s base frame, placed by the estimate *poses*."""
    inv = G.inverse(poses[ref])
    return np.vstack([G.transform_points(inv @ poses[m] @ keyframes[m].base_T_sensor, keyframes[m].points)[:, :2]
                      for m in members])


def context_agrees(group: list[LoopClosure], keyframes: list[Keyframe], poses: Array, path_m: Array,
                   config: LoopConfig, min_score: float = 0.0) -> bool:
    """Whether the recent path up to the *group*'s newest keyframe, matched as a whole on the old place, lands
    where the group says (see the module docstring). *path_m*: cumulative odometry path (m) at each keyframe.
    True when the test has nothing to add: off, no recent path of its own, no surroundings, or a best pose
    that scores below *min_score* (a path the estimate blurred, or surroundings that hold little of it: no
    pose explains it, and which explains it least badly says nothing)."""
    c = config
    if c.group_context_path_m is None or not group:
        return True
    newest = max(group, key=lambda lc: lc.j)
    j = newest.j
    lo, hi = min(lc.i for lc in group), max(lc.i for lc in group)
    reach = c.group_context_path_m
    recent = [m for m in range(j, hi, -1) if path_m[j] - path_m[m] <= reach]
    if len(recent) < 2 or path_m[j] - path_m[recent[-1]] < _MIN_OWN_PATH * reach:
        return True
    old = [m for m in range(recent[-1]) if path_m[lo] - reach <= path_m[m] <= path_m[hi] + reach]
    if len(old) < 2:
        return True
    res = c.correlative_resolution_m
    query = _cloud(keyframes, poses, j, recent)
    query = query[np.unique(np.floor(query / res).astype(np.int64), axis=0, return_index=True)[1]]  # a point a cell
    try:
        pyramid = correlative.LikelihoodPyramid(_cloud(keyframes, poses, newest.i, old), res, res, levels=_PYRAMID_LEVELS)
        guess = G.xytheta_to_matrix(G.matrix_to_xytheta(newest.measurement))
        found = correlative.match(query, pyramid, guess, c.group_context_window_m, np.radians(c.window_floor_deg))
    except DegenerateInputError:
        return True
    if found.score < min_score:
        return True
    d = G.matrix_to_xytheta(G.relative(guess, found.transform))
    near = bool(np.hypot(d[0], d[1]) <= c.window_floor_m and abs(d[2]) <= np.radians(c.window_floor_deg))
    return near or found.guess_score >= c.ambiguity_ratio * found.score
