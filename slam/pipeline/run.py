"""``Pipeline``: the whole pipeline on one log, streaming its frames once (``run_slam`` for short).

1. odometry per scan (KISS-ICP or our scan-to-map ICP; wheel odometry as the initial guess), in its
   own process by default, running ahead of the rest;
2. keyframes and odometry edges with the compounded registration covariance;
3. loop closures for every keyframe, verified by ICP (χ², fitness, consistency);
4. iSAM2 after every keyframe (or periodic chordal batch solves), a final batch solve;
5. the self-check of the result against its own scans (:mod:`slam.pipeline.self_check`);
6. a pose for every scan, the occupancy map from the keyframe scans, all outputs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from core.errors import GpslamError
from slam.loops import LoopClosure

from .backend import PipelineBackend
from .config import SlamConfig
from .front_process import run_front_end
from .frontend import Keyframe
from .online_graph import OnlineGraph
from .self_check import self_check
from .trajectory import interpolate_scan_poses

Array = NDArray[np.float64]


@dataclass
class Progress:
    """What the progress bar shows after each scan."""

    scans: int
    keyframes: int
    loop_closures: int
    elapsed_s: float


@dataclass
class SlamResult:
    """Everything the outputs are written from."""

    planar: bool
    stamps: Array  # (N,) every scan
    poses: Array  # (N, 4, 4) optimised world_T_base of every scan
    odometry: Array  # (N, 4, 4) front-end odometry world_T_base
    wheel: Array | None  # (N, 4, 4) raw wheel odometry, when every scan has it
    keyframes: list[Keyframe]
    keyframe_poses: Array  # (K, 4, 4) optimised
    backend: PipelineBackend
    loops: list[LoopClosure]
    loop_stats: dict
    stage_times_s: dict[str, float]
    occupancy_map: object | None = None  # mapping.occupancy_map.OccupancyMap
    map_scans_fused: int = 0
    odometry_stats: dict = field(default_factory=dict)  # alternative ICP starts taken, wheel edges left out
    peak_memory_mb: dict[str, float] = field(default_factory=dict)  # of the stage processes ("front_end", "mapping"), when they ran as such
    self_check: dict = field(default_factory=dict)  # slam.pipeline.self_check: does the result contradict its own data?


def run_slam(frames, config: SlamConfig, progress: Callable[[Progress], None] | None = None) -> SlamResult:
    """``Pipeline(config, progress).run(frames)``."""
    return Pipeline(config, progress).run(frames)


class Pipeline:
    """The whole SLAM pipeline on one log: the front end's frame loop (:func:`run_front_end`, shared with
    the loop replay), loop closure and the back end (:class:`OnlineGraph`, also shared with the replay)
    and the mapping stage for every keyframe, then the final solve, the self-check, every scan's pose
    and the map. One object per run."""

    def __init__(self, config: SlamConfig, progress: Callable[[Progress], None] | None = None) -> None:
        self.config = config
        self.progress = progress
        self.keyframes: list[Keyframe] = []
        self.graph: OnlineGraph | None = None  # loop closure + back end, made for the first keyframe's dimension
        self.mapper = None  # the mapping stage (inline or its process), likewise
        self.times = {"odometry_s": 0.0, "loop_closure_s": 0.0, "backend_s": 0.0, "mapping_s": 0.0, "final_solve_s": 0.0}
        self._t_start = 0.0

    def run(self, frames) -> SlamResult:  # type: ignore[no-untyped-def]
        """Run over an iterable of :class:`Frame` (time order). BLAS runs single-threaded.

        With ``config.stage_processes`` (the default) odometry and mapping run in child processes
        (:mod:`slam.pipeline.front_process`, :mod:`slam.pipeline.mapping_process`); a script calling this
        then needs the usual ``if __name__ == "__main__":`` guard of multiprocessing. A frame generator is
        closed on the way out, also on an error or Ctrl-C, so a reader's background thread stops here
        rather than at interpreter shutdown."""
        from slam.blas import single_blas_thread

        try:
            with single_blas_thread():
                return self._run(frames)
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()

    def add_keyframe(self, kf: Keyframe, edge, wheel) -> None:  # type: ignore[no-untyped-def]
        """The back half for one keyframe from the front end: loop closure, the graph, the map."""
        from .mapping_process import start_mapping

        if self.graph is None:
            planar = kf.frame.is_planar
            self.graph = OnlineGraph(self.config.loops, self.config.backend, planar)
            self.mapper = start_mapping(self.config.mapping, planar, self.config.stage_processes)
        self.keyframes.append(kf)
        new = self.graph.add(self.keyframes, edge, wheel)
        t5 = time.perf_counter()
        self.mapper.add_keyframe(kf, self.graph.backend.poses[kf.id])
        kf.drop_cloud()  # loop closure and mapping have read it: a 3D cloud is not needed again
        if new:
            self.mapper.refresh(self.graph.backend.poses)
        self.times["mapping_s"] += time.perf_counter() - t5

    def _on_scan(self, n: int, _frame) -> None:  # type: ignore[no-untyped-def]
        if self.progress is not None:
            loops = len(self.graph.loops) if self.graph is not None else 0
            self.progress(Progress(n, len(self.keyframes), loops, time.perf_counter() - self._t_start))

    def _run(self, frames) -> SlamResult:  # type: ignore[no-untyped-def]
        from .mapping_process import MappingProcess

        self._t_start = time.perf_counter()
        times = self.times
        try:
            summary = run_front_end(frames, self.config, self.add_keyframe, self._on_scan)
            graph, mapper, keyframes = self.graph, self.mapper, self.keyframes
            if graph is None or mapper is None:
                raise GpslamError("the log yielded no scans")
            planar = keyframes[0].frame.is_planar
            t4 = time.perf_counter()
            kf_poses = graph.finish()
            times["final_solve_s"] = time.perf_counter() - t4
            if isinstance(mapper, MappingProcess):
                mapper.request_final(kf_poses)  # the map is fused in its process while the self-check runs here
            t7 = time.perf_counter()
            check = self_check(keyframes, kf_poses, graph.loops, planar).as_dict()
            times["self_check_s"] = time.perf_counter() - t7
            t6 = time.perf_counter()
            occ = mapper.finish(kf_poses)
            if isinstance(mapper, MappingProcess):
                times["mapping_s"] += mapper.time_s  # the child's busy time; this process only sent it scans
            else:
                times["mapping_s"] += time.perf_counter() - t6
        finally:
            if self.mapper is not None:
                self.mapper.close()
        times["odometry_s"] = summary.odometry_s
        times.update(graph.times)
        tr = summary.track
        stamps = np.asarray(tr.stamps)
        odom = np.asarray(tr.odom_poses)
        kfs = keyframes
        poses = interpolate_scan_poses(stamps, odom, np.asarray(tr.keyframe), np.array([k.stamp for k in kfs]),
                                       np.array([k.odom_pose for k in kfs]), kf_poses, planar)
        wheel = np.asarray(tr.wheel_poses) if all(w is not None for w in tr.wheel_poses) else None
        peaks = {"front_end": summary.peak_memory_mb} if self.config.stage_processes else {}
        if isinstance(mapper, MappingProcess):
            peaks["mapping"] = mapper.peak_memory_mb
        return SlamResult(planar, stamps, poses, odom, wheel, kfs, kf_poses, graph.backend, graph.loops, graph.stats,
                          times, occ, map_scans_fused=mapper.scans_fused, odometry_stats=summary.stats,
                          peak_memory_mb=peaks, self_check=check)
