"""Which odometry the front end runs: KISS-ICP (Vizzo et al., RA-L 2023) or our scan-to-map SVD-ICP,
with the configuration's settings for planar (2D laser) or 3D frames. One place, used by ``run_slam``'s
front end, its stage process and the loop replay."""

from __future__ import annotations

from registration.odometry import IcpOdometry, Odometry
from registration.odometry_kiss import KissOdometry

from .config import SlamConfig

__all__ = ["make_odometry"]


def make_odometry(config: SlamConfig, planar: bool) -> Odometry:
    """The configured odometry source for planar (2D laser) or 3D frames."""
    c = config.odometry
    if c.method == "kiss":  # auto: our ICP, planar and 3D (docs/ODOMETRY.md has the measurements)
        return KissOdometry(c.kiss_2d if planar else c.kiss_3d, use_wheel_odometry=c.use_wheel_odometry)
    return IcpOdometry(c.icp_2d if planar else c.icp_3d, use_wheel_odometry=c.use_wheel_odometry)
