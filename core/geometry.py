"""SE(2)/SE(3) geometry: the one place where pose conversions live.

Every pose at a package boundary is a 4×4 float64 homogeneous matrix ``a_T_b`` that maps
points from frame *b* into frame *a* (``p_a = a_T_b @ p_b``). A planar pose is the same
matrix with z = 0 and roll = pitch = 0. Angles are radians, translations metres.

Quaternions are stored ``(qx, qy, qz, qw)`` (scalar last, as in TUM files, ROS and g2o).

The exponential and logarithm maps follow Barfoot, *State Estimation for Robotics* (2017),
§7.1.3 (SO(3): Rodrigues, eq. 7.14) and §7.1.5 (SE(3): eq. 7.86 / 7.94), with the tangent
vector ordered ``(ρ, φ)`` = (translation part, rotation part), the GTSAM ordering being
``(φ, ρ)``; see :func:`se3_log`.

Functions accept a single pose ``(4, 4)`` or a stack ``(N, 4, 4)`` where documented;
stacks are processed without Python loops.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError

Array = NDArray[np.float64]

__all__ = [
    "rotation_to_quat",
    "quat_to_rotation",
    "identity",
    "is_pose",
    "inverse",
    "relative",
    "compose",
    "transform_points",
    "bounds",
    "xytheta_to_matrix",
    "matrix_to_xytheta",
    "wrap_angle",
    "rot2",
    "rotz",
    "so3_hat",
    "so3_exp",
    "so3_log",
    "rotation_angle",
    "rotation_angles",
    "se3_exp",
    "se3_log",
    "se2_exp",
    "se2_log",
    "project_to_so3",
    "project_to_so2",
    "planar_to_3d",
    "adjoint",
    "compound_covariance",
]

_EPS = 1e-12


def identity() -> Array:
    """The 4×4 identity pose."""
    return np.eye(4)


def is_pose(T: ArrayLike, tol: float = 1e-6) -> bool:
    """True when *T* is a (stack of) proper rigid transform(s): RᵀR = I, det R = +1, last row 0 0 0 1."""
    T = np.asarray(T, dtype=float)
    if T.shape[-2:] != (4, 4):
        return False
    if T.ndim == 2:  # one pose: the determinant in closed form (np.linalg.det costs ~10 µs a call)
        R, ((a, b, c), (d, e, f), (g, h, i)) = T[:3, :3], T[:3, :3].tolist()
        det1 = abs(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) - 1.0) <= tol
        return bool(det1 and np.abs(R.T @ R - np.eye(3)).max() <= tol and np.abs(T[3] - (0, 0, 0, 1.0)).max() <= tol)
    R = T[..., :3, :3]
    ortho = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() <= tol
    det = np.abs(np.linalg.det(R) - 1.0).max() <= tol
    row = np.abs(T[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max() <= tol
    return bool(ortho and det and row)


def inverse(T: ArrayLike) -> Array:
    """Closed-form inverse [Rᵀ, −Rᵀt] of one pose or a stack of poses."""
    T = np.asarray(T, dtype=float)
    if T.shape == (4, 4):  # one pose: scalar arithmetic, the same sums in the same order, ~3× faster
        (a, b, c, x), (d, e, f, y), (g, h, i, z) = T[:3].tolist()
        return np.array([[a, d, g, -(a * x + d * y + g * z)], [b, e, h, -(b * x + e * y + h * z)],
                         [c, f, i, -(c * x + f * y + i * z)], [0.0, 0.0, 0.0, 1.0]])
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def relative(a_T_b: ArrayLike, a_T_c: ArrayLike) -> Array:
    """The pose of *c* in *b*: ``b_T_c = a_T_b⁻¹ · a_T_c`` (the ⊖ of Kümmerle et al. 2009)."""
    return inverse(a_T_b) @ np.asarray(a_T_c, dtype=float)


def compose(*poses: ArrayLike) -> Array:
    """Left-to-right product of poses (⊕)."""
    out = np.asarray(poses[0], dtype=float)
    for p in poses[1:]:
        out = out @ np.asarray(p, dtype=float)
    return out


def transform_points(T: ArrayLike, points: ArrayLike) -> Array:
    """Apply pose *T* to ``(N, 2)`` or ``(N, 3)`` points; 2D points are treated as z = 0 and returned 2D."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise GeometryError(f"points must be (N, 2) or (N, 3), got shape {P.shape}")
    if P.shape[1] == 2:
        return P @ T[:2, :2].T + T[:2, 3]
    return P @ T[:3, :3].T + T[:3, 3]


def bounds(points: ArrayLike) -> tuple[Array, Array]:
    """Lower and upper corner (per coordinate) of points ``(N, d)``, N ≥ 1: the same values as ``min(axis=0)``
    and ``max(axis=0)``, one reduction per column (numpy's axis-0 reduction of a narrow (N, 2) array is ~10×
    slower, and the loop-closure searches take bounds of thousands of local maps)."""
    P = np.asarray(points)
    cols = range(P.shape[1])
    return np.array([P[:, k].min() for k in cols]), np.array([P[:, k].max() for k in cols])


# ----------------------------------------------------------------------------- planar

def wrap_angle(theta: ArrayLike) -> Array | float:
    """Wrap angles to [−π, π)."""
    out = (np.asarray(theta, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi
    return float(out) if np.ndim(out) == 0 else out


def rot2(theta: ArrayLike) -> Array:
    """2×2 rotation matrix (or stack) for angle(s) *theta*."""
    th = np.asarray(theta, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def rotz(theta: ArrayLike) -> Array:
    """3×3 rotation about z (or a stack)."""
    th = np.asarray(theta, dtype=float)
    R = np.zeros(th.shape + (3, 3))
    R[..., :2, :2] = rot2(th)
    R[..., 2, 2] = 1.0
    return R


def xytheta_to_matrix(x: ArrayLike, y: ArrayLike | None = None, theta: ArrayLike | None = None) -> Array:
    """(x, y, θ) → 4×4 pose. Accepts three scalars, or one array ``(..., 3)``."""
    if y is None:
        v = np.asarray(x, dtype=float)
        if v.shape[-1] != 3:
            raise GeometryError(f"expected (..., 3) array of (x, y, theta), got shape {v.shape}")
        x, y, theta = v[..., 0], v[..., 1], v[..., 2]
    x = np.asarray(x, dtype=float)
    if x.ndim == 0 and np.ndim(y) == 0 and np.ndim(theta) == 0:  # one pose, without the stacking
        th = np.asarray(theta, dtype=float)
        c, s = np.cos(th), np.sin(th)
        return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], dtype=float)
    T = np.zeros(np.shape(x) + (4, 4))
    T[..., :3, :3] = rotz(theta)
    T[..., 0, 3] = x
    T[..., 1, 3] = y
    T[..., 3, 3] = 1.0
    return T


def matrix_to_xytheta(T: ArrayLike) -> Array:
    """4×4 pose (or stack) → (x, y, θ) with θ = atan2(R10, R00) in [−π, π]."""
    T = np.asarray(T, dtype=float)
    if T.ndim == 2:  # one pose, without the stacking
        return np.array([T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0])])
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])], -1)


def se2_exp(xi: ArrayLike) -> Array:
    """SE(2) exponential of ``(ρx, ρy, θ)`` as a 4×4 pose (Barfoot eq. 7.86 restricted to the plane)."""
    xi = np.asarray(xi, dtype=float)
    rho, th = xi[..., :2], xi[..., 2]
    small = np.abs(th) < 1e-9
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, th / 2.0, (1.0 - np.cos(ths)) / ths)
    V = np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)
    t = np.einsum("...ij,...j->...i", V, rho)
    T = xytheta_to_matrix(t[..., 0], t[..., 1], th)
    return T


def se2_log(T: ArrayLike) -> Array:
    """Inverse of :func:`se2_exp`: 4×4 planar pose → ``(ρx, ρy, θ)``."""
    x, y, th = np.moveaxis(matrix_to_xytheta(T), -1, 0)
    small = np.abs(th) < 1e-9
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, th / 2.0, (1.0 - np.cos(ths)) / ths)
    det = a * a + b * b
    rx = (a * x + b * y) / det
    ry = (-b * x + a * y) / det
    return np.stack([rx, ry, th], -1)


def project_to_so2(M: ArrayLike) -> Array:
    """Nearest rotation (Frobenius) to a 2×2 matrix or stack: R = rot2(atan2(m10 − m01, m00 + m11))."""
    M = np.asarray(M, dtype=float)
    return rot2(np.arctan2(M[..., 1, 0] - M[..., 0, 1], M[..., 0, 0] + M[..., 1, 1]))


# ----------------------------------------------------------------------------- rotations

def so3_hat(w: ArrayLike) -> Array:
    """Skew-symmetric matrix [w]× of a 3-vector (or stack)."""
    w = np.asarray(w, dtype=float)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: ArrayLike) -> Array:
    """Rodrigues' formula R = I + sinθ/θ [w]× + (1 − cosθ)/θ² [w]×² (Barfoot eq. 7.14)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    K = so3_hat(w)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotation_angle(R: ArrayLike) -> float:
    """Angle (rad, in [0, π]) of a 3×3 rotation: atan2(½‖vee(R − Rᵀ)‖, ½(tr R − 1)), accurate near 0 and π
    and much cheaper than ``‖so3_log(R)‖`` for a scalar test."""
    R = np.asarray(R, dtype=float)
    s = 0.5 * math.sqrt((R[2, 1] - R[1, 2]) ** 2 + (R[0, 2] - R[2, 0]) ** 2 + (R[1, 0] - R[0, 1]) ** 2)
    return math.atan2(s, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0))


def rotation_angles(R: ArrayLike) -> Array:
    """Angles (rad, in [0, π]) of a stack ``(..., 3, 3)`` of rotations: :func:`rotation_angle` vectorised."""
    R = np.asarray(R, dtype=float)
    s = 0.5 * np.sqrt((R[..., 2, 1] - R[..., 1, 2]) ** 2 + (R[..., 0, 2] - R[..., 2, 0]) ** 2
                      + (R[..., 1, 0] - R[..., 0, 1]) ** 2)
    return np.arctan2(s, 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0))


def so3_log(R: ArrayLike) -> Array:
    """Rotation vector of a rotation matrix (or stack); robust near 0 and π."""
    R = np.asarray(R, dtype=float)
    # Via the quaternion: numerically stable everywhere (Shepperd's method in rotation_to_quat).
    q = rotation_to_quat(R)
    q = np.where(q[..., 3:4] < 0.0, -q, q)  # shortest rotation: qw ≥ 0
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    th = 2.0 * np.arctan2(s, q[..., 3])
    small = s < 1e-12
    scale = np.where(small, 2.0 / np.where(q[..., 3] == 0, 1.0, q[..., 3]), th / np.where(small, 1.0, s))
    return v * scale[..., None]


def _so3_left_jacobian(w: Array) -> Array:
    """Left Jacobian J of SO(3) (Barfoot eq. 7.77a)."""
    th = np.linalg.norm(w, axis=-1)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ths - np.sin(ths)) / ths**3)
    K = so3_hat(w)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def se3_exp(xi: ArrayLike) -> Array:
    """SE(3) exponential of ``ξ = (ρ, φ)`` (translation first): T = [exp(φ), J(φ)ρ; 0, 1] (Barfoot eq. 7.86)."""
    xi = np.asarray(xi, dtype=float)
    rho, phi = xi[..., :3], xi[..., 3:]
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = so3_exp(phi)
    T[..., :3, 3] = np.einsum("...ij,...j->...i", _so3_left_jacobian(phi), rho)
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: ArrayLike) -> Array:
    """Inverse of :func:`se3_exp`: returns ``(ρ, φ)``. GTSAM's ``Pose3.Logmap`` returns ``(φ, ρ)``."""
    T = np.asarray(T, dtype=float)
    phi = so3_log(T[..., :3, :3])
    J = _so3_left_jacobian(phi)
    rho = np.linalg.solve(J, T[..., :3, 3][..., None])[..., 0]
    return np.concatenate([rho, phi], -1)


def project_to_so3(M: ArrayLike) -> Array:
    """Nearest rotation in Frobenius norm: U diag(1, 1, det(UVᵀ)) Vᵀ from the SVD M = UΣVᵀ."""
    M = np.asarray(M, dtype=float)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vt


def quat_to_rotation(q: ArrayLike) -> Array:
    """Unit quaternion ``(qx, qy, qz, qw)`` (or stack) → rotation matrix. The input is normalised."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < _EPS):
        raise GeometryError("zero-norm quaternion")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotation_to_quat(R: ArrayLike) -> Array:
    """Rotation matrix (or stack) → unit quaternion ``(qx, qy, qz, qw)`` with qw ≥ 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # Four candidate formulas; pick per element the one with the largest pivot.
    cands = np.stack(
        [
            np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1], 1 + tr], -1),
            np.stack([1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 2, 1] - R[..., 1, 2]], -1),
            np.stack([R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1], R[..., 0, 2] - R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22, R[..., 1, 0] - R[..., 0, 1]], -1),
        ],
        -2,
    )
    pivots = np.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def planar_to_3d(T2: ArrayLike) -> Array:
    """Embed a 3×3 homogeneous SE(2) matrix (or stack) in a 4×4 pose."""
    T2 = np.asarray(T2, dtype=float)
    T = np.zeros(T2.shape[:-2] + (4, 4))
    T[..., :2, :2] = T2[..., :2, :2]
    T[..., :2, 3] = T2[..., :2, 2]
    T[..., 2, 2] = 1.0
    T[..., 3, 3] = 1.0
    return T


# ----------------------------------------------------------------------------- adjoints

def adjoint(T: ArrayLike, planar: bool = False) -> Array:
    """Adjoint of a pose in the project's tangent order (translation first): Exp(Ad_T ξ) = T Exp(ξ) T⁻¹.

    3D ``(ρ, φ)``: ``[[R, [t]×R], [0, R]]`` (Barfoot eq. 7.45). Planar ``(x, y, θ)`` (*planar*):
    ``[[R₂, (t_y, −t_x)ᵀ], [0, 1]]``.
    """
    T = np.asarray(T, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    if planar:
        A = np.eye(3)
        A[:2, :2] = R[:2, :2]
        A[0, 2], A[1, 2] = t[1], -t[0]
        return A
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[:3, 3:] = so3_hat(t) @ R
    return A


def compound_covariance(cov_ab: ArrayLike, b_T_c: ArrayLike, cov_bc: ArrayLike) -> Array:
    """Covariance of ``a_T_c = a_T_b · b_T_c`` with right perturbations on all three poses.

    ``a_T_b Exp(δ₁) b_T_c Exp(δ₂) = a_T_c Exp(Ad(b_T_c⁻¹) δ₁ + δ₂)`` to first order, hence
    ``Σ_ac = Ad Σ_ab Adᵀ + Σ_bc`` with independent increments (Barfoot §7.3.3, eq. 7.262).
    """
    cov_ab = np.asarray(cov_ab, dtype=float)
    A = adjoint(inverse(b_T_c), planar=cov_ab.shape[0] == 3)
    return A @ cov_ab @ A.T + np.asarray(cov_bc, dtype=float)
