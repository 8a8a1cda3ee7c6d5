"""Synthetic scenes for the loop-closure tests: small occupancy worlds and keyframes scanned in them.

``room()`` is a 12 × 8 m room with a few boxes (distinctive everywhere); ``corridor()`` a 40 m long,
2 m wide corridor without features (a scan matches anywhere along it). Scans come from the
simulator's ray caster (``evaluation.sim.cast_rays``) with a 181-beam 180° laser and 1 cm noise.
"""

from __future__ import annotations

import numpy as np

from core import geometry as G
from core.frame import Frame
from evaluation.sim import LaserSpec, World, cast_rays
from registration.voxel import voxel_downsample
from slam.keyframes import Keyframe

RES = 0.05
LASER = LaserSpec("test_laser", 181, -np.pi / 2, np.pi / 2, 0.05, 30.0, 10.0, 0.01)


def _grid(width: float, height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    margin = 1.0
    nx, ny = int(round((width + 2 * margin) / RES)), int(round((height + 2 * margin) / RES))
    xs = -margin + (np.arange(nx) + 0.5) * RES
    ys = -margin + (np.arange(ny) + 0.5) * RES
    return np.zeros((ny, nx), dtype=bool), xs, ys, np.array([-margin, -margin])


def _box(occ: np.ndarray, xs: np.ndarray, ys: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> None:
    yy = (ys >= y0) & (ys <= y1)
    xx = (xs >= x0) & (xs <= x1)
    occ[np.ix_(yy, xx)] = True


def _walls(occ: np.ndarray, xs: np.ndarray, ys: np.ndarray, width: float, height: float, t: float = 0.15) -> None:
    _box(occ, xs, ys, -t, -t, width + t, 0.0)
    _box(occ, xs, ys, -t, height, width + t, height + t)
    _box(occ, xs, ys, -t, -t, 0.0, height + t)
    _box(occ, xs, ys, width, -t, width + t, height + t)


def room() -> World:
    """A 12 × 8 m room with boxes of different sizes in it."""
    occ, xs, ys, origin = _grid(12.0, 8.0)
    _walls(occ, xs, ys, 12.0, 8.0)
    for x0, y0, x1, y1 in ((2.0, 2.0, 2.6, 2.4), (6.0, 5.0, 6.3, 6.2), (9.0, 1.0, 10.2, 1.5), (4.0, 6.5, 4.4, 6.9),
                           (10.5, 6.0, 11.0, 7.2), (7.5, 2.5, 7.9, 2.9)):
        _box(occ, xs, ys, x0, y0, x1, y1)
    return World(occ, np.ones_like(occ), RES, origin, "test_room")


def room_with_a_wall_across(x: float = 6.0) -> World:
    """The :func:`room` with a wall across it at *x* (a door closed, a screen put up) — for one pass only."""
    occ, xs, ys, origin = _grid(12.0, 8.0)
    base = room()
    occ[:] = base.occupied
    _box(occ, xs, ys, x, 0.0, x + 0.1, 8.0)
    return World(occ, np.ones_like(occ), RES, origin, "test_room_wall")


#: boxes standing in one pass only (cars parked for a while, furniture moved), for :func:`room_with_boxes`
BOXES_FIRST = ((3.0, 4.5, 3.6, 4.9), (8.0, 5.5, 9.2, 6.0), (5.0, 1.2, 5.6, 1.6))
BOXES_SECOND = ((4.5, 4.8, 5.1, 5.2), (10.0, 3.0, 10.5, 4.2), (7.8, 1.0, 8.4, 1.4))


def room_with_boxes(boxes: tuple[tuple[float, float, float, float], ...]) -> World:
    """The :func:`room` with more *boxes* ``(x0, y0, x1, y1)`` standing in it — for one pass only."""
    occ, xs, ys, origin = _grid(12.0, 8.0)
    occ[:] = room().occupied
    for box in boxes:
        _box(occ, xs, ys, *box)
    return World(occ, np.ones_like(occ), RES, origin, "test_room_boxes")


def corridor(length: float = 40.0) -> World:
    """A featureless corridor, 2 m wide and *length* m long (its ends beyond the laser's reach)."""
    occ, xs, ys, origin = _grid(length, 2.0)
    _box(occ, xs, ys, -0.15, -0.15, length + 0.15, 0.0)
    _box(occ, xs, ys, -0.15, 2.0, length + 0.15, 2.15)
    return World(occ, np.ones_like(occ), RES, origin, "test_corridor")


def corridor_with_bays(period: float = 5.0, length: float = 80.0) -> World:
    """The :func:`corridor` with a 2 m wide, 0.8 m deep bay in both walls every *period* metres (doors along a
    corridor: every place looks like the ones *period* metres on, and unlike those a metre or two away)."""
    occ, xs, ys, origin = _grid(length, 2.0)
    occ[:] = corridor(length).occupied
    for x in np.arange(period / 2, length, period):
        _box(occ, xs, ys, x - 1.15, -0.95, x + 1.15, 0.0)  # walls round the bays ...
        _box(occ, xs, ys, x - 1.15, 2.0, x + 1.15, 2.95)
        occ[np.ix_((ys > -0.8) & (ys < 0.0), (xs > x - 1.0) & (xs < x + 1.0))] = False  # ... and the bays
        occ[np.ix_((ys > 2.0) & (ys < 2.8), (xs > x - 1.0) & (xs < x + 1.0))] = False
    return World(occ, np.ones_like(occ), RES, origin, "test_corridor_bays")


def bays_round_a_corner(period: float = 5.0, length: float = 40.0, side: float = 20.0) -> World:
    """A 2 m corridor *length* m east, with 2 m wide, 0.8 m deep bays in both walls every *period* metres from
    7.5 m on, entered at its west end from a plain 2 m corridor *side* m long running north: along the bays
    every place looks like the ones *period* metres on; the way in, round the corner, does not."""
    occ, xs, ys, origin = _grid(length, side)
    occ[:] = True
    occ[np.ix_((ys > 0.0) & (ys < 2.0), (xs > 0.0) & (xs < length))] = False
    occ[np.ix_((ys > 0.0) & (ys < side), (xs > 0.0) & (xs < 2.0))] = False
    for x in np.arange(7.5, length - 1.0, period):
        occ[np.ix_((ys > -0.8) & (ys <= 0.0), (xs > x - 1.0) & (xs < x + 1.0))] = False
        occ[np.ix_((ys >= 2.0) & (ys < 2.8), (xs > x - 1.0) & (xs < x + 1.0))] = False
    return World(occ, np.ones_like(occ), RES, origin, "test_bays_round_a_corner")


def keyframes(world: World, xyt: list[tuple[float, float, float]], seed: int = 0, laser: LaserSpec = LASER,
              first_id: int = 0) -> list[Keyframe]:
    """A keyframe per pose ``(x, y, θ)`` (base = sensor), scanned in *world*; ``odom_pose`` is the true pose;
    ids from *first_id*."""
    rng = np.random.default_rng(seed)
    xyt = np.asarray(xyt, dtype=float)
    ranges = cast_rays(world, xyt, laser, rng=rng, range_noise=laser.noise_std)
    angles = laser.angles()
    out = []
    for k, (pose, r) in enumerate(zip(xyt, ranges), start=first_id):
        hit = np.isfinite(r)
        pts = np.column_stack([r[hit] * np.cos(angles[hit]), r[hit] * np.sin(angles[hit])])
        frame = Frame(float(k), pts, k, angles, np.where(hit, r, np.inf), ~hit, max_range=laser.range_max)
        T = G.xytheta_to_matrix(*pose)
        out.append(Keyframe(k, k, float(k), T, np.eye(4), voxel_downsample(pts, 0.02), frame))
    return out
