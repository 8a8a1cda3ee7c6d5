"""Placing a 2D scan without wheel odometry: a correlative search on the local map, widened when it fails.

Without wheels the constant-velocity guess says little when the robot accelerates or the log keeps only
some scans (0.5–1 m apart, turning up to 100° between two of them), so each scan is placed first by a
correlative branch-and-bound search of a window around that guess on the local map's likelihood field
(Olson, "Real-time correlative scan matching", ICRA 2009; Hess et al., ICRA 2016, §IV), and ICP starts from
its best pose. When that best scores well below the last scans' typical score (the robot turned or jumped
beyond the window), the search is repeated over twice the distance and every heading, around the guess and
around the last pose.

A likelihood field rewards points that land on the map's walls and never penalises points that land where
the map saw nothing, so a corridor taken the other way round, or a room turned onto its neighbour, can
outscore the right pose of a scan that sees mostly new ground. Each candidate of a widened search is
therefore also tested against what the local map's scans saw (:func:`registration.free_space.contradiction`,
Olson 2009 §III-B): one that puts its points into their free space, or theirs into its own, is not taken
while a candidate that does not is there. When the window's own best contradicts the map, the same window
is searched around the last pose too (the guess carried on a turn the robot did not make); docs/LOOP_CLOSURE.md,
"A placement that contradicts the map".
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from core.errors import DegenerateInputError
from core.frame import Frame

from . import correlative
from .config import IcpOdometryConfig
from .free_space import contradiction

Array = NDArray[np.float64]


class UnguidedPlacement:
    """The search of the module docstring, on one odometry's local map; :meth:`reset` when that map changes."""

    def __init__(self, config: IcpOdometryConfig) -> None:
        self.config = config
        self.scores: deque[float] = deque(maxlen=50)  # best scores of the last searches
        self.escalations = 0  # searches repeated over every heading
        self.contradicted = 0  # widened searches whose best-scoring pose contradicted the map and was passed over
        self._pyramid: correlative.LikelihoodPyramid | None = None

    def reset(self) -> None:
        """The local map changed: its likelihood pyramid is rebuilt at the next search."""
        self._pyramid = None

    def place(self, pts: Array, frame: Frame, guess: Array, last_pose: Array, map_points: Callable[[], Array],
              seen: Sequence[tuple[Array, Frame]]) -> Array:
        """The pose (``world_T_sensor``) to start ICP from for the scan *pts* (sensor frame; its beams in
        *frame*): the search's best when it scores better than the constant-velocity *guess*, else the guess.
        *last_pose* is the previous scan's, *map_points* gives the local map (world frame), *seen* its scans
        (``world_T_sensor``, frame)."""
        cfg = self.config
        if self._pyramid is None:
            window = int(np.ceil(2 * cfg.unguided_window_m / cfg.unguided_resolution_m))
            levels = int(min(6, np.ceil(np.log2(2 * window + 1))))
            self._pyramid = correlative.LikelihoodPyramid(map_points()[:, :2], cfg.unguided_resolution_m,
                                                          cfg.unguided_resolution_m, levels=levels)
        try:
            found = self._search(pts, guess, cfg.unguided_window_m, cfg.unguided_window_rad or 0.0)
            typical = float(np.median(self.scores)) if len(self.scores) >= 5 else None
            if cfg.unguided_escalation is not None and typical is not None and found.score < cfg.unguided_escalation * typical:
                self.escalations += 1
                found = self._widened(pts, frame, guess, last_pose, seen, found)
        except DegenerateInputError:
            return guess
        self.scores.append(found.score)
        return found.transform if found.score > found.guess_score else guess

    def _search(self, pts: Array, centre: Array, window_m: float, window_rad: float,
                min_score: float = 0.0) -> correlative.CorrelativeResult:
        return correlative.match(pts[:, :2], self._pyramid, centre, window_m, window_rad, min_score=min_score)

    def _widened(self, pts: Array, frame: Frame, guess: Array, last_pose: Array, seen: Sequence[tuple[Array, Frame]],
                 found: correlative.CorrelativeResult) -> correlative.CorrelativeResult:
        """The widened search of a poor window best *found*. A wider search must restore what the window lost
        (beat its best by the escalation factor): a corridor seen the other way round scores a little better
        than a poor but right pose. Where candidates that do not contradict the map exist, only they compete."""
        cfg = self.config
        limit = cfg.unguided_max_contradiction
        clear: dict[int, bool] = {}

        def fits(r: correlative.CorrelativeResult) -> bool:
            if limit is None or not seen:
                return True
            if id(r) not in clear:
                clear[id(r)] = contradiction(r.transform, pts, frame, seen) <= limit
            return clear[id(r)]

        best = found if fits(found) else None
        if best is None:  # the guess carried on a turn the robot did not make: the same window around the last pose
            near = self._search(pts, last_pose, cfg.unguided_window_m, cfg.unguided_window_rad or 0.0)
            best = near if fits(near) else None
        level = (best or found).score / cfg.unguided_escalation
        passed: list[correlative.CorrelativeResult] = []  # widened bests above the level that contradict the map
        for centre in (guess, last_pose):
            # Each search need only find what beats the level so far (the branch and bound prunes below it).
            r = self._search(pts, centre, 2 * cfg.unguided_window_m, np.pi, min_score=level)
            if r.score > level:
                if fits(r):
                    best, level = r, r.score
                else:
                    passed.append(r)
        if best is None:  # every candidate contradicts the map: the best score wins, as without the test
            best = max(passed + [found], key=lambda r: r.score)
        elif any(r.score > best.score for r in passed):
            self.contradicted += 1
        return correlative.CorrelativeResult(best.transform, best.score, found.guess_score)
