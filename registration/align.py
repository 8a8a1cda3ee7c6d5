"""Closed-form rigid alignment of matched point pairs (2D and 3D, optional weights).

Both solvers return ``target_T_source``: the 4×4 pose that maps source points ``p'_i`` onto
their matches ``p_i`` in the least-squares sense, ``min Σ w_i ‖R p'_i + t − p_i‖²``.
Planar inputs ``(N, 2)`` give a planar 4×4 pose (z = 0, rotation about z only).

* :func:`align_svd` — Arun, Huang & Blostein (1987) / Umeyama (1991): barycentric
  centring, ``H = Σ w_i q'_i q_iᵀ``, ``H = UΣVᵀ``, ``R = V diag(1, …, det(VUᵀ)) Uᵀ`` (the
  reflection fix), ``t = p_m − R p'_m``.
* :func:`align_horn` — Horn (1987), "Closed-form solution of absolute orientation using unit
  quaternions": the rotation is the eigenvector of the largest eigenvalue of the symmetric
  4×4 matrix ``N`` built from ``H``. It is an independent check of :func:`align_svd`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.errors import DegenerateInputError
from core.geometry import quat_to_rotation

Array = NDArray[np.float64]

__all__ = ["align_svd", "align_horn", "weighted_centroids", "cross_covariance"]

# Relative size of a singular value of H (w.r.t. the largest) below which the point set is
# taken as having no extent in that direction.
_RANK_TOL = 1e-10


def _check_pairs(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None) -> tuple[Array, Array, Array]:
    P = np.asarray(source, dtype=np.float64)
    Q = np.asarray(target, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] not in (2, 3) or P.shape != Q.shape:
        raise DegenerateInputError(
            f"source and target must be matched (N, 2) or (N, 3) arrays of equal shape, got {P.shape} and {Q.shape}"
        )
    n = P.shape[0]
    if n < 3:
        raise DegenerateInputError(f"rigid alignment needs at least 3 point pairs, got {n}")
    if weights is None:
        w = np.full(n, 1.0 / n)
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape[0] != n or np.any(w < 0) or not np.all(np.isfinite(w)):
            raise DegenerateInputError(f"weights must be {n} finite non-negative numbers")
        s = w.sum()
        if s <= 0:
            raise DegenerateInputError("all weights are zero")
        if np.count_nonzero(w) < 3:
            raise DegenerateInputError(f"rigid alignment needs at least 3 pairs with positive weight, got {np.count_nonzero(w)}")
        w = w / s
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(Q))):
        raise DegenerateInputError("point pairs contain NaN or inf")
    return P, Q, w


def weighted_centroids(source: Array, target: Array, w: Array) -> tuple[Array, Array]:
    """Barycentres ``p'_m = Σ w_i p'_i`` and ``p_m = Σ w_i p_i`` (weights summing to 1)."""
    return w @ source, w @ target


def cross_covariance(source: Array, target: Array, w: Array) -> tuple[Array, Array, Array]:
    """``(H, p'_m, p_m)`` with ``H = Σ w_i (p'_i − p'_m)(p_i − p_m)ᵀ`` (Arun et al. 1987)."""
    pm_s, pm_t = weighted_centroids(source, target, w)
    H = (source - pm_s).T @ ((target - pm_t) * w[:, None])
    return H, pm_s, pm_t


def _check_extent(source: Array, w: Array, pm: Array) -> None:
    """Raise unless the source has extent in ≥ 2 directions (3D) or ≥ 1 direction (2D)."""
    C = (source - pm).T @ ((source - pm) * w[:, None])
    ev = np.linalg.eigvalsh(C)[::-1]
    scale = max(ev[0], 1e-300)
    if ev[0] <= 1e-24:
        raise DegenerateInputError("all source points coincide: the rotation is undetermined")
    if source.shape[1] == 3 and ev[1] <= _RANK_TOL * scale:
        raise DegenerateInputError("source points are collinear: the rotation about their line is undetermined")


def _to_pose(R: Array, t: Array) -> Array:
    T = np.eye(4)
    d = R.shape[0]
    T[:d, :d] = R
    T[:d, 3] = t
    return T


def align_svd(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> Array:
    """Weighted least-squares rigid transform ``target_T_source`` by SVD (Arun 1987; Umeyama 1991).

    Args:
        source: ``(N, d)`` points ``p'_i`` (metres, source frame), d = 2 or 3.
        target: ``(N, d)`` matched points ``p_i`` (metres, target frame).
        weights: optional ``(N,)`` non-negative weights.

    Returns:
        4×4 ``target_T_source`` (planar when d = 2).

    Raises:
        DegenerateInputError: fewer than 3 pairs, coincident points, or collinear 3D points.
    """
    P, Q, w = _check_pairs(source, target, weights)
    H, pm_s, pm_t = cross_covariance(P, Q, w)
    _check_extent(P, w, pm_s)
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T
    d = P.shape[1]
    D = np.ones(d)
    # Reflection fix (Umeyama 1991): if det(VUᵀ) = −1 flip the axis of the smallest singular value.
    D[-1] = np.sign(np.linalg.det(V @ U.T)) or 1.0
    R = (V * D) @ U.T
    t = pm_t - R @ pm_s
    return _to_pose(R, t)


def horn_matrix(H: Array) -> Array:
    """Horn's symmetric 4×4 matrix N of the 3×3 cross-covariance ``H`` (Horn 1987), (w, x, y, z) order."""
    Sxx, Sxy, Sxz = H[0]
    Syx, Syy, Syz = H[1]
    Szx, Szy, Szz = H[2]
    return np.array(
        [
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ]
    )


def align_horn(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> Array:
    """Weighted rigid transform ``target_T_source`` by Horn's unit-quaternion method (Horn 1987).

    The optimal rotation quaternion is the eigenvector of the largest eigenvalue of ``N(H)``.
    Planar inputs are embedded with z = 0; the rotation then comes out about z. Same inputs,
    output and errors as :func:`align_svd`.
    """
    P, Q, w = _check_pairs(source, target, weights)
    d = P.shape[1]
    P3 = P if d == 3 else np.column_stack([P, np.zeros(len(P))])
    Q3 = Q if d == 3 else np.column_stack([Q, np.zeros(len(Q))])
    H, pm_s, pm_t = cross_covariance(P3, Q3, w)
    _check_extent(P, w, pm_s[:d])
    N = horn_matrix(H)
    if d == 2:
        # Quaternions of rotations about z are (cos θ/2, 0, 0, sin θ/2): restrict N to its (w, z) block,
        # so that a planar reflection cannot be realised by a half-turn about an in-plane axis.
        _, ev2 = np.linalg.eigh(N[np.ix_([0, 3], [0, 3])])
        qw, qz = ev2[:, -1]
        th = 2.0 * np.arctan2(qz, qw)
        R2 = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        return _to_pose(R2, pm_t[:2] - R2 @ pm_s[:2])
    _, evecs = np.linalg.eigh(N)
    qw, qx, qy, qz = evecs[:, -1]
    R = quat_to_rotation([qx, qy, qz, qw])
    return _to_pose(R, pm_t - R @ pm_s)
