"""The sensor frame: one laser scan or one point cloud with everything the pipeline needs.

Frames of reference: ``points`` are in the **sensor** frame; ``base_T_sensor`` places the sensor
on the robot base; ``odom`` and ``ground_truth`` are ``world_T_base`` poses of the robot base
(4×4, metres / radians). For a 2D laser the beam geometry (``angles``, ``ranges``) is kept
because free-space mapping needs the beams that returned nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .errors import GeometryError

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Frame:
    """One scan.

    Attributes:
        stamp: acquisition time, float seconds (the CARMEN ipc_timestamp, the ROS header stamp).
        points: hit points in the sensor frame, ``(N, 2)`` for a planar laser or ``(N, 3)`` for
            LiDAR, float64, metres. For a 2D laser these are exactly the beams with a return.
        index: position of the scan among the scans of the log (0-based).
        angles: 2D laser only, ``(B,)`` beam angles in the sensor frame (rad), all beams.
        ranges: 2D laser only, ``(B,)`` measured ranges (m); ``inf`` where the beam had no return.
        no_return: 2D laser only, ``(B,)`` bool, True where the beam returned nothing (max range
            or ``inf``): free space along the whole beam up to ``max_range``.
        beam_times: 2D laser only, ``(B,)`` when each beam was measured, seconds after ``stamp``
            (ROS ``LaserScan.time_increment``), or None when the log does not say.
        odom: wheel-odometry pose of the robot base ``odom_T_base`` at ``stamp``, if the log has it.
        ground_truth: ground-truth pose ``world_T_base`` (simulated logs, KITTI), if known.
        base_T_sensor: pose of the sensor on the robot base (identity when unknown).
        max_range: largest range the sensor reports (m); ``inf`` when unknown.
        min_range: smallest valid range (m).
        source: where the scan came from, e.g. ``floor2.clf.bz2:line 17`` (for error messages).
    """

    stamp: float
    points: Array
    index: int = 0
    angles: Array | None = None
    ranges: Array | None = None
    no_return: NDArray[np.bool_] | None = None
    beam_times: Array | None = None
    odom: Array | None = None
    ground_truth: Array | None = None
    base_T_sensor: Array = field(default_factory=lambda: np.eye(4))
    max_range: float = float("inf")
    min_range: float = 0.0
    source: str = ""

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] not in (2, 3):
            raise GeometryError(f"{self.source or 'frame'}: points must be (N, 2) or (N, 3), got {pts.shape}")
        object.__setattr__(self, "points", pts)
        if self.ranges is not None:
            r = np.asarray(self.ranges, dtype=np.float64)
            a = np.asarray(self.angles, dtype=np.float64)
            nr = np.asarray(self.no_return, dtype=bool) if self.no_return is not None else ~np.isfinite(r)
            if not (r.shape == a.shape == nr.shape) or r.ndim != 1:
                raise GeometryError(f"{self.source or 'frame'}: angles, ranges and no_return must be equal-length 1-D arrays")
            object.__setattr__(self, "ranges", r)
            object.__setattr__(self, "angles", a)
            object.__setattr__(self, "no_return", nr)
        if self.beam_times is not None:
            t = np.asarray(self.beam_times, dtype=np.float64)
            if self.ranges is None or t.shape != self.ranges.shape or not np.all(np.isfinite(t)):
                raise GeometryError(f"{self.source or 'frame'}: beam_times must be finite, one per beam")
            object.__setattr__(self, "beam_times", t)

    @property
    def dim(self) -> int:
        """2 for a planar laser scan, 3 for a 3D point cloud."""
        return int(self.points.shape[1])

    @property
    def is_planar(self) -> bool:
        return self.dim == 2

    @property
    def num_beams(self) -> int:
        """Beams per scan (2D) or points per cloud (3D)."""
        return int(self.ranges.shape[0]) if self.ranges is not None else int(self.points.shape[0])

    def points_3d(self) -> Array:
        """Hit points as ``(N, 3)`` (z = 0 appended for a planar scan)."""
        if self.dim == 3:
            return self.points
        return np.column_stack([self.points, np.zeros(len(self.points))])

    def free_endpoints(self, max_range: float | None = None) -> Array:
        """Sensor-frame end points ``(B, 2)`` of every beam for free-space carving.

        Beams with a return end at their hit; no-return beams end at ``max_range`` (argument, or
        the frame's own when finite).
        """
        if self.ranges is None:
            raise GeometryError(f"{self.source or 'frame'}: free_endpoints needs a 2D laser scan")
        far = self.max_range if max_range is None else max_range
        r = np.where(self.no_return, far, self.ranges)
        return np.column_stack([r * np.cos(self.angles), r * np.sin(self.angles)])

    def with_points(self, points: Array) -> "Frame":
        """A copy with other points (e.g. deskewed or cropped); beams are dropped for 3D."""
        from dataclasses import replace

        return replace(self, points=points)
