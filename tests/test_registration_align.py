"""Closed-form alignment: SVD (Arun/Umeyama) and Horn's quaternion method."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from core.errors import DegenerateInputError, GpslamError
from registration.align import align_horn, align_svd


def _apply(T, P):
    return geo.transform_points(T, P)


@pytest.mark.parametrize("seed", range(20))
def test_svd_and_horn_agree_on_random_3d(seed):
    """SVD and Horn solve the same least-squares problem: on random noisy 3D pairs (and random
    weights) their poses agree to 1e-10."""
    rng = np.random.default_rng(seed)
    P = rng.normal(scale=3.0, size=(40, 3))
    T = geo.se3_exp(rng.normal(size=6))
    Q = _apply(T, P) + rng.normal(scale=0.2, size=P.shape)
    w = rng.uniform(0.1, 2.0, size=40)
    for weights in (None, w):
        A, B = align_svd(P, Q, weights), align_horn(P, Q, weights)
        assert np.abs(A - B).max() < 1e-10
        assert geo.is_pose(A)


@pytest.mark.parametrize("seed", range(10))
def test_svd_and_horn_agree_on_random_2d(seed):
    """The planar solutions (SVD on 2×2 H; Horn restricted to rotations about z) agree to 1e-10."""
    rng = np.random.default_rng(100 + seed)
    P = rng.normal(scale=3.0, size=(30, 2))
    T = geo.xytheta_to_matrix(*rng.normal(size=2), rng.uniform(-np.pi, np.pi))
    Q = _apply(T, P) + rng.normal(scale=0.2, size=P.shape)
    A, B = align_svd(P, Q), align_horn(P, Q)
    assert np.abs(A - B).max() < 1e-10
    assert A[2, 3] == 0.0 and np.allclose(A[:3, 2], [0, 0, 1])


@pytest.mark.parametrize("dim", [2, 3])
def test_noise_free_recovery_is_exact(dim):
    """Noise-free matched pairs are mapped back exactly (to 1e-12) by both methods, including
    rotations near π."""
    rng = np.random.default_rng(7)
    for k in range(10):
        P = rng.uniform(-10, 10, size=(25, dim))
        if dim == 3:
            axis = rng.normal(size=3)
            T = geo.se3_exp(np.r_[rng.normal(size=3), (np.pi - 1e-3 * k) * axis / np.linalg.norm(axis)])
        else:
            T = geo.xytheta_to_matrix(3.0, -2.0, np.pi - 1e-3 * k)
        Q = _apply(T, P)
        for f in (align_svd, align_horn):
            assert np.abs(f(P, Q) - T).max() < 1e-12


def test_reflection_case_returns_a_rotation_for_coplanar_points():
    """Arun et al.'s failure case: for noisy coplanar points the plain V Uᵀ can be a reflection;
    the det fix (Umeyama eq. 39) returns the proper rotation, which for noise-free coplanar data
    is exactly the true one."""
    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-5, 5, size=(30, 2)), np.zeros(30)])
    T = geo.se3_exp([1.0, 2.0, 3.0, 0.3, -0.4, 1.1])
    Q = _apply(T, P)
    for f in (align_svd, align_horn):
        A = f(P, Q)
        assert np.linalg.det(A[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        assert np.abs(A - T).max() < 1e-10
    # Coplanar source, target = its in-plane mirror image: H has a zero singular value and the plain
    # V Uᵀ is the reflection; the fixed solution is the half-turn about y, a rotation fitting exactly.
    Qm = P * np.array([-1.0, 1.0, 1.0])
    U, _, Vt = np.linalg.svd((P - P.mean(0)).T @ (Qm - Qm.mean(0)))
    assert np.linalg.det(Vt.T @ U.T) < 0
    A = align_svd(P, Qm)
    assert geo.is_pose(A)
    assert np.abs(_apply(A, P) - Qm).max() < 1e-10  # a rotation reproduces a mirror of a planar set


def test_mirrored_3d_data_gives_best_rotation_not_reflection():
    """For a truly mirrored non-planar set no rotation fits; both methods return the same proper
    rotation (det +1), the constrained least-squares optimum."""
    rng = np.random.default_rng(5)
    P = rng.normal(size=(50, 3))
    Q = P * np.array([-1.0, 1.0, 1.0])
    A, B = align_svd(P, Q), align_horn(P, Q)
    assert np.linalg.det(A[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    assert np.abs(A - B).max() < 1e-10
    # No other rotation does better: random perturbations of the optimum only increase the cost.
    cost = lambda T: np.sum((_apply(T, P) - Q) ** 2)  # noqa: E731
    c0 = cost(A)
    for _ in range(50):
        assert cost(A @ geo.se3_exp(rng.normal(scale=0.05, size=6))) >= c0 - 1e-9


def test_weights_equal_duplication():
    """Integer weights are equivalent to repeating pairs (definition of the weighted problem)."""
    rng = np.random.default_rng(11)
    P = rng.normal(size=(12, 3))
    Q = _apply(geo.se3_exp(rng.normal(size=6)), P) + rng.normal(scale=0.1, size=P.shape)
    w = rng.integers(1, 4, size=12)
    A = align_svd(P, Q, w.astype(float))
    B = align_svd(np.repeat(P, w, axis=0), np.repeat(Q, w, axis=0))
    assert np.abs(A - B).max() < 1e-12


@pytest.mark.parametrize(
    "P",
    [
        np.array([[0.0, 0, 0], [1, 0, 0]]),  # two pairs
        np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]]),  # collinear 3D
        np.ones((5, 3)),  # coincident
        np.ones((4, 2)),  # coincident 2D
    ],
)
def test_degenerate_input_raises(P):
    """Fewer than 3 pairs, collinear 3D points and coincident points raise DegenerateInputError
    (a GpslamError) with a message saying why."""
    for f in (align_svd, align_horn):
        with pytest.raises(DegenerateInputError) as ei:
            f(P, P + 1.0)
        assert isinstance(ei.value, GpslamError)
        assert any(w in str(ei.value) for w in ("at least 3", "collinear", "coincide"))


def test_shape_mismatch_raises():
    """Unmatched arrays are rejected, not broadcast."""
    with pytest.raises(DegenerateInputError):
        align_svd(np.zeros((5, 3)), np.zeros((6, 3)))
