"""Loop-closure experiments without re-running odometry: record the front end once, replay the back half.

``record_front_end`` runs :class:`~slam.pipeline.frontend.FrontEnd` over a log exactly as
:func:`slam.pipeline.run.run_slam` does (the front end never looks at the back end, so its keyframes and
odometry edges are the same) and keeps the keyframes, their odometry/wheel edges and the per-scan track.
``replay_loops`` then feeds that keyframe sequence through a fresh
:class:`~slam.loops.closer.LoopCloser` and :class:`~slam.pipeline.backend.PipelineBackend` in the
same incremental order as ``run_slam`` — both go through
:class:`~slam.pipeline.online_graph.OnlineGraph`: add keyframe, add odometry (+ wheel) edge, detect against the
online estimate, add closures, iSAM2 update — and finishes with the final batch solve and pruning.
So one recording serves any number of loop-closure settings, and each replay accepts exactly the
closures ``run_slam`` would with that :class:`~slam.pipeline.config.LoopConfig`.

Poses are ``world_T_base`` (4×4, metres); stamps are seconds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np
from numpy.typing import NDArray

from core.errors import GpslamError
from core.frame import Frame
from slam.loops import LoopClosure

from .backend import PipelineBackend
from .config import BackendConfig, LoopConfig, SlamConfig
from .front_process import run_front_end
from .frontend import Keyframe, OdometryEdge, WheelEdge
from .online_graph import OnlineGraph
from .trajectory import interpolate_scan_poses

Array = NDArray[np.float64]

__all__ = ["FrontEndRecord", "LoopReplay", "record_front_end", "replay_loops"]


@dataclass
class FrontEndRecord:
    """What the front end produced over a log, enough to replay loop closure and the back end.

    Attributes:
        planar: 2D laser log (SE(2) graph) or 3D.
        keyframes: ``(K,)`` keyframes, id = index.
        edges: ``edges[k]`` is the odometry edge into keyframe k (``None`` for k = 0).
        wheel_edges: ``wheel_edges[k]`` is the wheel-odometry edge into keyframe k, when the log has one.
        stamps: ``(N,)`` s, every scan read.
        odometry: ``(N, 4, 4)`` front-end ``world_T_base`` of every scan.
        scan_keyframe: ``(N,)`` id of the latest keyframe at or before each scan.
        ground_truth: ``(N, 4, 4)`` true ``world_T_base`` of every scan when every frame carried one, else None.
        time_s: wall-clock seconds spent in the front end.
    """

    planar: bool
    keyframes: list[Keyframe]
    edges: list[OdometryEdge | None]
    wheel_edges: list[WheelEdge | None]
    stamps: Array
    odometry: Array
    scan_keyframe: NDArray[np.int64]
    ground_truth: Array | None
    time_s: float

    @property
    def keyframe_ground_truth(self) -> Array | None:
        """``(K, 4, 4)`` true poses of the keyframes, or None without ground truth."""
        if self.ground_truth is None:
            return None
        return self.ground_truth[[kf.scan_index for kf in self.keyframes]]

    def scan_poses(self, keyframe_poses: Array) -> Array:
        """``(N, 4, 4)`` pose of every scan from optimised keyframe poses (as ``run_slam`` interpolates them)."""
        kfs = self.keyframes
        return interpolate_scan_poses(self.stamps, self.odometry, self.scan_keyframe, np.array([k.stamp for k in kfs]),
                                      np.array([k.odom_pose for k in kfs]), keyframe_poses, self.planar)


@dataclass
class LoopReplay:
    """Outcome of one loop-closure setting.

    Attributes:
        loops: every closure the verifier accepted, in acceptance order (before pruning).
        stats: :class:`~slam.loops.types.LoopStats` counters plus ``pruned``.
        keyframe_poses: ``(K, 4, 4)`` optimised keyframe poses after the final solve and pruning.
        backend: the back end (its graph holds the closures kept after pruning).
        time_s: wall-clock seconds of detection, verification, online and final solves.
    """

    loops: list[LoopClosure]
    stats: dict
    keyframe_poses: Array
    backend: PipelineBackend
    time_s: float


def record_front_end(frames: Iterable[Frame], config: SlamConfig,
                     progress: Callable[[int, int], None] | None = None) -> FrontEndRecord:
    """Run the configured odometry and keyframe selection over *frames* once (``config.max_scans`` honoured).

    *progress* is called with (scans read, keyframes) after every scan. Raises GpslamError for an empty log.
    """
    from slam.blas import single_blas_thread

    t0 = time.perf_counter()
    keyframes: list[Keyframe] = []
    edges: list[OdometryEdge | None] = []
    wheels: list[WheelEdge | None] = []
    gt: list[Array] = []  # the ground truth of every scan, while every scan has one
    all_gt = True

    def keep(kf: Keyframe, edge: OdometryEdge | None, wheel: WheelEdge | None) -> None:
        keyframes.append(kf)
        edges.append(edge)
        wheels.append(wheel)

    def seen(n: int, frame: Frame) -> None:
        nonlocal all_gt
        if all_gt and frame.ground_truth is None:
            all_gt = False
            gt.clear()
        elif all_gt:
            gt.append(np.asarray(frame.ground_truth, dtype=float))
        if progress is not None:
            progress(n, len(keyframes))

    with single_blas_thread():
        summary = run_front_end(frames, config, keep, seen, processes=False)
    if not keyframes:
        raise GpslamError("the log yielded no scans")
    tr = summary.track
    return FrontEndRecord(
        planar=keyframes[0].frame.is_planar, keyframes=keyframes, edges=edges, wheel_edges=wheels,
        stamps=np.asarray(tr.stamps, dtype=float), odometry=np.asarray(tr.odom_poses, dtype=float),
        scan_keyframe=np.asarray(tr.keyframe, dtype=np.int64),
        ground_truth=np.asarray(gt, dtype=float).reshape(-1, 4, 4) if all_gt else None,
        time_s=time.perf_counter() - t0)


def replay_loops(record: FrontEndRecord, loops: LoopConfig, backend: BackendConfig) -> LoopReplay:
    """Loop detection, verification and the pose graph over *record* with these settings (``run_slam`` order)."""
    from slam.blas import single_blas_thread

    t0 = time.perf_counter()
    with single_blas_thread():
        graph = OnlineGraph(loops, backend, record.planar)
        kfs = record.keyframes
        for kf, edge, wheel in zip(kfs, record.edges, record.wheel_edges):
            graph.add(kfs[: kf.id + 1], edge, wheel)
        poses = graph.finish()
    return LoopReplay(graph.loops, graph.stats, poses, graph.backend, time.perf_counter() - t0)
