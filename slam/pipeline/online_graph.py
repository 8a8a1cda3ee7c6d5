"""The online pose graph: each new keyframe's odometry (and wheel) edge, its loop closures found
against the current estimate, then an incremental solve.

The one place that fixes this order, so ``run_slam`` and the loop-closure replay of ``slam loops``
(:mod:`slam.pipeline.loop_replay`) cannot drift apart.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from core import geometry as G

from .backend import PipelineBackend
from .config import BackendConfig, LoopConfig
from .frontend import Keyframe, OdometryEdge, WheelEdge
from slam.loops import LoopCloser, LoopClosure
from slam.loops.calibration import WindowCalibration
from slam.loops.uncertainty import RelativeUncertainty

Array = NDArray[np.float64]


class OnlineGraph:
    """Keyframes in, optimised keyframe poses out (``backend.poses`` online, :meth:`finish` at the end)."""

    def __init__(self, loops: LoopConfig, backend: BackendConfig, planar: bool) -> None:
        self.backend = PipelineBackend(backend, loops, planar)
        self.loops: list[LoopClosure] = []
        self.planar = planar
        self.dim = 2 if planar else 3  # translation dimensions
        # Every edge's covariance: each keyframe's uncertainty relative to the new one sizes its search
        # (tracked up to 100 m σ; beyond, a place is out of reach of any search).
        self.uncertainty = RelativeUncertainty(planar, limit_m2=100.0**2,
                                               drift_rad_per_m=float(np.radians(loops.heading_drift_deg_per_m)))
        self.closer = LoopCloser(loops, planar, self.uncertainty)
        # The run's own long closures widen that uncertainty where it is too sure (2D chains only).
        self.calibration = (WindowCalibration(float(np.radians(loops.heading_drift_deg_per_m)))
                            if planar and loops.window_calibration else None)
        self.window_scale_max = 1.0
        self._keyframes: list[Keyframe] = []  # every keyframe so far (the last add's)
        self.times = {"loop_closure_s": 0.0, "backend_s": 0.0}

    def add(self, keyframes: list[Keyframe], edge: OdometryEdge | None, wheel: WheelEdge | None) -> list[LoopClosure]:
        """Add ``keyframes[-1]`` (all keyframes known so far are passed: the detector never sees the future)
        with its odometry edge (None for the first keyframe) and wheel edge; returns its accepted closures."""
        kf = keyframes[-1]
        be = self.backend
        t0 = time.perf_counter()
        if edge is None:
            be.add_keyframe(kf.id, kf.odom_pose)
        else:
            be.add_keyframe(kf.id, be.poses[edge.i] @ edge.measurement)
            be.add_odometry(edge.i, edge.j, edge.measurement, edge.covariance, alone=not edge.wheels)
            self.uncertainty.add_edge(edge.i, edge.j, edge.covariance, float(np.linalg.norm(edge.measurement[:self.dim, 3])))
            if wheel is not None:
                be.add_odometry(wheel.i, wheel.j, wheel.measurement, wheel.covariance, group="wheel")
                self.uncertainty.add_edge(wheel.i, wheel.j, wheel.covariance, float(np.linalg.norm(wheel.measurement[:self.dim, 3])))
            if self.calibration is not None:
                for e in (edge, wheel) if wheel is not None else (edge,):
                    self.calibration.add_step(e.i, e.j, e.measurement, e.covariance)
        t1 = time.perf_counter()
        poses = be.poses
        unc = self.uncertainty.from_node(kf.id, poses[:, : self.dim, 3])
        new, relocalise = self.closer.detect(keyframes, poses, kf.id, unc)
        t2 = time.perf_counter()
        self._keyframes = keyframes
        self._add_closures(new, relocalise)
        self.times["loop_closure_s"] += t2 - t1
        self.times["backend_s"] += (t1 - t0) + (time.perf_counter() - t2)
        return new

    def finish(self) -> Array:
        """The groups of the closures still pending when the log ended, then the final batch solve (with
        pruning of violated closures); ``(K, 4, 4)`` keyframe poses."""
        t0 = time.perf_counter()
        while (decided := self.closer.close_open_window(self.backend.poses)) is not None:
            if decided[0]:
                self._add_closures(*decided)
        self.times["loop_closure_s"] += time.perf_counter() - t0
        return self.backend.finish()

    def _add_closures(self, closures: list[LoopClosure], relocalise: bool) -> None:
        """Closures into the graph and the uncertainty search, then the estimate's update: a batch move onto
        them when they are a group the estimate could not vouch for (*relocalise*), else an iSAM2 step."""
        be = self.backend
        for lc in closures:
            be.add_loop(lc)
            self.uncertainty.add_edge(lc.i, lc.j, lc.covariance)
            if self.calibration is not None:
                self.calibration.add_closure(lc.i, lc.j, lc.measurement, lc.covariance)
        self.loops.extend(closures)
        if self.calibration is not None and closures:
            self.uncertainty.scale = self.calibration.update()
            self.window_scale_max = max(self.window_scale_max, self.uncertainty.scale)
        if not relocalise:
            be.update(loop_added=bool(closures))
            return
        before = be.poses.copy()
        be.relocalise()
        if not self.closer.refused:
            return
        # Keyframes the relocalisation moved by more than a floor window were sought under a wrong estimate.
        cfg = self.closer.config
        moved = np.array([np.linalg.norm(d[:3, 3]) > cfg.window_floor_m or G.rotation_angle(d[:3, :3]) > np.radians(cfg.window_floor_deg)
                          for d in (G.relative(a, b) for a, b in zip(before, be.poses))], dtype=bool)
        again, relocalise_again = self.closer.reseek(self._keyframes, be.poses, moved, self.uncertainty)
        if again:
            self._add_closures(again, relocalise_again)

    @property
    def stats(self) -> dict:
        """Loop detection counters plus the closures pruned by the final solve."""
        s = self.closer.summary()
        s["pruned"] = self.backend.pruned_loops
        s["window_scale"] = self.uncertainty.scale  # the closures' calibration of the closer's variances at the end
        s["window_scale_max"] = self.window_scale_max
        s["isam2_restarts"] = self.backend.smoother_restarts
        return s
