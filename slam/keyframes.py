"""Keyframes: the scans kept as pose-graph nodes, and when a scan becomes one (the robot moved or
turned enough, or time passed).

The thresholds are the usual ones of graph SLAM front ends (e.g. Grisetti et al., "A Tutorial on
Graph-Based SLAM", 2010, §III: nodes every ~0.5 m or 0.5 rad) and keep the pose graph sparse while
consecutive keyframe scans still overlap.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from core import geometry as G
from core.frame import Frame


@dataclass
class Keyframe:
    """A scan kept as a pose-graph node.

    Attributes:
        id: node id (0, 1, 2, … in time order).
        scan_index: index of the scan among the scans read.
        stamp: seconds.
        odom_pose: ``world_T_base`` from the odometry source (the front end's estimate).
        base_T_sensor: sensor on the robot.
        points: sensor-frame hit points used for loop-closure ICP (voxel-downsampled), metres.
        frame: the full scan (beams kept for 2D occupancy mapping); a 3D keyframe's cloud is dropped
            once the stages that read it are done (:meth:`drop_cloud`).
    """

    id: int
    scan_index: int
    stamp: float
    odom_pose: NDArray[np.float64]
    base_T_sensor: NDArray[np.float64]
    points: NDArray[np.float64]
    frame: Frame

    def drop_cloud(self) -> None:
        """Forget a 3D keyframe's full cloud, keeping the rest of its frame (stamp, mount, odometry).

        Only the new keyframe's cloud is read: the loop closer's place descriptor and the mapping stage's
        planar slice are made of it when the keyframe arrives; everything later uses ``points``. A KITTI
        scan is 3.0 MB of float64 points against ~0.3 MB kept for ICP, so holding clouds would cost a
        4,500-frame drive ~13 GB. A planar scan keeps its beams (the self-check reads them at the end)."""
        if not self.frame.is_planar:
            self.frame = replace(self.frame, points=np.empty((0, 3)))


class KeyframeConfig(BaseModel):
    """When a scan becomes a keyframe (whichever threshold is crossed first)."""

    model_config = {"extra": "forbid"}

    distance_m: float = Field(0.25, gt=0, description="translation since the last keyframe, metres")
    angle_rad: float = Field(0.25, gt=0, description="rotation since the last keyframe, radians")
    time_s: float = Field(10.0, gt=0, description="time since the last keyframe, seconds")
    max_range_m: float = Field(30.0, gt=0, description="a keyframe keeps the points of its scan within this range of the sensor (for its edge covariance, loop closure and the self-check)")
    min_range_m: float = Field(0.05, ge=0, description="... and beyond this one")


@dataclass
class KeyframeSelector:
    """Stateful selector fed with the odometry pose of every scan (``world_T_base``, 4×4)."""

    config: KeyframeConfig
    _last_pose: NDArray[np.float64] | None = None
    _last_stamp: float = -np.inf

    def is_keyframe(self, stamp: float, pose: NDArray[np.float64]) -> bool:
        """True (and remember this scan) when the scan at *stamp* with odometry *pose* is a keyframe."""
        if self._last_pose is None:
            self._accept(stamp, pose)
            return True
        rel = G.relative(self._last_pose, pose)
        dist = float(np.linalg.norm(rel[:3, 3]))
        ang = G.rotation_angle(rel[:3, :3])
        c = self.config
        if dist >= c.distance_m or ang >= c.angle_rad or stamp - self._last_stamp >= c.time_s:
            self._accept(stamp, pose)
            return True
        return False

    def _accept(self, stamp: float, pose: NDArray[np.float64]) -> None:
        self._last_pose = np.array(pose, dtype=float)
        self._last_stamp = float(stamp)
