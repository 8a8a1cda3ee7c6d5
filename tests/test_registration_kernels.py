"""The compiled 2D kernels (registration.kernels) against the numpy / scipy implementations they replace
on hot paths: the same neighbours, normals, ICP poses and correlative scores."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import geometry as geo
from core.errors import DegenerateInputError
from registration import alignment, kernels
from registration.config import IcpConfig
from registration.correlative import LikelihoodPyramid
from registration.point_to_plane import icp_point_to_plane
from registration.target import IcpTarget, estimate_normals, gated_nearest


def _scan_like(rng: np.random.Generator, n: int = 1500) -> np.ndarray:
    """Wall segments of random orientation with 1 cm noise, plus scattered clutter."""
    segs = []
    for _ in range(12):
        a, L = rng.uniform(0, np.pi), rng.uniform(1, 8)
        c = rng.uniform(-10, 10, 2)
        s = rng.uniform(-0.5, 0.5, n // 15)[:, None] * L
        segs.append(c + s * np.array([np.cos(a), np.sin(a)]))
    segs.append(rng.uniform(-12, 12, (n // 10, 2)))
    P = np.vstack(segs)
    return P + rng.normal(0, 0.01, P.shape)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("gate", [0.05, 0.3, 1.0, 5.0])
def test_grid_nearest_within_gate_equals_the_kd_tree(seed, gate):
    rng = np.random.default_rng(seed)
    P = _scan_like(rng)
    Q = rng.uniform(-16, 16, (3000, 2))  # many queries outside the points' bounding box
    tgt = IcpTarget(P)
    got = gated_nearest(tgt, Q, gate)
    want = cKDTree(P).query(Q, k=1, distance_upper_bound=gate)[1]
    np.testing.assert_array_equal(got, want)
    assert (got == len(P)).any() and (got < len(P)).any()


@pytest.mark.parametrize("cell", [0.05, 0.25, 3.0])
def test_grid_search_is_exact_whatever_the_cell_size(cell):
    rng = np.random.default_rng(7)
    P = _scan_like(rng, 600)
    g = kernels.PointGrid(P, cell=cell)
    Q = rng.uniform(-12, 12, (2000, 2))
    got = kernels.nearest_within(Q, g.points, *g.args(), 0.8)
    want = cKDTree(P).query(Q, k=1, distance_upper_bound=0.8)[1]
    want[want == len(P)] = -1
    np.testing.assert_array_equal(got, want)


def test_a_grid_over_a_huge_span_coarsens_its_cells():
    P = np.array([[0.0, 0.0], [5000.0, 3.0], [2500.0, 1.0]])
    g = kernels.PointGrid(P, cell=0.25)
    assert g.nx * g.ny <= kernels.MAX_CELLS + 2 * (g.nx + g.ny)
    assert kernels.nearest_within(np.array([[4999.0, 3.0]]), g.points, *g.args(), 2.0)[0] == 1


@pytest.mark.parametrize("k", [3, 8, 10])
def test_grid_normals_equal_the_kd_tree_pca_normals(k):
    rng = np.random.default_rng(k)
    P = _scan_like(rng)
    got = IcpTarget(P, normal_neighbors=k).normals()
    want = estimate_normals(P, cKDTree(P), k)
    # The sign of a normal is arbitrary; both use the same formula, so they agree to rounding.
    assert np.abs(np.abs(np.einsum("ij,ij->i", got, want)) - 1.0).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)


def test_normals_with_k_at_least_the_point_count_use_every_point():
    P = np.array([[0.0, 0.0], [1.0, 0.01], [2.0, 0.0], [3.0, 0.02]])
    got = IcpTarget(P, normal_neighbors=10).normals()
    want = estimate_normals(P, cKDTree(P), 10)
    assert np.abs(np.abs(np.einsum("ij,ij->i", got, want)) - 1.0).max() < 1e-12


def _room(step: float = 0.05) -> np.ndarray:
    s = np.arange(0.0, 1.0, step / 8.0)
    walls = [np.column_stack([-4 + 8 * s, np.full_like(s, -2.5)]), np.column_stack([-4 + 8 * s, np.full_like(s, 2.5)]),
             np.column_stack([np.full_like(s, -4.0), -2.5 + 5 * s]), np.column_stack([np.full_like(s, 4.0), -2.5 + 5 * s])]
    a = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    return np.vstack(walls + [np.column_stack([1.0 + 0.4 * np.cos(a), 0.5 + 0.4 * np.sin(a)])])


def _noisy_scan(seed: int):
    """The room, 300 of its points seen from a pose 0.3 m / 6° off (returned), with 2 cm noise and 10 % outliers."""
    rng = np.random.default_rng(seed)
    P = _room()
    T = geo.xytheta_to_matrix(*rng.uniform(-0.3, 0.3, 2), rng.uniform(-0.1, 0.1))
    src = geo.transform_points(geo.inverse(T), P[rng.choice(len(P), 300, replace=False)])
    src = src + rng.normal(0, 0.02, src.shape)
    src[:30] += rng.uniform(-1, 1, (30, 2))
    return P, src, T


@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("loop, gates", [("plane", (1.0, 0.4, 0.15)), ("point", (0.5,)), ("point", (1.0, 0.4, 0.15))])
def test_compiled_2d_icp_equals_the_numpy_loop(monkeypatch, robust, seed, loop, gates):
    """The compiled 2D loops (registration.kernels_icp: plane_icp_2d, point_icp_2d) against the numpy iterations they
    replace: the same pose (to rounding, 1e-9 at least), iterations, convergence, inliers and covariance,
    from a start 0.3 m / 6° off, with 2 cm noise and 10 % outliers. The point-to-point loops run to the
    fixed point (tolerance 1e-10; unweighted they stop where the matches repeat)."""
    from registration.icp import icp

    P, src, T = _noisy_scan(seed)
    if loop == "plane":
        align, fit = icp_point_to_plane, dict(max_iterations=40, tol_translation_m=1e-6, tol_rotation_rad=1e-6, normal_neighbors=8)
    else:
        align, fit = icp, dict(max_iterations=300, tol_translation_m=1e-10, tol_rotation_rad=1e-10)
    cfg = IcpConfig(gates_m=gates, robust=robust, robust_scale_m=0.06, sigma_m=0.03, workers=1, **fit)
    fast = align(src, P, None, cfg)
    monkeypatch.setattr(alignment, "COMPILED_2D", False)
    ref = align(src, P, None, cfg)
    plane = loop == "plane"
    assert np.abs(fast.transform - ref.transform).max() < (1e-10 if plane else 1e-9)
    assert (fast.iterations, fast.converged, fast.inliers) == (ref.iterations, ref.converged, ref.inliers)
    np.testing.assert_allclose(fast.covariance, ref.covariance, rtol=1e-8 if plane else 1e-7, atol=1e-16)
    assert np.abs(geo.se2_log(geo.relative(T, fast.transform))).max() < (0.01 if plane else 0.02)


@pytest.mark.parametrize("compiled", [True, False])
def test_both_2d_point_to_point_loops_refuse_too_few_pairs(monkeypatch, compiled):
    from registration.icp import icp

    monkeypatch.setattr(alignment, "COMPILED_2D", compiled)
    P = _room()
    with pytest.raises(DegenerateInputError, match=r"ICP iteration 1: 0 pairs within 1.0 m \(need 10\)"):
        icp(P + 50.0, P, None, IcpConfig(gates_m=(1.0, 0.5)))


@pytest.mark.parametrize("compiled", [True, False])
def test_both_2d_loops_refuse_too_few_pairs_and_a_singular_system(monkeypatch, compiled):
    monkeypatch.setattr(alignment, "COMPILED_2D", compiled)
    P = _room()
    far = P + 50.0
    with pytest.raises(DegenerateInputError, match=r"iteration 1: 0 pairs within 1.0 m \(need 10\)"):
        icp_point_to_plane(far, P, None, IcpConfig(gates_m=(1.0, 0.5)))
    line = np.column_stack([np.linspace(0, 5, 100), np.zeros(100)])  # slides along x: no x information
    with pytest.raises(DegenerateInputError, match="singular normal equations"):
        icp_point_to_plane(line, line, None, IcpConfig(gates_m=(0.5,)))


def test_compiled_correlative_scores_equal_their_definition():
    """Mean of the level grid at the clipped shifted cells, / 255 — checked at every level, with
    offsets that push points off the grid on every side."""
    rng = np.random.default_rng(3)
    pyr = LikelihoodPyramid(_scan_like(rng, 800), 0.1, 0.1, levels=4)
    H, W = pyr.shape
    cells = rng.integers(-5, max(H, W) + 5, (7, 180, 2)).astype(np.int32)
    rot = rng.integers(0, 7, 500)
    off = rng.integers(-40, 40, (500, 2))
    for level in range(pyr.levels + 1):
        g = pyr.grids[level]
        ix = np.clip(cells[rot, :, 0] + off[:, None, 0], 0, H - 1)
        iy = np.clip(cells[rot, :, 1] + off[:, None, 1], 0, W - 1)
        want = g[ix, iy].astype(np.float64).mean(axis=1) / 255.0
        np.testing.assert_array_equal(pyr.score_candidates(level, cells, rot, off), want)


@pytest.mark.parametrize("resolution,sigma", [(0.1, 0.1), (0.05, 0.05), (0.05, 0.12), (0.1, 0.07)])
def test_likelihood_field_equals_the_distance_transform_definition(resolution, sigma):
    """The stamped field is rint(255·exp(−d²/2σ²)), 0 beyond 3σ, with d from a Euclidean distance
    transform of the whole grid — bit for bit."""
    from scipy import ndimage

    from registration.correlative import likelihood_field

    rng = np.random.default_rng(11)
    reach = int(np.ceil(3.0 * sigma / resolution))
    shape = (90, 70)
    cells = np.column_stack([rng.integers(reach, shape[0] - reach, 300), rng.integers(reach, shape[1] - reach, 300)])
    occupied = np.zeros(shape, dtype=bool)
    occupied[cells[:, 0], cells[:, 1]] = True
    d = ndimage.distance_transform_edt(~occupied) * resolution
    field = np.exp(-0.5 * (d / sigma) ** 2)
    field[d > 3.0 * sigma] = 0.0
    np.testing.assert_array_equal(likelihood_field(cells, shape, resolution, sigma), np.rint(field * 255.0).astype(np.uint8))
