"""ICP covariance (inverse Fisher information) and the residual χ² test, by Monte Carlo with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from registration.config import IcpConfig
from registration.covariance import chi2_test, jacobian_plane, jacobian_point
from registration.icp import icp
from registration.target import IcpTarget

SIGMA = 0.01  # m, residual standard deviation per coordinate

# A room with walls in several directions (x0, y0, x1, y1), metres.
ROOM = np.array([[0, 0, 8, 0], [8, 0, 8, 5], [8, 5, 0, 5], [0, 5, 0, 0], [3, 0, 3, 2.5], [5, 5, 6.5, 3.5]], float)


def sample_segments(segs: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """*n* points uniformly along the segments (by length)."""
    L = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    k = rng.choice(len(segs), n, p=L / L.sum())
    u = rng.uniform(size=n)[:, None]
    s = segs[k]
    return s[:, :2] + u * (s[:, 2:] - s[:, :2])


def dense_segments(segs: np.ndarray, step: float) -> np.ndarray:
    """Points every *step* metres along each segment (a noise-free 'continuous' target)."""
    out = []
    for s in segs:
        L = np.hypot(s[2] - s[0], s[3] - s[1])
        u = np.arange(0.0, L, step)[:, None] / L
        out.append(s[:2] + u * (s[2:] - s[:2]))
    return np.vstack(out)


def nees(T_est: np.ndarray, T_true: np.ndarray, cov: np.ndarray) -> float:
    """NEES of δ = Log(T_est⁻¹ · T_true), i.e. T_true = T_est · Exp(δ) (the right perturbation of
    docs/ARCHITECTURE.md, translation first)."""
    E = geo.relative(T_est, T_true)
    d = geo.se2_log(E) if cov.shape[0] == 3 else geo.se3_log(E)
    return float(d @ np.linalg.solve(cov, d))


@pytest.mark.parametrize("dim", [2, 3])
def test_point_model_nees_is_consistent(dim):
    """Point model, 200 trials: well-separated points, source and target each with isotropic
    Gaussian noise σ/√2 (residual σ per coordinate), random truth. The mean NEES of the ICP
    estimate against its covariance σ²(JᵀJ)⁻¹ lies in [0.8, 1.2]·dof (issue 3 acceptance)."""
    rng = np.random.default_rng(10 + dim)
    cfg = IcpConfig(gates_m=(0.5,), covariance_model="point", sigma_m=SIGMA, tol_translation_m=1e-10, tol_rotation_rad=1e-10)
    vals = []
    for _ in range(200):
        if dim == 2:
            T = geo.se2_exp(rng.normal(size=3) * [0.05, 0.05, 0.02])
        else:
            T = geo.se3_exp(rng.normal(size=6) * [0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
        base = rng.uniform(-5, 5, size=(100 if dim == 2 else 150, dim))
        tgt = base + rng.normal(scale=SIGMA / np.sqrt(2), size=base.shape)
        src = geo.transform_points(geo.inverse(T), base) + rng.normal(scale=SIGMA / np.sqrt(2), size=base.shape)
        r = icp(src, tgt, None, cfg)
        vals.append(nees(r.transform, T, r.covariance))
    dof = 3 if dim == 2 else 6
    assert 0.8 <= np.mean(vals) / dof <= 1.2


def test_plane_model_nees_is_consistent_2d():
    """Plane (line) model, 200 trials: scan-like random points on the walls of a room with
    isotropic noise σ, matched by nearest neighbour against a dense noise-free target. Only the
    normal component of the noise is informative; the mean NEES is within [0.8, 1.2]·3."""
    rng = np.random.default_rng(21)
    tgt = IcpTarget(dense_segments(ROOM, 0.002))
    cfg = IcpConfig(gates_m=(0.3, 0.1), covariance_model="plane", sigma_m=SIGMA, tol_translation_m=1e-9, tol_rotation_rad=1e-9)
    vals = []
    for _ in range(200):
        T = geo.se2_exp(rng.normal(size=3) * [0.05, 0.05, 0.02])
        pts = sample_segments(ROOM, 300, rng) + rng.normal(scale=SIGMA, size=(300, 2))
        r = icp(geo.transform_points(geo.inverse(T), pts), tgt, None, cfg)
        vals.append(nees(r.transform, T, r.covariance))
    assert 0.8 <= np.mean(vals) / 3 <= 1.2


def test_corridor_covariance_is_largest_along_the_corridor():
    """Two parallel walls along x (a corridor 20 m long, 2 m wide): the largest-variance direction
    of the translation covariance is the corridor axis (the aperture problem)."""
    rng = np.random.default_rng(4)
    walls = np.array([[-10, -1, 10, -1], [-10, 1, 10, 1]], float)
    tgt = IcpTarget(dense_segments(walls, 0.01))
    pts = sample_segments(walls * [0.5, 1, 0.5, 1], 300, rng) + rng.normal(scale=SIGMA, size=(300, 2))
    T = geo.xytheta_to_matrix(0.03, 0.02, 0.01)
    r = icp(geo.transform_points(geo.inverse(T), pts), tgt, None, IcpConfig(gates_m=(0.3,), sigma_m=SIGMA))
    ev, V = np.linalg.eigh(r.covariance[:2, :2])
    assert abs(V[0, -1]) > 0.99  # principal axis ≈ x
    assert ev[-1] > 100 * ev[0]


def test_corridor_from_simulated_scan():
    """Same property on simulated SICK scans of the project's 'corridor' world (evaluation.sim):
    a scan 10 cm further along the lower corridor registered to the first; the dominant
    translation-covariance axis is within 20° of the corridor direction (world x)."""
    sim = pytest.importorskip("evaluation.sim")
    world = sim.load_world("corridor")
    spec = sim.LASER_PRESETS["sick_lms"]
    x0, x1, y0, _ = world.extent
    # The lower corridor (2 m wide along the outer wall), a quarter of the way along it.
    a = np.array([x0 + 0.25 * (x1 - x0), y0 + 1.0, 0.0])
    iy, ix = world.cell_of(a[None, :2])
    assert world.free[iy[0], ix[0]]
    b = a + [0.1, 0.0, 0.0]
    rng = np.random.default_rng(0)
    R = sim.cast_rays(world, np.stack([a, b]), spec, rng=rng, range_noise=0.01)
    ang = spec.angles()

    def pts(r):
        ok = np.isfinite(r)
        return np.column_stack([r[ok] * np.cos(ang[ok]), r[ok] * np.sin(ang[ok])])

    res = icp(pts(R[1]), pts(R[0]), np.eye(4), IcpConfig(gates_m=(0.5, 0.2)))
    ev, V = np.linalg.eigh(res.covariance[:2, :2])
    assert abs(V[0, -1]) > np.cos(np.radians(20))


@pytest.mark.parametrize("dim", [2, 3])
def test_jacobians_match_finite_differences(dim):
    """The analytic right-perturbation Jacobians equal central finite differences of the residuals
    r(δ) = T·Exp(δ)·p' − q and e(δ) = nᵀ r(δ)."""
    rng = np.random.default_rng(1)
    P = rng.normal(size=(5, dim))
    Q = rng.normal(size=(5, dim))
    n = rng.normal(size=(5, dim))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    T = geo.se2_exp(rng.normal(size=3)) if dim == 2 else geo.se3_exp(rng.normal(size=6))
    exp = geo.se2_exp if dim == 2 else geo.se3_exp
    dof = 3 if dim == 2 else 6
    Jp, Jn = jacobian_point(P, T[:dim, :dim]), jacobian_plane(P, n, T[:dim, :dim])
    h = 1e-6
    for k in range(dof):
        e = np.zeros(dof)
        e[k] = h
        rp = geo.transform_points(T @ exp(e), P) - Q
        rm = geo.transform_points(T @ exp(-e), P) - Q
        num = (rp - rm) / (2 * h)
        assert np.allclose(Jp[:, :, k], num, atol=1e-7)
        assert np.allclose(Jn[:, k], np.einsum("ij,ij->i", num, n), atol=1e-7)


def test_chi2_false_rejection_rate_matches_configuration():
    """With false_rejection_rate α = 0.05 and the true σ, correct alignments (300 trials, plane
    model) are rejected at a measured rate within the 99.9 % binomial band of α."""
    rng = np.random.default_rng(33)
    tgt = IcpTarget(dense_segments(ROOM, 0.002))
    cfg = IcpConfig(gates_m=(0.3, 0.1), sigma_m=SIGMA, false_rejection_rate=0.05)
    rejected = 0
    n = 300
    for _ in range(n):
        T = geo.se2_exp(rng.normal(size=3) * [0.05, 0.05, 0.02])
        pts = sample_segments(ROOM, 150, rng) + rng.normal(scale=SIGMA, size=(150, 2))
        rejected += not icp(geo.transform_points(geo.inverse(T), pts), tgt, None, cfg).accepted
    band = 3.3 * np.sqrt(0.05 * 0.95 / n)
    assert abs(rejected / n - 0.05) <= band


def test_chi2_rejects_wrong_basin_in_symmetric_room():
    """A rectangular room (8 m × 4 m, symmetric under 180°): started 90° off, ICP (gates 0.5 → 0.2 m)
    converges to a wrong local minimum and the χ² test (course rule, factor 3, true σ) rejects it;
    started near the truth it converges and is accepted. (With a huge first gate ICP may instead
    swing to the 180° alias, which fits as well as the truth: no residual test can reject that.)"""
    rng = np.random.default_rng(8)
    room = np.array([[-4, -2, 4, -2], [4, -2, 4, 2], [4, 2, -4, 2], [-4, 2, -4, -2]], float)
    tgt = IcpTarget(dense_segments(room, 0.005))
    pts = sample_segments(room, 400, rng) + rng.normal(scale=SIGMA, size=(400, 2))
    T = geo.xytheta_to_matrix(0.1, -0.05, 0.05)
    src = geo.transform_points(geo.inverse(T), pts)
    cfg = IcpConfig(gates_m=(0.5, 0.2), sigma_m=SIGMA, min_inliers=10)
    good = icp(src, tgt, np.eye(4), cfg)
    assert good.accepted and np.abs(good.transform - T).max() < 0.01
    bad = icp(src, tgt, geo.xytheta_to_matrix(0.0, 0.0, np.pi / 2), cfg)
    assert not bad.accepted
    assert bad.chi2.residual > bad.chi2.threshold


def test_chi2_test_thresholds():
    """The course rule is Res > 3(n − dof)σ²; with α the threshold is the χ² quantile."""
    v = chi2_test(10.0, 106, 6, 0.02)
    assert v.threshold == pytest.approx(3 * 100 * 0.02)
    from scipy.stats import chi2

    v = chi2_test(10.0, 106, 6, 0.02, false_rejection_rate=0.01)
    assert v.threshold == pytest.approx(0.02 * chi2.ppf(0.99, 100))
