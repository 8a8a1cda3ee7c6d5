"""Correlative scan matching: the pyramid bounds, exactness of branch and bound, recovery of large offsets."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from registration import correlative as C
from registration import geometry as G
from registration.errors import DegenerateInputError


def room(rng: np.random.Generator, n: int = 1200) -> np.ndarray:
    """Walls of a 9 m × 6 m room with an inner wall and a pillar (not symmetric), jittered off the grid."""
    t = rng.uniform(0, 1, n)
    segs = [((0, 0), (9, 0)), ((9, 0), (9, 6)), ((9, 6), (0, 6)), ((0, 6), (0, 0)),
            ((3, 0), (3, 2.5)), ((6, 4), (7.5, 4)), ((6.2, 1.3), (6.6, 1.7))]
    k = rng.integers(0, len(segs), n)
    a = np.array([segs[i][0] for i in k], float)
    b = np.array([segs[i][1] for i in k], float)
    return a + t[:, None] * (b - a) + rng.normal(0, 0.003, (n, 2)) + 0.0137


def test_pyramid_levels_bound_blocks_of_level_zero():
    rng = np.random.default_rng(1)
    pyr = C.LikelihoodPyramid(rng.uniform(0, 4, (60, 2)), 0.1, 0.1, levels=3)
    g0 = pyr.grids[0]
    for h in range(1, 4):
        s = 2**h
        gh = pyr.grids[h]
        for _ in range(200):
            x, y = rng.integers(0, g0.shape[0]), rng.integers(0, g0.shape[1])
            assert gh[x, y] == g0[x:x + s, y:y + s].max()


def test_field_is_one_on_points_and_zero_far_away():
    pts = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 0.5]])
    pyr = C.LikelihoodPyramid(pts, 0.05, 0.05)
    on = pyr.cells(pts)
    assert np.all(pyr.grids[0][on[:, 0], on[:, 1]] == 255)
    far = pyr.cells(np.array([[0.5, 0.5]]))
    assert pyr.grids[0][far[0, 0], far[0, 1]] == 0.0


def brute_force(scan, pyr, guess, window_m, window_rad):
    x0, y0, th0 = G.matrix_to_xytheta(guess)
    step = C.angular_step(scan, pyr.resolution)
    k = int(np.ceil(window_rad / step))
    w = int(np.ceil(window_m / pyr.resolution))
    best = (-1.0, None)
    for th in th0 + step * np.arange(-k, k + 1):
        c, s = np.cos(th), np.sin(th)
        p = np.c_[c * scan[:, 0] - s * scan[:, 1] + x0, s * scan[:, 0] + c * scan[:, 1] + y0]
        cells = pyr.cells(p)
        for dx in range(-w, w + 1):
            for dy in range(-w, w + 1):
                ix = np.clip(cells[:, 0] + dx, 0, pyr.shape[0] - 1)
                iy = np.clip(cells[:, 1] + dy, 0, pyr.shape[1] - 1)
                v = float(pyr.grids[0][ix, iy].mean(dtype=np.float64)) / 255.0
                if v > best[0]:
                    best = (v, (th, dx, dy))
    return best


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), levels=st.integers(0, 5))
def test_branch_and_bound_finds_the_brute_force_maximum(seed, levels):
    rng = np.random.default_rng(seed)
    walls = room(rng, 500)
    truth = G.xytheta_to_matrix(rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.1))
    scan = G.transform_points(G.inverse(truth), walls[rng.choice(len(walls), 60, replace=False)])
    scan += rng.normal(0, 0.02, scan.shape)
    pyr = C.LikelihoodPyramid(walls, 0.1, 0.1, levels=levels)
    found = C.match(scan, pyr, np.eye(4), 0.5, np.radians(6))
    best, _ = brute_force(scan, pyr, np.eye(4), 0.5, np.radians(6))
    assert found.score == pytest.approx(best, abs=1e-6)
    assert found.guess_score <= found.score + 1e-12


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), min_score=st.floats(0.0, 1.0))
def test_min_score_keeps_the_maximum_above_it_and_returns_the_guess_below_it(seed, min_score):
    """Starting the bound at min_score changes nothing when the window's maximum exceeds it; otherwise
    the result is the guess itself, with its (lower) score."""
    rng = np.random.default_rng(seed)
    walls = room(rng, 500)
    truth = G.xytheta_to_matrix(rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.1))
    scan = G.transform_points(G.inverse(truth), walls[rng.choice(len(walls), 60, replace=False)])
    scan += rng.normal(0, 0.02, scan.shape)
    pyr = C.LikelihoodPyramid(walls, 0.1, 0.1, levels=3)
    free = C.match(scan, pyr, np.eye(4), 0.5, np.radians(6))
    bounded = C.match(scan, pyr, np.eye(4), 0.5, np.radians(6), min_score=min_score)
    if free.score > min_score + 1e-9:
        assert bounded.score == pytest.approx(free.score, abs=1e-12)
    elif free.score < min_score - 1e-9:
        assert bounded.score == bounded.guess_score == pytest.approx(free.guess_score, abs=1e-12)
        assert np.array_equal(bounded.transform, np.eye(4))


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), fraction=st.floats(0.0, 2.0))
def test_min_gain_keeps_the_maximum_when_it_beats_the_guess_by_that_much(seed, fraction):
    """The bound starting at guess score + min_gain: the window's maximum when it is that much better than
    the guess, otherwise the guess itself — exactly the decision a caller makes on the unbounded search."""
    rng = np.random.default_rng(seed)
    walls = room(rng, 500)
    truth = G.xytheta_to_matrix(rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.1))
    scan = G.transform_points(G.inverse(truth), walls[rng.choice(len(walls), 60, replace=False)])
    scan += rng.normal(0, 0.02, scan.shape)
    pyr = C.LikelihoodPyramid(walls, 0.1, 0.1, levels=3)
    free = C.match(scan, pyr, np.eye(4), 0.5, np.radians(6))
    min_gain = fraction * (free.score - free.guess_score)  # around the actual gain: both outcomes occur
    bounded = C.match(scan, pyr, np.eye(4), 0.5, np.radians(6), min_gain=min_gain)
    assert bounded.guess_score == free.guess_score
    if free.score >= free.guess_score + min_gain + 1e-9:
        assert bounded.score == pytest.approx(free.score, abs=1e-12)
        assert bounded.score >= bounded.guess_score + min_gain
    elif free.score < free.guess_score + min_gain - 1e-9:
        assert bounded.score == bounded.guess_score
        assert np.array_equal(bounded.transform, np.eye(4))


@pytest.mark.parametrize("seed", range(5))
def test_large_offsets_land_within_one_cell_and_one_angular_step(seed):
    rng = np.random.default_rng(seed)
    walls = room(rng)
    truth = G.xytheta_to_matrix(rng.uniform(-1.3, 1.3), rng.uniform(-1.3, 1.3), rng.uniform(-0.15, 0.15))
    pose = G.xytheta_to_matrix(4.0, 3.0, 0.3)  # sensor inside the room, scan in the sensor frame
    scan = G.transform_points(G.inverse(pose @ truth), walls[rng.choice(len(walls), 300, replace=False)])
    scan += rng.normal(0, 0.01, scan.shape)
    pyr = C.LikelihoodPyramid(walls, 0.05, 0.05)
    found = C.match(scan, pyr, pose, 1.5, np.radians(10))
    err = G.matrix_to_xytheta(G.relative(pose @ truth, found.transform))
    step = C.angular_step(scan, 0.05)
    assert abs(err[2]) <= 1.5 * step
    # A rotation error of one step moves points 4 m from the sensor by ~1 cell; allow two cells.
    assert np.hypot(err[0], err[1]) <= 2 * 0.05 * np.sqrt(2)
    assert found.score > 0.6 > found.guess_score


def test_degenerate_inputs_raise():
    with pytest.raises(DegenerateInputError):
        C.LikelihoodPyramid(np.empty((0, 2)))
    pyr = C.LikelihoodPyramid(np.array([[0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(DegenerateInputError):
        C.match(np.zeros((2, 2)), pyr, np.eye(4), 1.0, 0.1)
