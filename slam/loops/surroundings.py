"""What a place looks like from the surroundings the robot saw arriving there: the order of the global search.

The global search (:mod:`slam.loops.candidates`) can afford one old place per turn, and after a long
drifted stretch dozens lie within the estimate's reach; the estimate's own order (nearest in standard
deviations) is no better than chance when the estimate is off by several of them, which is exactly when
the global search is needed. Appearance is independent of the estimate: the global search takes the
place that looks most like the new keyframe.

A single 2D scan says little (a 180° laser arriving from the other side sees the other half of the
place; in corridors all scans look alike): on a measured long return with a known drift injected, the
right place among ~180 ranked first for 7 % of keyframes by single-scan Scan Context against 17–22 %
for the descriptor of the scans gathered over the last 5–20 m of path (docs/LOOP_CLOSURE.md, "The global
search in the order of appearance"). So each keyframe is described by the polar descriptor (Scan Context, Kim & Kim
2018, with the 2D occupancy bins of :mod:`slam.loops.descriptor`) of the points of every keyframe within
the descriptor's own range of path behind it — the path over which the robot saw the disc the
descriptor covers — placed with the estimate when the descriptor is first asked for (over that stretch
the estimate is the odometry's).
A place (a keyframe and its local map of ±``half`` keyframes) is as alike as its most alike keyframe.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from slam.keyframes import Keyframe

from .descriptor import PolarDescriptorConfig, polar_descriptor, shift_distances

Array = NDArray[np.float64]


class Surroundings:
    """The surroundings descriptors of keyframes, computed when first asked for (a log without global
    searches computes none) and kept: the estimate of a stretch of path this short hardly changes."""

    def __init__(self, cfg: PolarDescriptorConfig = PolarDescriptorConfig()) -> None:
        self.cfg = cfg
        self._desc: dict[int, Array] = {}

    def descriptor(self, k: int, keyframes: list[Keyframe], poses: Array, path_m: Array) -> Array:
        """Keyframe *k*'s descriptor: the points of the keyframes within ``cfg.max_range`` m of *path_m*
        (cumulative odometry path per keyframe) behind it, in its sensor frame, placed by the estimate *poses*."""
        if k not in self._desc:
            first = int(np.searchsorted(path_m[: k + 1], path_m[k] - self.cfg.max_range, side="left"))
            sensor_k = G.inverse(poses[k] @ keyframes[k].base_T_sensor)
            parts = [G.transform_points(sensor_k @ poses[i] @ keyframes[i].base_T_sensor, keyframes[i].points[:, :2])
                     for i in range(first, k + 1)]
            self._desc[k] = polar_descriptor(np.vstack(parts), self.cfg)
        return self._desc[k]

    def place_distances(self, j: int, places: NDArray[np.int64], half: int, last: int,
                        keyframes: list[Keyframe], poses: Array, path_m: Array) -> Array:
        """Per place in *places*: the smallest Scan Context distance (over every heading) between keyframe
        *j*'s surroundings and those of the place's keyframes ``place ± half`` older than *last* (inf when
        it has none)."""
        lo = np.maximum(places - half, 0)
        hi = np.minimum(places + half + 1, last)
        ids = sorted({int(k) for a, b in zip(lo, hi) for k in range(a, b)})
        if not ids:
            return np.full(len(places), np.inf)
        d = np.full(last, np.inf)
        d[ids] = shift_distances(self.descriptor(j, keyframes, poses, path_m),
                                 np.array([self.descriptor(k, keyframes, poses, path_m) for k in ids])).min(axis=1)
        return np.array([d[a:b].min() if b > a else np.inf for a, b in zip(lo, hi)])
