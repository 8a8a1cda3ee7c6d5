"""Which way a laser's beams were taken, read from its own scans before deskewing with their times.

A log's beam times cannot be trusted blindly: the rplidar_ros and ydlidar drivers list the beams of a
clockwise mirror by increasing angle while ``time_increment`` still counts from the first listed
(Slamtec/rplidar_ros #55, cartographer_ros #1546), so deskewing with the log's times doubles the skew
instead of removing it. Whether the times run as listed, the other way, or make no difference shows in
the scans themselves: two scans a few apart whose twists differ, both deskewed alike, fit each other best
when the deskew is right (a scan against a map drawn from undeskewed scans cannot show it, nor two scans
skewed alike: docs/ODOMETRY.md).

:class:`SweepCheck` collects such pairs while the robot turns, aligns each pair under the three readings
(as listed, reversed, none) with point-to-plane ICP from the odometry's relative pose, and once it has
enough, names the reading with the smallest summed residual (the median point-to-line distance of the
aligned scan's points to the other's) as soon as it beats each of the other two by ``margin``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core.errors import DegenerateInputError
from core.frame import Frame

from .deskew import deskew_planar, planar_twist
from .point_to_plane import icp_point_to_plane
from .target import IcpTarget

Array = NDArray[np.float64]

__all__ = ["SweepCheck", "READINGS", "as_read"]

#: the readings of a scan's beam times: as the log lists them, reversed (t_max − t), not at all
READINGS = ("listed", "reversed", "none")


def as_read(frame: Frame, reading: str) -> Frame:
    """*frame* with its beam times as *reading* takes them (one of :data:`READINGS`)."""
    t = frame.beam_times
    if reading == "listed":
        return frame
    if reading == "reversed":
        return replace(frame, beam_times=float(t.max()) - t)
    return replace(frame, beam_times=np.zeros_like(t))


@dataclass
class _Seen:
    frame: Frame
    pose: Array  # world_T_sensor as registered


class SweepCheck:
    """Decides the reading of a planar laser's beam times from pairs of its scans.

    Args:
        gap: scans between the two of a pair.
        min_change: a pair counts when its scans' turn rates differ by at least this much (rad/s): a scan
            turning at a steady ω is compressed by a steady factor, which another scan compressed alike
            matches up to a rotation, so only a change of the turn shows the skew. (Pairs whose speeds
            differ were tried too: on real logs their residual fell with either reading, docs/ODOMETRY.md.)
        pairs: pairs to collect before deciding (and after, until one reading is ahead by *margin*).
        margin: the best reading must fit this fraction better than each of the other two.
        max_range_m: points farther than this are left out of the fit (a far wall magnifies heading error).
    """

    def __init__(self, gap: int = 4, pairs: int = 20, min_change: float = 0.5, margin: float = 0.02,
                 max_range_m: float = 8.0) -> None:
        self.gap, self.pairs_needed, self.min_change, self.margin, self.max_range = gap, pairs, min_change, margin, max_range_m
        self._seen: deque[_Seen] = deque(maxlen=gap + 3)
        self.costs = dict.fromkeys(READINGS, 0.0)
        self.pairs = 0
        self.scans = 0  # scans fed so far
        self.verdict: str | None = None

    def _twist(self, k: int) -> Array | None:
        """Central-difference twist of the k-th kept scan (needs its neighbours)."""
        a, b = self._seen[k - 1], self._seen[k + 1]
        dt = b.frame.stamp - a.frame.stamp
        return planar_twist(geo.relative(a.pose, b.pose), dt) if dt > 0 else None

    def _points(self, frame: Frame, twist: Array, reading: str) -> Array:
        pts = deskew_planar(as_read(frame, reading), twist).points
        return pts[np.linalg.norm(pts, axis=1) <= self.max_range]

    def add(self, frame: Frame, world_T_sensor: Array) -> str | None:
        """Feed each registered scan (with its beam times) in order; returns the verdict once decided
        (``"listed"``, ``"reversed"`` or ``"none"``), None before."""
        if self.verdict is not None:
            return self.verdict
        self.scans += 1
        self._seen.append(_Seen(frame, np.asarray(world_T_sensor, dtype=np.float64)))
        if len(self._seen) < self.gap + 3:
            return None
        # the pair: the second-newest scan (whose next neighbour has arrived) and the one `gap` before it
        tw_i, tw_j = self._twist(1), self._twist(len(self._seen) - 2)
        if tw_i is None or tw_j is None or abs(tw_j[2] - tw_i[2]) < self.min_change:
            return None  # alike twists skew alike, and two scans skewed alike fit each other whatever the reading
        si, sj = self._seen[1], self._seen[-2]
        start = geo.relative(si.pose, sj.pose)
        row = {}
        for reading in READINGS:
            a, b = self._points(si.frame, tw_i, reading), self._points(sj.frame, tw_j, reading)
            try:
                target = IcpTarget(a)
                T = icp_point_to_plane(b, target, start).transform
            except DegenerateInputError:
                return None
            moved = b @ T[:2, :2].T + T[:2, 3]
            _, idx = target.tree.query(moved)
            row[reading] = float(np.median(np.abs(np.einsum("ij,ij->i", target.normals(idx), moved - a[idx]))))
        for reading, cost in row.items():
            self.costs[reading] += cost
        self.pairs += 1
        if self.pairs >= self.pairs_needed:
            best = min(READINGS, key=self.costs.__getitem__)
            if all(self.costs[best] < (1.0 - self.margin) * self.costs[r] for r in READINGS if r != best):
                self.verdict = best
        return self.verdict
