"""Simulator worlds (procedural and map_server) and the planned robot tours."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from core.errors import ConfigError
from evaluation.sim import LASER_PRESETS, load_world
from evaluation.sim.path import plan_path
from tests.conftest import shared_path

SPEC = LASER_PRESETS["fastgpom"]


@pytest.mark.parametrize("name", ["rooms", "corridor", "obstacles", "ring"])
def test_procedural_worlds_deterministic_and_closed(name):
    """Same seed → identical grids; another seed → a different world; the free space reachable from
    the inside never touches an unknown cell or the grid border (outer walls close the world)."""
    a, b, c = load_world(name, seed=4), load_world(name, seed=4), load_world(name, seed=5)
    assert np.array_equal(a.occupied, b.occupied) and np.array_equal(a.known, b.known)
    assert not np.array_equal(a.occupied, c.occupied)
    assert a.resolution == 0.05 and a.occupied.any() and a.free.any()
    labels, _ = ndimage.label(a.free)
    big = np.bincount(labels[labels > 0]).argmax()
    near_unknown = ndimage.binary_dilation(~a.known)
    border = np.ones(a.shape, bool)
    border[1:-1, 1:-1] = False
    assert not ((near_unknown | border) & (labels == big)).any()
    assert (labels == big).sum() > 0.5 * a.free.sum()


def test_resolution_changes_cells_not_geometry():
    """The same seed at 0.05 m and 0.02 m rasterises the same shapes: every occupied cell centre of
    one grid is within one coarse cell diagonal of an occupied cell centre of the other (shapes
    minus carved doors are not convex, so half-diagonals alone do not bound it)."""
    a, b = load_world("rooms", resolution=0.05, seed=1), load_world("rooms", resolution=0.02, seed=1)

    def occ_pts(w):
        xs, ys = w.cell_centres()
        iy, ix = np.nonzero(w.occupied)
        return np.column_stack([xs[ix], ys[iy]])

    pa, pb = occ_pts(a), occ_pts(b)
    tol = 0.05 * math.sqrt(2) + 1e-9
    assert cKDTree(pa).query(pb)[0].max() <= tol
    assert cKDTree(pb).query(pa)[0].max() <= tol


def test_stdr_world_loads_and_resamples():
    """An STDR map becomes a world with the map's size; occupied = map_server class 100, unknown
    transparent; 2× up-sampling keeps every occupied cell (exact nearest-centre resampling)."""
    p = shared_path("stdr_maps", "simple_rooms.yaml")
    w = load_world(str(p))
    assert w.shape == (300, 400) and w.resolution == 0.05 and np.allclose(w.origin_xy, 0)
    w2 = load_world(str(p), resolution=0.025)
    assert w2.shape == (600, 800)
    np.testing.assert_array_equal(w2.occupied[::2, ::2], w.occupied)
    s = load_world(str(shared_path("stdr_maps", "sparse_obstacles.kuanghaofei_fork.yaml")))
    assert np.allclose(s.origin_xy, [-7.75, -7.46]) and (~s.known).any()


def test_unknown_world_name():
    """A name that is neither a built-in world nor an existing file is a ConfigError."""
    with pytest.raises(ConfigError, match="unknown world"):
        load_world("nowhere")


def _nonfree_tree(world):
    iy, ix = np.nonzero(~world.free)
    xs, ys = world.cell_centres()
    return cKDTree(np.column_stack([xs[ix], ys[iy]]))


@pytest.mark.parametrize("name,res", [("rooms", 0.05), ("corridor", 0.05), ("obstacles", 0.04)])
def test_path_collision_free_bounded_and_revisiting(name, res):
    """The tour keeps ≥ robot radius from every occupied/unknown cell (checked at poses and
    midpoints against cell squares), respects the speed and acceleration limits, and revisits: two poses
    ≥ 10 m of travel apart lie within 1 m of each other."""
    world = load_world(name, resolution=res, seed=2)
    radius, v, w = 0.2, 0.5, 1.0
    p = plan_path(world, 1500, SPEC, np.random.default_rng(3), robot_radius=radius, max_speed=v, max_turn_rate=w)
    assert p.shape == (1500, 3)
    tree = _nonfree_tree(world)
    mids = 0.5 * (p[1:, :2] + p[:-1, :2])
    d, _ = tree.query(np.vstack([p[:, :2], mids]))
    assert d.min() - world.resolution * math.sqrt(2) / 2 >= radius
    iy, ix = world.cell_of(p[:, :2])
    assert world.free[iy, ix].all()
    steps = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    dth = np.abs((np.diff(p[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
    assert steps.max() <= v * SPEC.period + 1e-9 and dth.max() <= w * SPEC.period + 1e-9
    # bounded accelerations (0.5 m/s², 2 rad/s²): mean speeds of consecutive intervals differ by ≤ a·dt
    dt = SPEC.period
    assert np.abs(np.diff(steps / dt)).max() <= 0.5 * dt + 1e-9
    assert np.abs(np.diff(dth / dt)).max() <= 2.0 * dt + 1e-9
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    pair_d = np.linalg.norm(p[:, None, :2] - p[None, :, :2], axis=-1)
    far_in_travel = np.abs(travel[:, None] - travel[None, :]) >= 10.0
    assert (pair_d[far_in_travel] <= 1.0).any()
    assert travel[-1] > 30.0  # it actually moves through the world


def test_short_budget_still_returns():
    """With only 100 scans (10 s) the robot goes out and comes back: the last pose is within 0.2 m
    of the first though it moved ≥ 0.5 m away."""
    world = load_world("obstacles", seed=1)
    p = plan_path(world, 100, SPEC, np.random.default_rng(0))
    assert p.shape == (100, 3)
    far = np.linalg.norm(p[:, :2] - p[0, :2], axis=1)
    assert far.max() >= 0.5 and far[-1] <= 0.2


def test_path_deterministic_for_rng_seed():
    """The same rng seed gives the same path; another seed another path."""
    world = load_world("rooms", seed=0)
    a = plan_path(world, 400, SPEC, np.random.default_rng(7))
    b = plan_path(world, 400, SPEC, np.random.default_rng(7))
    c = plan_path(world, 400, SPEC, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_ring_world_is_four_loops_of_corridors_44_to_56_m_across(seed):
    """A square ring crossed by two corridors: its free space is one piece around exactly four solid blocks (four
    independent loops), within a square of 44–56 m, and no corridor is narrower than the robot needs (the
    distance to the nearest non-free cell reaches 1.1 m: 2.4 m corridors)."""
    w = load_world("ring", seed=seed)
    _, n_free = ndimage.label(w.free)
    assert n_free == 1
    _, n_solid = ndimage.label(~w.free)
    assert n_solid == 5  # the outer walls with the unknown margin, and the four blocks
    xs, ys = w.cell_centres()
    iy, ix = np.nonzero(w.free)
    span = max(xs[ix].max() - xs[ix].min(), ys[iy].max() - ys[iy].min())
    assert 44.0 - 0.5 <= span <= 56.0 + 1.0
    assert ndimage.distance_transform_edt(w.free).max() * w.resolution >= 1.1
