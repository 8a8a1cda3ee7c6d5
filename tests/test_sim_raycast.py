"""Ray casting of the 2D laser simulator against analytic geometry and an independent ray march."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core.errors import GeometryError
from evaluation.sim import LASER_PRESETS, LaserSpec, World, cast_rays, load_world, raycast_distances


def _empty_world(w=200, h=120, res=0.05):
    return World(np.zeros((h, w), bool), np.ones((h, w), bool), res, np.zeros(2), "empty")


def _march_occupied(world, start, theta, r_max, step):
    """Independent check: sample points every *step* along a ray; True where a sample is in an occupied cell."""
    s = np.arange(0.0, r_max, step)
    pts = start[None, :] + s[:, None] * np.array([math.cos(theta), math.sin(theta)])[None, :]
    iy, ix = world.cell_of(pts)
    h, w = world.shape
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    occ = np.zeros(len(s), bool)
    occ[ok] = world.occupied[iy[ok], ix[ok]]
    return s, occ


def test_wall_at_known_distance():
    """A wall filling x >= 2 m: the range at bearing φ from (x0, y0) is (2 − x0)/cos φ (closed form),
    for any bearing in ±70°, and ``inf`` when that exceeds range_max."""
    world = _empty_world()
    world.occupied[:, 40:] = True  # cells from x = 40·0.05 = 2.0 m on
    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.1, 1.9, 500)
    y0 = rng.uniform(2.0, 4.0, 500)
    phi = rng.uniform(-1.2, 1.2, 500)
    d = raycast_distances(world.occupied, world.origin_xy, world.resolution, np.column_stack([x0, y0]),
                          np.column_stack([np.cos(phi), np.sin(phi)]), 100.0)
    expected = (2.0 - x0) / np.cos(phi)
    inside = y0 + expected * np.sin(phi)
    valid = (inside > 0) & (inside < 6.0)
    np.testing.assert_allclose(d[valid], expected[valid], rtol=0, atol=1e-9)
    short = raycast_distances(world.occupied, world.origin_xy, world.resolution, np.column_stack([x0, y0]),
                              np.column_stack([np.cos(phi), np.sin(phi)]), 0.5)
    assert np.all(np.isinf(short[expected > 0.5 + 1e-9]))


def test_disc_at_known_distance():
    """Rays aimed at the centre of a rasterised disc of radius r at distance D return D − r within
    half a cell diagonal (the rasterisation error bound)."""
    res = 0.02
    world = _empty_world(w=500, h=500, res=res)
    xs, ys = world.cell_centres()
    cx, cy, r = 5.0, 5.0, 0.7
    world.occupied[:] = (xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2 <= r * r
    rng = np.random.default_rng(1)
    ang = rng.uniform(-np.pi, np.pi, 400)
    dist = rng.uniform(1.0, 4.5, 400)
    starts = np.column_stack([cx + dist * np.cos(ang), cy + dist * np.sin(ang)])
    dirs = -np.column_stack([np.cos(ang), np.sin(ang)])
    d = raycast_distances(world.occupied, world.origin_xy, res, starts, dirs, 10.0)
    assert np.max(np.abs(d - (dist - r))) <= res * math.sqrt(2) / 2 + 1e-9


def test_axis_aligned_and_diagonal_rays():
    """Rays along the axes and exact diagonals (ties of the traversal) hit the wall boundary exactly."""
    world = _empty_world()
    world.occupied[:, 60:] = True   # x >= 3.0
    world.occupied[100:, :] = True  # y >= 5.0
    world.occupied[:, :4] = True    # x < 0.2
    world.occupied[:4, :] = True    # y < 0.2
    start = np.array([[1.0, 1.0]] * 6)
    dirs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1], [1, 1], [-1, -1]], float)
    d = raycast_distances(world.occupied, world.origin_xy, world.resolution, start, dirs, 10.0)
    np.testing.assert_allclose(d, [2.0, 4.0, 0.8, 0.8, 2.0 * math.sqrt(2), 0.8 * math.sqrt(2)], atol=1e-9)


def test_unknown_cells_are_transparent_and_leaving_the_grid_is_no_return():
    """Unknown cells do not stop a beam (STDR semantics); a beam leaving the grid has no return."""
    world = _empty_world()
    world.known[:, 30:50] = False
    d = raycast_distances(world.occupied, world.origin_xy, world.resolution, [[0.5, 3.0]], [[1.0, 0.0]], 100.0)
    assert np.isinf(d[0])
    world.occupied[:, 80] = True
    d = raycast_distances(world.occupied, world.origin_xy, world.resolution, [[0.5, 3.0]], [[1.0, 0.0]], 100.0)
    assert d[0] == pytest.approx(4.0 - 0.5, abs=1e-9)


def test_origin_outside_grid_rejected():
    """Ray origins outside the world grid raise a GeometryError."""
    world = _empty_world()
    with pytest.raises(GeometryError):
        raycast_distances(world.occupied, world.origin_xy, world.resolution, [[-1.0, 1.0]], [[1.0, 0.0]], 5.0)


@pytest.mark.parametrize("name,res", [("rooms", 0.05), ("obstacles", 0.03), ("corridor", 0.05), ("ring", 0.05)])
def test_hits_and_no_returns_against_independent_march(name, res):
    """Noise-free: every hit point lies on an occupied cell (a step past it is occupied) and an
    independent fine ray march finds no occupied cell before it; every no-return beam's march
    finds no occupied cell within range_max."""
    world = load_world(name, resolution=res, seed=3)
    spec = LASER_PRESETS["fastgpom"]
    rng = np.random.default_rng(5)
    free = np.argwhere(world.free)
    sel = free[rng.choice(len(free), 12, replace=False)]
    xs, ys = world.cell_centres()
    poses = np.column_stack([xs[sel[:, 1]], ys[sel[:, 0]], rng.uniform(-np.pi, np.pi, len(sel))])
    ranges = cast_rays(world, poses, spec, range_noise=0.0)
    assert ranges.shape == (len(poses), spec.num_beams)
    step = res / 10
    angles = spec.angles()
    checked_hits = checked_none = 0
    for k, pose in enumerate(poses):
        for b in range(0, spec.num_beams, 7):
            th = pose[2] + angles[b]
            r = ranges[k, b]
            if np.isfinite(r):
                if r <= spec.range_min:
                    continue
                s, occ = _march_occupied(world, pose[:2], th, r - 1e-6, step)
                assert not occ.any()
                _, past = _march_occupied(world, pose[:2] + (r + 1e-6) * np.array([math.cos(th), math.sin(th)]), th, 1e-7, 1.0)
                assert past[0]
                checked_hits += 1
            else:
                _, occ = _march_occupied(world, pose[:2], th, spec.range_max, step)
                assert not occ.any()
                checked_none += 1
    assert checked_hits > 100 and checked_none > 10


def test_noisy_hits_within_a_cell_plus_noise_of_an_occupied_cell():
    """With range noise σ every hit point lies within half a cell diagonal + 6σ of an occupied cell
    centre, and ranges stay within [range_min, range_max) (noise is clipped)."""
    world = load_world("obstacles", seed=2)
    spec = LASER_PRESETS["hokuyo_utm30"]
    rng = np.random.default_rng(9)
    free = np.argwhere(world.free)
    sel = free[rng.choice(len(free), 20, replace=False)]
    xs, ys = world.cell_centres()
    poses = np.column_stack([xs[sel[:, 1]], ys[sel[:, 0]], rng.uniform(-np.pi, np.pi, len(sel))])
    sigma = 0.02
    ranges = cast_rays(world, poses, spec, rng=rng, range_noise=sigma)
    hit = np.isfinite(ranges)
    assert np.all((ranges[hit] >= spec.range_min) & (ranges[hit].astype(np.float32) < np.float32(spec.range_max)))
    th = poses[:, 2:3] + spec.angles()[None, :]
    pts = np.stack([poses[:, 0:1] + ranges * np.cos(th), poses[:, 1:2] + ranges * np.sin(th)], -1)[hit]
    oy, ox = np.nonzero(world.occupied)
    tree = cKDTree(np.column_stack([xs[ox], ys[oy]]))
    dist, _ = tree.query(pts)
    assert dist.max() <= world.resolution * math.sqrt(2) / 2 + 6 * sigma


def test_hits_below_range_min_are_clipped_returns():
    """A sensor closer to a wall than range_min reports range_min (a return), never inf."""
    world = _empty_world()
    world.occupied[:, 40:] = True
    spec = LaserSpec("t", 3, -0.1, 0.1, 0.5, 10.0, 10.0, 0.0)
    r = cast_rays(world, [[1.8, 3.0, 0.0]], spec)
    np.testing.assert_allclose(r, 0.5)
