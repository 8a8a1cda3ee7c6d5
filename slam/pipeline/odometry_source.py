"""Which odometry the front end runs: KISS-ICP (Vizzo et al., RA-L 2023) or our scan-to-map SVD-ICP,
built from the configuration for planar (2D laser) or 3D frames. One place, used by ``run_slam``'s front
end, its stage process and the loop replay."""

from __future__ import annotations

import numpy as np

from registration.config import IcpConfig, IcpOdometryConfig, KissOdometryConfig
from registration.odometry import IcpOdometry, KissOdometry, Odometry

from .config import SlamConfig

__all__ = ["make_odometry"]


def make_odometry(config: SlamConfig, planar: bool) -> Odometry:
    """The configured odometry source for planar (2D laser) or 3D frames."""
    c = config.odometry
    if c.method == "kiss" or (c.method == "auto" and not planar):
        base = KissOdometryConfig.planar_default() if planar else KissOdometryConfig()
        # The pipeline computes its own keyframe-edge covariance, so KISS's per-scan one is skipped.
        kc = base.model_copy(update={"use_wheel_odometry": c.use_wheel_odometry, "compute_covariance": False,
                                     "max_range": c.max_range_m if planar else base.max_range})
        return KissOdometry(kc)
    # Planar: one 0.3 m gate from the wheel guess by default (config.odometry.icp_gates_m).
    icp_cfg = IcpConfig(gates=c.icp_gates_m, max_iterations=30, tol_translation=c.icp_tolerance, tol_rotation=c.icp_tolerance,
                        robust="cauchy", robust_scale=0.05, workers=1) if planar else IcpConfig(
                        gates=(1.5, 0.6, 0.3), voxel_size=0.5, robust="cauchy", robust_scale=0.2)
    return IcpOdometry(IcpOdometryConfig(icp=icp_cfg, map_scans=10, point_to_plane=c.icp_point_to_plane,
                                         keyframe_distance=c.icp_map_step_m, keyframe_angle=c.icp_map_step_rad,
                                         max_guess_deviation_m=c.icp_max_guess_deviation_m,
                                         max_guess_deviation_rad=c.icp_max_guess_deviation_rad,
                                         alternative_start_m=c.icp_alternative_start_m,
                                         alternative_start_rad=c.icp_alternative_start_rad,
                                         map_voxel_size=0.03 if planar else 0.3,
                                         max_range=c.max_range_m if planar else 100.0, min_range=c.min_range_m,
                                         use_wheel_odometry=c.use_wheel_odometry,
                                         unguided_window_m=c.unguided_window_m if planar else None,
                                         unguided_window_rad=float(np.radians(c.unguided_window_deg)),
                                         prior_point_sigma=c.icp_wheel_prior_sigma, prior_sigma_per_m=c.wheel_sigma_per_m,
                                         prior_sigma_rad_per_m=c.wheel_sigma_rad_per_m,
                                         prior_sigma_rad_per_rad=c.wheel_sigma_rad_per_rad))
