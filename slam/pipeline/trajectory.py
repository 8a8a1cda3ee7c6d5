"""A pose for every scan from the optimised keyframe poses.

Each scan's odometry pose ``O_s`` is corrected by a world correction ``C = X_k O_k⁻¹`` that is
interpolated on the group between the surrounding keyframes k and k+1 by time:
``C(α) = C_k · Exp(α · Log(C_k⁻¹ C_{k+1}))`` and ``x_s = C(α) O_s``. Keyframes keep exactly their
optimised pose, and the scans between them follow the odometry's shape with the drift correction
blended smoothly instead of jumping at the next keyframe.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as G

Array = NDArray[np.float64]


def interpolate_scan_poses(scan_stamps: Array, scan_odom: Array, scan_kf: NDArray[np.int64], kf_stamps: Array,
                           kf_odom: Array, kf_opt: Array, planar: bool) -> Array:
    """``(N, 4, 4)`` corrected poses of all scans (see module docstring).

    Args:
        scan_stamps, scan_odom: ``(N,)`` seconds and ``(N, 4, 4)`` odometry poses of every scan.
        scan_kf: ``(N,)`` id of the latest keyframe at or before each scan (−1 before the first).
        kf_stamps, kf_odom, kf_opt: ``(K,)`` stamps, odometry poses and optimised poses of the keyframes.
    """
    K = len(kf_stamps)
    C = kf_opt @ G.inverse(kf_odom)  # (K, 4, 4) world corrections at the keyframes
    k = np.clip(np.asarray(scan_kf), 0, K - 1)
    k1 = np.minimum(k + 1, K - 1)
    span = kf_stamps[k1] - kf_stamps[k]
    alpha = np.where(span > 0, (scan_stamps - kf_stamps[k]) / np.where(span > 0, span, 1.0), 0.0)
    alpha = np.clip(alpha, 0.0, 1.0)
    D = G.inverse(C[k]) @ C[k1]
    if planar:
        xi = G.se2_log(D)
        Ca = C[k] @ G.se2_exp(alpha[:, None] * xi)
    else:
        xi = G.se3_log(D)
        Ca = C[k] @ G.se3_exp(alpha[:, None] * xi)
    return Ca @ scan_odom
