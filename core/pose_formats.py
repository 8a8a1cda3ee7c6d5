"""Poses to and from the other forms they travel in: translation + unit quaternion ``(qx, qy, qz, qw)`` (ROS
messages, TUM files), roll-pitch-yaw (KITTI, Kümmerle relations) and GTSAM's ``Pose2`` / ``Pose3``. The group
operations, and the rotation ↔ quaternion maps they rest on, are in :mod:`core.geometry`."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .geometry import quat_to_rotation, rotation_to_quat, xytheta_to_matrix

Array = NDArray[np.float64]

__all__ = ["pose_from_quat", "pose_to_quat", "rpy_to_rotation", "rotation_to_rpy", "to_gtsam_pose2", "from_gtsam_pose2", "to_gtsam_pose3", "from_gtsam_pose3"]


def pose_from_quat(t: ArrayLike, q: ArrayLike) -> Array:
    """Translation ``(..., 3)`` and quaternion ``(..., 4)`` (x, y, z, w) → 4×4 pose(s)."""
    t = np.asarray(t, dtype=float)
    R = quat_to_rotation(q)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_to_quat(T: ArrayLike) -> tuple[Array, Array]:
    """4×4 pose(s) → (translation ``(..., 3)``, quaternion ``(..., 4)`` x, y, z, w)."""
    T = np.asarray(T, dtype=float)
    return T[..., :3, 3].copy(), rotation_to_quat(T[..., :3, :3])


def rpy_to_rotation(roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> Array:
    """R = Rz(yaw) · Ry(pitch) · Rx(roll) (the ROS / KITTI / Kümmerle-relations convention)."""
    r, p, y = (np.asarray(a, dtype=float) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def rotation_to_rpy(R: ArrayLike) -> Array:
    """Inverse of :func:`rpy_to_rotation`: returns ``(..., 3)`` roll, pitch, yaw."""
    R = np.asarray(R, dtype=float)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def to_gtsam_pose2(T: ArrayLike):
    """4×4 planar pose → ``gtsam.Pose2``."""
    import gtsam

    T = np.asarray(T, dtype=float)  # one pose: scalars, not matrix_to_xytheta's stack (called per graph node)
    return gtsam.Pose2(float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0])))


def from_gtsam_pose2(p) -> Array:
    """``gtsam.Pose2`` → 4×4 pose."""
    return xytheta_to_matrix(p.x(), p.y(), p.theta())


def to_gtsam_pose3(T: ArrayLike):
    """4×4 pose → ``gtsam.Pose3``."""
    import gtsam

    return gtsam.Pose3(np.asarray(T, dtype=float))


def from_gtsam_pose3(p) -> Array:
    """``gtsam.Pose3`` → 4×4 pose."""
    return np.asarray(p.matrix(), dtype=float)
