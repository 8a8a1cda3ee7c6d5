"""KISS-ICP odometry (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP", RA-L 2023) behind the
interface of :class:`registration.odometry.Odometry`: ``kiss_icp.kiss_icp.KissICP`` with our configuration mapped
onto it; planar scans become z = 0 points, deskewing off. KISS-ICP gives no covariance: it is computed by
:func:`registration.alignment.evaluate_alignment` of the current scan against the previous one at the KISS pose
(plane model, gate 3σ of KISS's threshold)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core.errors import DegenerateInputError, GeometryError
from core.frame import Frame

from .alignment import evaluate_alignment
from .config import IcpConfig, KissOdometryConfig
from .odometry import Odometry, OdometryStep, planar_pose
from .target import IcpTarget
from .voxel import voxel_downsample

Array = NDArray[np.float64]

__all__ = ["KissOdometry"]


class KissOdometry(Odometry):
    """KISS-ICP odometry for 3D clouds and planar scans (z = 0), config mapped from ours."""

    def __init__(self, config: KissOdometryConfig | None = None, use_wheel_odometry: bool = True) -> None:
        super().__init__(use_wheel_odometry)
        self.config = config or KissOdometryConfig()
        self._kiss = None
        self._planar: bool | None = None
        self._prev_world: Array | None = None

    @property
    def kiss(self):
        """The wrapped ``kiss_icp.kiss_icp.KissICP`` (None before the first frame)."""
        return self._kiss

    def update(self, frame: Frame) -> OdometryStep:
        from kiss_icp.kiss_icp import KissICP

        if self._kiss is None:
            self._planar = frame.is_planar
            self._kiss = KissICP(self.config.to_kiss(planar=self._planar))
        elif frame.is_planar != self._planar:
            raise GeometryError(f"{frame.source or 'frame'} {frame.index}: mixed planar and 3D frames")
        kiss = self._kiss
        if self._prev_frame is not None:
            # KISS-ICP predicts last_pose · last_delta; seeding last_delta injects our guess.
            kiss.last_delta = self._guess(frame, self.use_wheel_odometry)
        sigma = float(kiss.adaptive_threshold.get_threshold())
        pts3 = frame.points_3d()
        _, source = kiss.register_frame(pts3, np.zeros(0))
        pose = np.array(kiss.last_pose, dtype=np.float64)
        if self._planar:
            pose = planar_pose(pose)
        d = frame.dim
        cov = accepted = None
        cfg = self.config
        if cfg.compute_covariance:
            src = np.asarray(source, dtype=np.float64)[:, :d]
            if self._prev_world is not None and len(src) >= 3:
                icfg = IcpConfig(gates_m=(3.0 * sigma,), sigma_m=cfg.covariance_sigma_m, covariance_model="plane",
                                 workers=1 if d == 2 else -1)
                try:
                    tgt = IcpTarget(self._prev_world, workers=icfg.workers)
                    res = evaluate_alignment(src, tgt, pose, icfg.gates_m[0], icfg)
                    cov, accepted = res.covariance, res.accepted if cfg.covariance_sigma_m else None
                except DegenerateInputError:
                    cov = None
            vs = kiss.config.mapping.voxel_size * 0.5
            self._prev_world = geo.transform_points(pose, voxel_downsample(frame.points, vs))
        return self._emit(frame, pose, cov, accepted)
