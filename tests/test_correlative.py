"""Correlative scan matching: the pyramid bounds, exactness of branch and bound, recovery of large offsets."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import geometry as G
from core.errors import DegenerateInputError
from registration import correlative as C


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


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n_headings=st.integers(1, 40), resolution=st.sampled_from([0.03, 0.05, 0.1]))
def test_compiled_cells_of_turned_scans_equal_the_numpy_formula(seed, n_headings, resolution):
    """The search's cells of the scan at every heading: the compiled loop does the numpy arithmetic in the same
    order, so every index is the same integer. A wrong axis, sign or offset fails here; a last-bit difference
    (a cell off by one on a boundary) is what the replayed runs' trajectory hashes catch."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-25, 25, (int(rng.integers(3, 300)), 2))
    pyr = C.LikelihoodPyramid(rng.uniform(-20, 20, (80, 2)), resolution, resolution, levels=2)
    thetas, (x0, y0) = rng.uniform(-np.pi, np.pi, n_headings), rng.uniform(-5, 5, 2)
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    turned = np.stack([c * pts[:, 0] - s * pts[:, 1] + x0, s * pts[:, 0] + c * pts[:, 1] + y0], axis=-1)
    expected = np.floor((turned - pyr.origin) / pyr.resolution).astype(np.int64)
    got = C._cells(pts, pyr, x0, y0, thetas)
    assert got.dtype == np.int32 and np.array_equal(got.astype(np.int64), expected)


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


def corridor(rng: np.random.Generator, n: int = 800, length_m: float = 30.0) -> np.ndarray:
    """Two parallel walls 2 m apart along x, jittered off the grid: nothing fixes a shift along x."""
    x = rng.uniform(-length_m / 2, length_m / 2, n)
    y = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    return np.column_stack([x, y]) + rng.normal(0, 0.003, (n, 2)) + 0.0137


@pytest.mark.parametrize("seed", range(3))
def test_ambiguity_is_zero_for_a_sharp_match(seed):
    """In a room with an inner wall and a pillar only the true pose scores best: no slide."""
    rng = np.random.default_rng(seed)
    walls = room(rng)
    pose = G.xytheta_to_matrix(4.0, 3.0, rng.uniform(-np.pi, np.pi))
    scan = G.transform_points(G.inverse(pose), walls[rng.choice(len(walls), 300, replace=False)])
    pyr = C.LikelihoodPyramid(walls, 0.05, 0.05, levels=0)
    assert np.array_equal(C.ambiguity(scan, pyr, pose, 1.0, 0.9), np.zeros((3, 3)))


@pytest.mark.parametrize("heading", [0.0, 0.7, -2.1, np.pi])
def test_ambiguity_of_a_corridor_lies_along_it_in_the_scan_frame(heading):
    """A scan of a long corridor slides along it: the shifts within the ±w square window score alike, so
    the second moment along the corridor is that of a uniform spread over the corridor's chord of the
    square, L²/3 with L = w / max(|cos h|, |sin h|) at heading h (to the grid's discretisation), and
    nothing across it. The corridor runs along the scan's own x whatever the heading (right perturbation)."""
    rng = np.random.default_rng(3)
    pose = G.xytheta_to_matrix(2.0, -1.0, heading)
    scan = corridor(rng, 300, length_m=12.0)  # the sensor sees 12 m of it, the map holds 30 m
    walls = G.transform_points(pose, corridor(rng, 2000))
    pyr = C.LikelihoodPyramid(walls, 0.05, 0.05, levels=0)
    w = 1.0
    S = C.ambiguity(scan, pyr, pose, w, 0.9)
    chord = w / max(abs(np.cos(heading)), abs(np.sin(heading)))
    assert S[0, 0] == pytest.approx(chord**2 / 3, rel=0.15)
    assert S[1, 1] < 0.05**2
    assert abs(S[2, 2]) < np.radians(1.0) ** 2


def test_ambiguity_covers_a_second_peak():
    """The same posts twice, 0.8 m apart along x: a scan of one set also fits the other, so the second
    moment along x is the other peak's share of the near-best poses times 0.8², between a quarter and a
    half of 0.8² for two peaks of one or two grid poses each."""
    rng = np.random.default_rng(4)
    posts = np.array([[0.0, 0.0], [0.0, 1.5], [0.4, 2.2], [-0.3, 0.9]])
    ring = np.vstack([posts + rng.normal(0, 0.002, posts.shape) for _ in range(40)])
    walls = np.vstack([ring, ring + [0.8, 0.0]]) + 0.0137
    pose = G.xytheta_to_matrix(-1.0, 1.0, 0.0)
    scan = G.transform_points(G.inverse(pose), ring + 0.0137)
    pyr = C.LikelihoodPyramid(walls, 0.05, 0.05, levels=0)
    S = C.ambiguity(scan, pyr, pose, 1.0, 0.9)
    assert 0.8**2 / 4 <= S[0, 0] <= 0.8**2 / 2
    assert S[1, 1] < 0.05**2


def test_ambiguity_rejects_too_few_points():
    pyr = C.LikelihoodPyramid(np.array([[0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(DegenerateInputError):
        C.ambiguity(np.zeros((2, 2)), pyr, np.eye(4), 1.0, 0.9)


@pytest.mark.parametrize("seed", range(4))
def test_likelihood_field_is_the_distance_transforms_field(seed):
    """The field stamped around the occupied cells equals rint(255·exp(−d²/2σ²)) (0 beyond 3σ) of the Euclidean
    distance transform of the whole grid, cell for cell (Thrun et al. §6.4)."""
    from scipy.ndimage import distance_transform_edt

    rng = np.random.default_rng(seed)
    res = float(rng.choice([0.05, 0.1]))
    sigma = res * float(rng.choice([1.0, 1.5, 2.0]))
    points = rng.uniform(0, 3, (int(rng.integers(1, 200)), 2))
    pyr = C.LikelihoodPyramid(points, res, sigma, levels=2)
    occupied = np.zeros(pyr.shape, dtype=bool)
    occupied[tuple(pyr.cells(points).T)] = True
    d = distance_transform_edt(~occupied) * res
    expected = np.where(d > 3.0 * sigma, 0, np.rint(np.exp(-0.5 * (d / sigma) ** 2) * 255.0)).astype(np.uint8)
    assert np.array_equal(pyr.grids[0], expected)
