"""SVD-ICP, point-to-plane ICP and voxel subsampling: synthetic identities and real scans."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import geometry as geo
from core.errors import DegenerateInputError, GeometryError
from registration.config import IcpConfig
from registration.icp import icp
from registration.point_to_plane import icp_point_to_plane
from registration.target import IcpTarget, estimate_normals
from registration.voxel import voxel_downsample
from tests.conftest import DATA, shared_path


def _box(step: float, L=(6.0, 4.0, 3.0)) -> np.ndarray:
    """Points on the six faces of a box centred at 0 (a room)."""
    out = []
    for ax in range(3):
        a, b = [i for i in range(3) if i != ax]
        A, B = np.meshgrid(np.arange(0, L[a] + 1e-9, step), np.arange(0, L[b] + 1e-9, step))
        for v in (0.0, L[ax]):
            p = np.zeros((A.size, 3))
            p[:, a], p[:, b], p[:, ax] = A.ravel(), B.ravel(), v
            out.append(p)
    return np.vstack(out) - np.array(L) / 2


def test_icp_recovers_noise_free_3d_transform():
    """Identical noise-free clouds, source moved by a known pose: ICP from identity returns the
    inverse motion to 1e-9 with RMSE ≈ 0 and fitness 1."""
    rng = np.random.default_rng(0)
    P = rng.uniform(-5, 5, size=(2000, 3))
    T = geo.se3_exp([0.2, -0.1, 0.05, 0.02, -0.03, 0.08])
    r = icp(geo.transform_points(geo.inverse(T), P), P, None, IcpConfig(gates_m=(1.0, 0.5), tol_translation_m=1e-12, tol_rotation_rad=1e-12))
    assert np.abs(r.transform - T).max() < 1e-9
    assert r.rmse < 1e-9 and r.fitness == 1.0 and r.converged


def test_icp_2d_returns_planar_pose_and_uses_initial_guess():
    """A 2D scan displaced by 2 m and 60°: from identity the alignment fails or is wrong, from a
    guess within the basin it is exact; the result is a planar 4×4 pose."""
    rng = np.random.default_rng(1)
    P = rng.uniform(-10, 10, size=(500, 2))
    T = geo.xytheta_to_matrix(2.0, -1.0, np.radians(60))
    src = geo.transform_points(geo.inverse(T), P)
    r = icp(src, P, T @ geo.xytheta_to_matrix(0.05, 0.05, 0.02), IcpConfig(gates_m=(0.5, 0.2)))
    assert np.abs(r.transform - T).max() < 1e-9
    assert r.transform[2, 3] == 0 and np.allclose(r.transform[2, :3], [0, 0, 1])


@pytest.mark.parametrize("robust", ["trim", "huber", "cauchy"])
def test_robust_weights_reject_outliers(robust):
    """20 % of the source replaced by gross outliers (within the gate): the robust variants still
    recover the pose to 1 mm, while the unweighted one is pulled off."""
    rng = np.random.default_rng(2)
    P = rng.uniform(-5, 5, size=(1000, 2))
    T = geo.xytheta_to_matrix(0.05, 0.02, 0.01)
    src = geo.transform_points(geo.inverse(T), P)
    out = rng.choice(1000, 200, replace=False)
    src[out] += rng.uniform(-0.4, 0.4, size=(200, 2))
    base = IcpConfig(gates_m=(0.5, 0.3), robust_scale_m=0.02, trim_fraction=0.75, max_iterations=200)
    good = icp(src, P, None, base.model_copy(update={"robust": robust}))
    assert np.linalg.norm(good.transform[:2, 3] - T[:2, 3]) < 1e-3
    plain = icp(src, P, None, base)
    assert np.linalg.norm(plain.transform[:2, 3] - T[:2, 3]) > np.linalg.norm(good.transform[:2, 3] - T[:2, 3])


def test_point_to_plane_recovers_box_motion():
    """Point-to-plane ICP on a sampled box room (normals by PCA) recovers a known 6-DoF motion to
    1e-6 m / 1e-6 rad in a few iterations (Chen & Medioni converge quadratically on planes)."""
    P = _box(0.1)
    T = geo.se3_exp([0.1, -0.05, 0.03, 0.01, -0.02, 0.03])
    src = geo.transform_points(geo.inverse(T), P)[::3]
    r = icp_point_to_plane(src, P, None, IcpConfig(gates_m=(0.5, 0.2), tol_translation_m=1e-10, tol_rotation_rad=1e-10))
    E = geo.se3_log(geo.relative(T, r.transform))
    assert np.abs(E).max() < 1e-6
    assert r.iterations < 20


def test_pca_normals_of_planes():
    """PCA normals of points on z = 0 are ±e_z; in 2D the normal of a line is perpendicular to it."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-1, 1, size=(500, 2)), np.zeros(500)])
    n = estimate_normals(P, cKDTree(P), 10)
    assert np.allclose(np.abs(n[:, 2]), 1.0)
    th = 0.7
    u = rng.uniform(0, 5, 300)
    L = np.column_stack([u * np.cos(th), u * np.sin(th)])
    n2 = estimate_normals(L, cKDTree(L), 8)
    assert np.abs(n2 @ [np.cos(th), np.sin(th)]).max() < 1e-9


def test_voxel_downsample_properties():
    """Voxel subsampling keeps exactly one point per occupied voxel, every input point shares a
    voxel with an output point, and centroids are the voxel means."""
    rng = np.random.default_rng(4)
    P = rng.uniform(0, 3, size=(5000, 3))
    for mode in ("first", "centroid"):
        Q = voxel_downsample(P, 0.5, mode=mode)
        kin = {tuple(k) for k in np.floor(P / 0.5).astype(int)}
        kout = [tuple(k) for k in np.floor(Q / 0.5).astype(int)]
        assert len(kout) == len(set(kout)) == len(kin) and set(kout) == kin
    Q = voxel_downsample(np.array([[0.1, 0.1], [0.3, 0.3], [1.2, 0.1]]), 1.0, mode="centroid")
    assert np.allclose(sorted(map(tuple, Q)), [(0.2, 0.2), (1.2, 0.1)])
    with pytest.raises(GeometryError):
        voxel_downsample(P, -1.0)


@pytest.mark.parametrize("batch", [1, 700, 2500, 10**9])
def test_voxel_downsample_in_batches_is_the_one_shot_result(batch):
    """Reducing batch by batch, then the reductions, keeps the very points and order of one reduction of the
    whole (the first point of each voxel), whatever the batch size and however the parts split voxels."""
    from registration.voxel import voxel_downsample_stream

    rng = np.random.default_rng(9)
    parts = [rng.uniform(-2, 2, size=(int(n), 3)) + rng.uniform(-1, 1, 3) for n in rng.integers(1, 400, 30)]
    one = voxel_downsample(np.vstack(parts), 0.3)
    assert np.array_equal(voxel_downsample_stream(iter(parts), 0.3, batch_points=batch), one)


def test_too_few_pairs_within_gate_raises():
    """Clouds farther apart than the gate give a DegenerateInputError naming the gate."""
    P = np.random.default_rng(5).uniform(0, 1, size=(100, 3))
    with pytest.raises(DegenerateInputError, match="within"):
        icp(P + 10.0, P, None, IcpConfig(gates_m=(0.5,)))


def test_matches_open3d_fixed_point_on_real_intel_scans():
    """Consecutive real Intel scans (data/intel.clf.bz2), wheel-odometry guess, 0.5 m gate:
    our point-to-point fixed point equals Open3D's registration_icp to 1 mm / 0.01°."""
    o3d = pytest.importorskip("open3d")
    from slam.logs import open_log

    frames = []
    for f in open_log(DATA / "intel.clf.bz2").frames():
        if f.index >= 100:
            frames.append(f)
        if len(frames) == 6:
            break
    for a, b in zip(frames[:-1], frames[1:]):
        init = geo.relative(a.odom, b.odom)
        ours = icp(b.points, a.points, init, IcpConfig(gates_m=(0.5,), max_iterations=300, tol_translation_m=1e-10, tol_rotation_rad=1e-10))
        pc = []
        for P in (b.points, a.points):
            c = o3d.geometry.PointCloud()
            c.points = o3d.utility.Vector3dVector(np.column_stack([P, np.zeros(len(P))]))
            pc.append(c)
        crit = o3d.pipelines.registration.ICPConvergenceCriteria(1e-12, 1e-12, 300)
        ref = o3d.pipelines.registration.registration_icp(
            pc[0], pc[1], 0.5, init, o3d.pipelines.registration.TransformationEstimationPointToPoint(), crit)
        E = geo.relative(ref.transformation, ours.transform)
        assert np.linalg.norm(E[:3, 3]) <= 1e-3
        assert np.degrees(abs(geo.matrix_to_xytheta(E)[2])) <= 0.01


def test_point_to_plane_on_real_kitti_pair_moves_forward():
    """Real KITTI frames 1→2 (../shared/data): point-to-plane ICP from identity finds a forward
    motion of 0.6–0.9 m with < 0.5° rotation and a positive-definite covariance. (The tighter
    ground-truth comparison is in benchmarks/registration.py; see the report there.)"""
    from slam.logs import open_log

    seq = shared_path("kitti_odometry_00_sample", "sequences", "00")
    it = open_log(seq).frames()
    f0, f1 = next(it), next(it)
    tgt = IcpTarget(f0.points, voxel_m=0.5, normal_neighbors=10)
    r = icp_point_to_plane(voxel_downsample(f1.points, 0.5), tgt, None, IcpConfig(gates_m=(1.0, 0.5), max_iterations=60))
    assert 0.6 < r.transform[0, 3] < 0.9
    assert np.degrees(np.linalg.norm(geo.so3_log(r.transform[:3, :3]))) < 0.5
    assert np.all(np.linalg.eigvalsh(r.covariance) > 0)


def _room_2d(step: float = 0.05) -> np.ndarray:
    """A 2D room outline (8 m × 5 m) with a pillar: constrains x, y and θ."""
    s = np.arange(0.0, 1.0, step / 8.0)
    walls = [np.column_stack([-4 + 8 * s, np.full_like(s, -2.5)]), np.column_stack([-4 + 8 * s, np.full_like(s, 2.5)]),
             np.column_stack([np.full_like(s, -4.0), -2.5 + 5 * s]), np.column_stack([np.full_like(s, 4.0), -2.5 + 5 * s])]
    a = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    return np.vstack(walls + [np.column_stack([1.0 + 0.4 * np.cos(a), 0.5 + 0.4 * np.sin(a)])])


_EXACT = IcpConfig(gates_m=(0.5, 0.2), tol_translation_m=1e-12, tol_rotation_rad=1e-12, max_iterations=100)


def test_prior_of_zero_information_changes_nothing_and_a_stiff_prior_wins(monkeypatch):
    """The MAP step's two limits: a prior of zero information gives the plain point-to-plane result
    of the same (numpy) loop bit for bit, and the compiled 2D loop's to rounding; a prior of 10¹²
    information pins the pose to the prior's mean (1e-6) however well the points say otherwise."""
    from registration import alignment
    from registration.point_to_plane import PosePrior

    P = _room_2d()
    T = geo.xytheta_to_matrix(0.12, -0.05, 0.03)
    src = geo.transform_points(geo.inverse(T), P)
    compiled = icp_point_to_plane(src, P, None, _EXACT)
    monkeypatch.setattr(alignment, "COMPILED_2D", False)
    plain = icp_point_to_plane(src, P, None, _EXACT)
    assert np.abs(plain.transform - T).max() < 1e-9
    assert np.abs(compiled.transform - plain.transform).max() < 1e-12
    zero = icp_point_to_plane(src, P, None, _EXACT, prior=PosePrior(np.eye(4), np.zeros((3, 3))))
    np.testing.assert_array_equal(zero.transform, plain.transform)
    Pm = geo.xytheta_to_matrix(0.08, 0.0, 0.01)
    stiff = icp_point_to_plane(src, P, None, _EXACT, prior=PosePrior(Pm, np.eye(3) * 1e12))
    assert np.abs(geo.se2_log(geo.relative(Pm, stiff.transform))).max() < 1e-6


def test_prior_shifts_the_estimate_by_the_gaussian_product_formula():
    """Noise-free points and a prior 2 cm / 0.3° off the truth: the MAP pose is the information-weighted
    mean ξ* = (H + Λ)⁻¹ Λ ξ_p (to first order in the offset), with H = Σ JᵀJ the points' information at the
    truth — the closed form of two Gaussians' product — so a weak prior moves the estimate little and a
    strong one moves it most of the way."""
    from registration.point_to_plane import PosePrior

    P = _room_2d()
    T = geo.xytheta_to_matrix(0.12, -0.05, 0.03)
    src = geo.transform_points(geo.inverse(T), P)
    # Point information at the truth: each source point lands on its own target point, whose PCA normal
    # is the wall's (the pillar's radial direction); rows [nᵀ, m × n] for a left increment.
    tree = cKDTree(P)
    n = estimate_normals(P, tree, k=_EXACT.normal_neighbors)
    moved = geo.transform_points(T, src)
    nn = n[tree.query(moved)[1]]
    J = np.column_stack([nn, moved[:, 0] * nn[:, 1] - moved[:, 1] * nn[:, 0]])
    H = J.T @ J
    xi_p = np.array([0.02, -0.01, np.radians(0.3)])
    for scale in (0.01, 0.1, 1.0):
        Lam = scale * np.diag(np.diag(H))
        r = icp_point_to_plane(src, P, None, _EXACT, prior=PosePrior(T @ geo.se2_exp(xi_p), Lam))
        got = geo.se2_log(geo.relative(T, r.transform))
        want = np.linalg.solve(H + Lam, Lam @ xi_p)
        # 8 % of the shift: the residual is the second-order term (normals and lever arms move with ξ).
        np.testing.assert_allclose(got, want, atol=0.08 * np.abs(want).max())


def test_prior_holds_the_pose_along_a_featureless_corridor():
    """Two parallel walls say nothing about motion along them: without a prior the normal equations are
    singular (or the pose slides), with one the along-corridor coordinate is the prior's while the
    across-corridor offset and the heading come from the walls."""
    from core.errors import DegenerateInputError
    from registration.point_to_plane import PosePrior

    x = np.arange(-10.0, 10.0, 0.05)
    P = np.vstack([np.column_stack([x, np.full_like(x, -1.0)]), np.column_stack([x, np.full_like(x, 1.0)])])
    T = geo.xytheta_to_matrix(0.3, 0.04, 0.02)
    src = geo.transform_points(geo.inverse(T), P)[40:-40]  # the scan sees a shorter stretch of both walls
    Pm = geo.xytheta_to_matrix(0.22, 0.0, 0.0)  # the wheels: 8 cm short, no sideways motion, no turn
    r = icp_point_to_plane(src, P, None, _EXACT, prior=PosePrior(Pm, np.diag([1.0, 1.0, 1.0])))
    x_r, y_r, th_r = geo.matrix_to_xytheta(r.transform)
    assert abs(th_r - 0.02) < 1e-4 and abs(y_r - 0.04) < 1e-3
    assert abs(x_r - 0.22) < 1e-3
    with pytest.raises(DegenerateInputError):
        icp_point_to_plane(src, P, None, _EXACT)
