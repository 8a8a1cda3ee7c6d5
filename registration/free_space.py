"""Negative information of 2D laser scans: points that lie where another scan's beams passed through.

A point at bearing φ and range r, seen from a scan's sensor, contradicts that scan when the beam at φ
returned beyond ``r + margin + rel_margin·r``: the two scans cannot both be right — the negative-information
test of 2D scan matching (Olson, "Real-time correlative scan matching", ICRA 2009, §III-B). A likelihood
field scores only where points land, never where beams passed, so a pose that puts a scan's walls into a
corridor the map saw empty can outscore the right one; this test is what tells them apart.

Frames: each scan's own sensor frame; poses 4×4 ``world_T_sensor``. Units: metres, radians.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from core.frame import Frame

Array = NDArray[np.float64]

#: each scan's beams in angle order, made once per frame: the test runs many times per scan
_BEAMS: "weakref.WeakKeyDictionary[Frame, tuple[Array, Array, NDArray[np.bool_], float]]" = weakref.WeakKeyDictionary()


def _beams_by_angle(frame: Frame) -> tuple[Array, Array, NDArray[np.bool_], float]:
    """*frame*'s beams sorted by angle: angles (rad), ranges (m, ``inf`` where the beam returned nothing),
    the no-return mask, and the median angular increment (rad); cached per frame."""
    got = _BEAMS.get(frame)
    if got is None:
        order = np.argsort(frame.angles)
        a, dropped = frame.angles[order], frame.no_return[order]
        got = a, np.where(dropped, np.inf, frame.ranges[order]), dropped, float(np.median(np.diff(a)))
        _BEAMS[frame] = got
    return got


def violation(points_in_sensor: Array, frame: Frame, margin: float = 0.1, rel_margin: float = 0.02,
              min_inside: float = 0.0) -> float:
    """Fraction of *points* (in *frame*'s sensor frame) lying in the free space *frame*'s beams saw.

    A beam that returned nothing says nothing (dark or glancing surfaces drop out: half the beams
    of a Hokuyo URG-04LX in a cluttered lab, a third of a SICK's outdoors), and points outside the
    field of view are ignored. Returns 0 for a frame without beam geometry, when no point falls on a
    returned beam, or when fewer than *min_inside* of the points (a fraction) do: too little overlap to
    say anything.
    """
    if frame.angles is None or frame.ranges is None or len(frame.angles) < 2:
        return 0.0
    a, near, dropped, inc = _beams_by_angle(frame)
    phi = np.arctan2(points_in_sensor[:, 1], points_in_sensor[:, 0])
    r = np.hypot(points_in_sensor[:, 0], points_in_sensor[:, 1])
    # The nearest beam by angle (a reader may have left out beams, so the angles need not be uniform).
    hi_ = np.clip(np.searchsorted(a, phi), 1, len(a) - 1)
    k = np.where(np.abs(phi - a[hi_ - 1]) <= np.abs(a[hi_] - phi), hi_ - 1, hi_)
    inside = (np.abs(phi - a[k]) <= 0.5 * abs(inc) + 1e-9) & ~dropped[k]
    n_in = int(np.count_nonzero(inside))
    if n_in == 0 or n_in < min_inside * len(inside):
        return 0.0
    # The shortest return of the beam and its two neighbours: a wall seen at a glancing angle changes
    # range quickly from beam to beam, and a point between two beams is not contradicted by one of them.
    lo, hi = np.clip(k - 1, 0, len(a) - 1), np.clip(k + 1, 0, len(a) - 1)
    shortest = np.minimum(np.minimum(near[lo], near[k]), near[hi])
    viol = inside & (shortest > r + margin + rel_margin * r)
    return float(viol.sum() / n_in)


def contradiction(pose: Array, points: Array, frame: Frame, seen: Sequence[tuple[Array, Frame]]) -> float:
    """How much a scan placed at *pose* (``world_T_sensor``; its *points* in its sensor frame, its beams in
    *frame*) contradicts the scans *seen* (``(world_T_sensor, frame)`` each): the larger of the two mean
    :func:`violation` fractions over them — its points in their free space, and their points in its own."""
    if not seen:
        return 0.0
    pts = np.column_stack([points[:, :2], np.zeros(len(points))])
    into_seen, into_scan = [], []
    for seen_pose, seen_frame in seen:
        seen_T_scan = G.relative(seen_pose, pose)
        into_seen.append(violation(G.transform_points(seen_T_scan, pts), seen_frame))
        into_scan.append(violation(G.transform_points(G.inverse(seen_T_scan), seen_frame.points), frame))
    return max(float(np.mean(into_seen)), float(np.mean(into_scan)))
