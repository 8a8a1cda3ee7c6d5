"""Property tests of core.geometry: round trips, group laws, agreement with GTSAM."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import geometry as G
from core import pose_formats
from core.errors import GeometryError

finite = st.floats(-50.0, 50.0, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False, exclude_max=True)


def random_poses(rng, n):
    t = rng.normal(size=(n, 3)) * 5.0
    q = rng.normal(size=(n, 4))
    return pose_formats.pose_from_quat(t, q)


def test_inverse_is_group_inverse(rng):
    """T · T⁻¹ = I for a stack of random poses, and inverse is an involution."""
    T = random_poses(rng, 50)
    np.testing.assert_allclose(T @ G.inverse(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(G.inverse(G.inverse(T)), T, atol=1e-12)
    assert G.is_pose(T)


def test_relative_then_compose_recovers(rng):
    """a_T_b ⊕ (a_T_b ⊖ a_T_c) = a_T_c."""
    A, C = random_poses(rng, 20), random_poses(rng, 20)
    np.testing.assert_allclose(A @ G.relative(A, C), C, atol=1e-11)


def test_compose_is_associative(rng):
    """(AB)C = A(BC) for random poses."""
    A, B, C = random_poses(rng, 3)
    np.testing.assert_allclose(G.compose(G.compose(A, B), C), G.compose(A, G.compose(B, C)), atol=1e-12)


@given(finite, finite, angle)
def test_xytheta_round_trip(x, y, th):
    """(x, y, θ) → matrix → (x, y, θ) is the identity for θ in [−π, π)."""
    v = G.matrix_to_xytheta(G.xytheta_to_matrix(x, y, th))
    np.testing.assert_allclose(v[:2], [x, y], atol=1e-12)
    assert abs(G.wrap_angle(v[2] - th)) < 1e-12


def test_quaternion_round_trip_and_sign(rng):
    """R → q → R is exact, and q and −q give the same rotation (qw ≥ 0 chosen)."""
    q = rng.normal(size=(200, 4))
    R = G.quat_to_rotation(q)
    q2 = G.rotation_to_quat(R)
    assert np.all(q2[:, 3] >= 0)
    np.testing.assert_allclose(G.quat_to_rotation(q2), R, atol=1e-12)
    np.testing.assert_allclose(G.quat_to_rotation(-q), R, atol=1e-12)


def test_quaternion_near_pi_rotations():
    """Shepperd's method is stable for 180° rotations, where the trace formula divides by ~0."""
    for axis in np.eye(3):
        R = G.so3_exp(axis * np.pi)
        np.testing.assert_allclose(G.quat_to_rotation(G.rotation_to_quat(R)), R, atol=1e-12)


def test_zero_quaternion_raises():
    with pytest.raises(GeometryError):
        G.quat_to_rotation([0, 0, 0, 0])


def test_so3_exp_log_round_trip(rng):
    """Log(Exp(w)) = w for |w| < π, including tiny angles."""
    w = rng.normal(size=(300, 3))
    w *= (rng.uniform(0, np.pi - 1e-3, size=300) / np.linalg.norm(w, axis=1))[:, None]
    w[:5] *= 1e-9
    np.testing.assert_allclose(G.so3_log(G.so3_exp(w)), w, atol=1e-10)


def test_rotation_angle_is_the_norm_of_the_rotation_vector(rng):
    """rotation_angle(Exp(w)) = |w| for |w| in [0, π], tiny and near-π angles included."""
    w = rng.normal(size=(300, 3))
    ang = rng.uniform(0, np.pi, size=300)
    ang[:5] = [0.0, 1e-12, 1e-7, np.pi - 1e-7, np.pi]
    w *= (ang / np.linalg.norm(w, axis=1))[:, None]
    got = np.array([G.rotation_angle(R) for R in G.so3_exp(w)])
    np.testing.assert_allclose(got, ang, atol=1e-12, rtol=1e-10)
    np.testing.assert_allclose(G.rotation_angles(G.so3_exp(w)), ang, atol=1e-12, rtol=1e-10)
    assert G.rotation_angles(G.so3_exp(w).reshape(10, 30, 3, 3)).shape == (10, 30)


def test_se3_exp_log_round_trip_and_matches_gtsam(rng):
    """se3_log inverts se3_exp, and both equal gtsam.Pose3.Expmap/Logmap up to the (φ, ρ) ordering."""
    xi = rng.normal(size=(50, 6))
    phi_norm = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 3.0 / phi_norm)  # keep |φ| < π, where Log is single-valued
    T = G.se3_exp(xi)
    np.testing.assert_allclose(G.se3_log(T), xi, atol=1e-9)
    for k in range(10):
        g = gtsam.Pose3.Expmap(np.r_[xi[k, 3:], xi[k, :3]]).matrix()
        np.testing.assert_allclose(T[k], g, atol=1e-10)


def test_se2_exp_log_round_trip_and_matches_gtsam(rng):
    """se2_log(se2_exp(ξ)) = ξ and se2_exp equals gtsam.Pose2.Expmap (same (x, y, θ) order)."""
    xi = rng.normal(size=(50, 3))
    xi[:, 2] = np.clip(xi[:, 2], -3.0, 3.0)
    np.testing.assert_allclose(G.se2_log(G.se2_exp(xi)), xi, atol=1e-10)
    for k in range(10):
        g = gtsam.Pose2.Expmap(xi[k])
        np.testing.assert_allclose(G.matrix_to_xytheta(G.se2_exp(xi[k])), [g.x(), g.y(), g.theta()], atol=1e-10)


def test_gtsam_round_trips(rng):
    """4×4 ↔ gtsam.Pose2 / Pose3 are exact inverses."""
    T = random_poses(rng, 5)
    for k in range(5):
        np.testing.assert_allclose(pose_formats.from_gtsam_pose3(pose_formats.to_gtsam_pose3(T[k])), T[k], atol=1e-12)
    P = G.xytheta_to_matrix(1.5, -2.0, 2.9)
    np.testing.assert_allclose(pose_formats.from_gtsam_pose2(pose_formats.to_gtsam_pose2(P)), P, atol=1e-12)


def test_rpy_round_trip(rng):
    """rpy → R → rpy for pitch inside (−π/2, π/2); yaw-only equals rotz."""
    rpy = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], size=(100, 3))
    R = pose_formats.rpy_to_rotation(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    np.testing.assert_allclose(pose_formats.rotation_to_rpy(R), rpy, atol=1e-10)
    np.testing.assert_allclose(pose_formats.rpy_to_rotation(0, 0, 0.7), G.rotz(0.7), atol=1e-15)


def test_projections_return_nearest_rotation(rng):
    """project_to_so3 of a perturbed rotation is a rotation and is closer than the unperturbed one is to M."""
    R = G.so3_exp(rng.normal(size=(20, 3)))
    M = R + 0.05 * rng.normal(size=R.shape)
    P = G.project_to_so3(M)
    np.testing.assert_allclose(np.swapaxes(P, 1, 2) @ P, np.broadcast_to(np.eye(3), P.shape), atol=1e-12)
    assert np.all(np.linalg.det(P) > 0)
    assert np.all(np.linalg.norm(P - M, axis=(1, 2)) <= np.linalg.norm(R - M, axis=(1, 2)) + 1e-12)
    R2 = G.rot2(rng.uniform(-3, 3, size=20))
    np.testing.assert_allclose(G.project_to_so2(R2 * 3.0), R2, atol=1e-12)


def test_transform_points_2d_and_3d(rng):
    """Transforming points equals the homogeneous product; 2D points are treated as z = 0."""
    T = G.xytheta_to_matrix(1.0, 2.0, 0.3)
    P = rng.normal(size=(10, 2))
    h = np.c_[P, np.zeros(10), np.ones(10)] @ T.T
    np.testing.assert_allclose(G.transform_points(T, P), h[:, :2], atol=1e-14)
    with pytest.raises(GeometryError):
        G.transform_points(T, np.zeros((3, 4)))


@settings(max_examples=50)
@given(st.lists(angle, min_size=1, max_size=20))
def test_wrap_angle_range(angles):
    """wrap_angle maps into [−π, π) and preserves the angle modulo 2π."""
    a = np.asarray(angles) * 7.0
    w = G.wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-9)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-9)


def test_adjoint_identity_3d_and_planar(rng):
    """Exp(Ad_T ξ) = T Exp(ξ) T⁻¹ in SE(3) (ρ, φ) and SE(2) (x, y, θ) orderings."""
    T = random_poses(rng, 1)[0]
    xi = rng.normal(size=6) * 0.3
    np.testing.assert_allclose(G.se3_exp(G.adjoint(T) @ xi), T @ G.se3_exp(xi) @ G.inverse(T), atol=1e-10)
    P = G.xytheta_to_matrix(1.0, -2.0, 0.7)
    xi2 = np.array([0.2, -0.1, 0.3])
    np.testing.assert_allclose(G.se2_exp(G.adjoint(P, planar=True) @ xi2), P @ G.se2_exp(xi2) @ G.inverse(P),
                               atol=1e-10)


def test_compound_covariance_matches_monte_carlo(rng):
    """Σ_ac from compound_covariance matches the sample covariance of Log(T_ac⁻¹ T_ac_true)."""
    Tab, Tbc = G.xytheta_to_matrix(1.0, 0.5, 0.4), G.xytheta_to_matrix(2.0, -1.0, -0.8)
    S1, S2 = np.diag([1e-4, 4e-4, 1e-4]), np.diag([9e-4, 1e-4, 4e-4])
    n = 20000
    d1 = rng.multivariate_normal(np.zeros(3), S1, n)
    d2 = rng.multivariate_normal(np.zeros(3), S2, n)
    Tac_true = Tab @ G.se2_exp(d1) @ Tbc @ G.se2_exp(d2)
    err = G.se2_log(G.inverse(Tab @ Tbc) @ Tac_true)
    np.testing.assert_allclose(np.cov(err.T), G.compound_covariance(S1, Tbc, S2), rtol=0.05, atol=2e-6)
