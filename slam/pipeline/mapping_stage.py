"""Mapping stage: Fast-GPOM submaps built online from keyframe scans, fused at the optimised poses.

A new submap starts every ``keyframes_per_submap`` keyframes, anchored at its first keyframe; the
scans of its keyframes enter relative to that anchor (at the estimate of the moment, as in any
submap SLAM). After optimisations the submaps are re-placed at their anchors' new poses
(:meth:`mapping.submaps.SubmapFuser.update_poses`: no GP is re-run). 3D clouds become a virtual
planar scan of a height band first (:func:`planar_scan_from_cloud`).
The classic-GPOM and log-odds baselines are built at the end from the keyframes at final poses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from core.frame import Frame
from mapping.grid import GridGeometry
from mapping.occupancy_map import OccupancyMap
from mapping.submaps import SubmapFuser

from .config import MappingStageConfig
from .frontend import Keyframe

Array = NDArray[np.float64]


def planar_pose(T: Array) -> Array:
    """Project a 3D pose on the plane (x, y, yaw)."""
    return G.xytheta_to_matrix(G.matrix_to_xytheta(T))


def planar_scan_from_cloud(frame: Frame, band: tuple[float, float], n_beams: int, max_range: float) -> Frame:
    """A virtual 2D laser scan from a 3D cloud: nearest point per bearing bin within a z band.

    Points are taken in the sensor frame with ``band[0] ≤ z ≤ band[1]`` (m); bins of equal bearing
    width over 360°; bins without a point within *max_range* are no-return beams.
    """
    p = frame.points
    sel = (p[:, 2] >= band[0]) & (p[:, 2] <= band[1])
    xy = p[sel, :2]
    r = np.hypot(xy[:, 0], xy[:, 1])
    ok = (r > 0.5) & (r < max_range)
    xy, r = xy[ok], r[ok]
    inc = 2 * np.pi / n_beams
    angles = -np.pi + (np.arange(n_beams) + 0.5) * inc
    b = np.minimum(((np.arctan2(xy[:, 1], xy[:, 0]) + np.pi) / inc).astype(int), n_beams - 1)
    ranges = np.full(n_beams, np.inf)
    np.minimum.at(ranges, b, r)
    hit = np.isfinite(ranges)
    pts = np.c_[ranges[hit] * np.cos(angles[hit]), ranges[hit] * np.sin(angles[hit])]
    return Frame(frame.stamp, pts, frame.index, angles, ranges, ~hit, odom=None,
                 base_T_sensor=planar_pose(frame.base_T_sensor), max_range=max_range, min_range=0.5,
                 source=frame.source)


def cap_range(frame: Frame, cap: float) -> Frame:
    """*frame* with beams longer than *cap* (m) turned into no-return beams of range *cap*.

    Such a beam then carves free space up to *cap* and marks no hit, as a maximum usable range
    does in grid mappers (GMapping's ``maxUrange``): far, grazing returns are the least reliable.
    """
    if frame.ranges is None or (np.isfinite(frame.max_range) and frame.max_range <= cap):
        return frame
    far = frame.no_return | (frame.ranges > cap)
    ranges = np.where(far, np.inf, frame.ranges)
    hit = ~far
    pts = np.c_[ranges[hit] * np.cos(frame.angles[hit]), ranges[hit] * np.sin(frame.angles[hit])]
    from dataclasses import replace

    return replace(frame, points=pts, ranges=ranges, no_return=far, max_range=cap)


class RecomposeSchedule:
    """When to recompose the global map: at most every *every* optimisations that moved poses."""

    def __init__(self, every: int) -> None:
        self.every = every
        self._since = 0

    def due(self, force: bool = False) -> bool:
        """Count one optimisation; True (and start counting again) when a recomposition is due."""
        self._since += 1
        if not force and self._since < self.every:
            return False
        self._since = 0
        return True


class MapBuilder:
    """Builds the occupancy map of a SLAM run (see module docstring)."""

    def __init__(self, config: MappingStageConfig, planar: bool) -> None:
        self.config = config
        self.planar = planar
        self.fuser: SubmapFuser | None = None
        self._anchor_of: dict[int, int] = {}  # keyframe id → anchor keyframe id
        self._anchors: list[int] = []
        self._count_in_current = 0
        self._schedule = RecomposeSchedule(config.recompose_every_keyframes)
        self.scans_fused = 0
        self._baseline_scans: list[Frame] = []  # the baselines' planar scans, mapped at the final poses

    @property
    def enabled(self) -> bool:
        return self.config.enabled

    @property
    def online(self) -> bool:
        return self.config.enabled and self.config.params.method == "fastgpom"

    def scan_for(self, kf: Keyframe) -> Frame:
        """The planar scan of a keyframe (a virtual one for 3D clouds), limited to ``max_range_m``."""
        cap = self.config.max_range_m
        if not self.planar:
            return planar_scan_from_cloud(kf.frame, self.config.height_band_m, self.config.virtual_beams, cap)
        return cap_range(kf.frame, cap)

    def _geometry_around(self, centres: Array) -> GridGeometry:
        h = self.config.submap_half_size_m
        lo, hi = centres.min(axis=0) - h, centres.max(axis=0) + h
        return GridGeometry.covering(lo, hi, self.config.params.resolution_m, margin=h)

    def add_keyframe(self, kf: Keyframe, pose: Array) -> None:
        """Fuse keyframe *kf* (at its current estimate *pose*, world_T_base) into the current submap; for the
        baselines, which map every keyframe at the final poses, keep its planar scan."""
        if self.online:
            self.add_scan(kf.id, self.scan_for(kf), pose)
        elif self.enabled:
            self._baseline_scans.append(self.scan_for(kf))

    def add_scan(self, keyframe_id: int, scan: Frame, pose: Array) -> None:
        """Fuse keyframe *keyframe_id*'s planar *scan* (:meth:`scan_for`) at *pose* into the current submap."""
        if not self.online:
            return
        pose = planar_pose(pose)
        if self.fuser is None:
            self.fuser = SubmapFuser(self._geometry_around(pose[None, :2, 3]), self.config.params,
                                     submap_half_size=self.config.submap_half_size_m)
        if not self._anchors or self._count_in_current >= self.config.keyframes_per_submap:
            if self._anchors:
                self.fuser.seal(self._anchors[-1])
            self.fuser.add_submap(keyframe_id, pose)
            self._anchors.append(keyframe_id)
            self._count_in_current = 0
        anchor = self._anchors[-1]
        self.fuser.add_scan(anchor, scan, pose)
        self._anchor_of[keyframe_id] = anchor
        self._count_in_current += 1
        self.scans_fused += 1

    def _fit_world_grid(self, anchor_poses: dict[int, Array]) -> None:
        """Grow the global grid when an anchor came near its border (then everything is re-placed)."""
        f = self.fuser
        centres = np.array([T[:2, 3] for T in anchor_poses.values()])
        x0, x1, y0, y1 = f.geometry.extent
        h = self.config.submap_half_size_m
        if (centres[:, 0].min() - h < x0 or centres[:, 0].max() + h > x1
                or centres[:, 1].min() - h < y0 or centres[:, 1].max() + h > y1):
            f.resize(self._geometry_around(centres))

    def refresh(self, keyframe_poses: Array, force: bool = False) -> int:
        """Re-place submaps at the anchors' current poses (at most every ``recompose_every_keyframes``)."""
        if not self.online or self.fuser is None or not self._schedule.due(force):
            return 0
        anchors = {a: planar_pose(keyframe_poses[a]) for a in self._anchors}
        self._fit_world_grid(anchors)
        return self.fuser.update_poses(anchors)

    def close(self) -> None:
        """Nothing to stop (the interface of :class:`~slam.pipeline.mapping_process.MappingProcess`)."""

    def finish(self, keyframe_poses: Array) -> OccupancyMap | None:
        """The final map at the final poses of the keyframes added."""
        return self.finish_scans(self._baseline_scans, keyframe_poses)

    def finish_scans(self, scans: list[Frame], keyframe_poses: Array) -> OccupancyMap | None:
        """:meth:`finish` from the keyframes' planar scans (used by the baselines only)."""
        if not self.config.enabled:
            return None
        if self.online:
            if self.fuser is None:
                return None
            self.refresh(keyframe_poses, force=True)
            return self.fuser.to_map().crop_observed()
        from mapping.gpom import ClassicGPOM
        from mapping.logodds import LogOddsGrid

        P = np.array([planar_pose(T) for T in keyframe_poses])
        geom = self._geometry_around(P[:, :2, 3])
        cls = ClassicGPOM if self.config.params.method == "gpom" else LogOddsGrid
        mapper = cls(geom, self.config.params)
        for scan, T in zip(scans, P):
            mapper.update(scan, T)
            self.scans_fused += 1
        return mapper.to_map().crop_observed()
