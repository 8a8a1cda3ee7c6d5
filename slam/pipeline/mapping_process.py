"""The mapping stage in its own process: Fast-GPOM submaps are built beside loop closure and the back end.

Mapping only consumes keyframes and poses and feeds nothing back until the end, so a child process
(:class:`~slam.pipeline.child.ChildProcess`) can run the :class:`~slam.pipeline.mapping_stage.MapBuilder`
while this one closes loops. It receives each keyframe's planar scan (made here: for 3D clouds the
height-band slice, not the cloud) with the pose of the moment, and the keyframe poses whenever a
recomposition is due — the same calls in the same order as inline, so the map is the same bit for bit.
"""

from __future__ import annotations

import time
from typing import Iterator

from numpy.typing import NDArray

from mapping.occupancy_map import OccupancyMap

from .child import ChildProcess, Reply, peak_memory_mb
from .config import MappingStageConfig
from .frontend import Keyframe
from .mapping_stage import MapBuilder, RecomposeSchedule


def _serve(config: MappingStageConfig, planar: bool, messages: Iterator[tuple], reply: Reply) -> None:
    """Child: ("scan", id, scan, pose), ("recompose", poses), ("finish", poses) → ("map", map, scans fused,
    busy seconds, peak MB)."""
    builder = MapBuilder(config, planar)
    scans = []  # kept for the baselines, which map every keyframe at the final poses
    busy = 0.0
    for msg in messages:
        t0 = time.perf_counter()
        kind = msg[0]
        if kind == "scan":
            _, kf_id, scan, pose = msg
            if builder.online:
                builder.add_scan(kf_id, scan, pose)
            else:
                scans.append(scan)
        elif kind == "recompose":
            builder.refresh(msg[1], force=True)
        else:
            occ = builder.finish_scans(scans, msg[1])
            busy += time.perf_counter() - t0
            reply(("map", occ, builder.scans_fused, busy, peak_memory_mb()))
            continue
        busy += time.perf_counter() - t0


def start_mapping(config: MappingStageConfig, planar: bool, process: bool) -> MapBuilder | MappingProcess:
    """The mapping stage in a child process (with *process*, when mapping is on) or inline."""
    return MappingProcess(config, planar) if process and config.enabled else MapBuilder(config, planar)


class MappingProcess:
    """:class:`MapBuilder`'s interface for ``run_slam``, with the builder in a child process.

    After :meth:`finish`: ``scans_fused``, ``time_s`` (the child's busy time) and ``peak_memory_mb``.
    """

    def __init__(self, config: MappingStageConfig, planar: bool) -> None:
        self._scans = MapBuilder(config, planar)  # here only to make the planar scans (scan_for)
        self.online = self._scans.online
        self._schedule = RecomposeSchedule(config.recompose_every_keyframes)
        self._child = ChildProcess(_serve, (config, planar), "mapping")
        self._requested = False  # the final map asked for (request_final)
        self.scans_fused = 0
        self.time_s = 0.0
        self.peak_memory_mb = 0.0

    def add_keyframe(self, kf: Keyframe, pose: NDArray) -> None:
        """Send keyframe *kf*'s planar scan and its pose of the moment; raises a failure of the child."""
        for _ in self._child.replies():  # nothing is due before finish: only an error can be waiting
            pass
        self._child.send(("scan", kf.id, self._scans.scan_for(kf), pose))

    def refresh(self, keyframe_poses: NDArray) -> None:
        """Recompose at the current poses when due (every ``recompose_every_keyframes`` calls)."""
        if self.online and self._schedule.due():
            self._child.send(("recompose", keyframe_poses))

    def request_final(self, keyframe_poses: NDArray) -> None:
        """Have the child start the final map at *keyframe_poses* now (the caller works on meanwhile);
        :meth:`finish` with the same poses collects it."""
        self._child.send(("finish", keyframe_poses))
        self._requested = True

    def finish(self, keyframe_poses: NDArray) -> OccupancyMap | None:
        """The final map at the final keyframe poses (waits for the child)."""
        if not self._requested:
            self.request_final(keyframe_poses)
        _, occ, self.scans_fused, self.time_s, self.peak_memory_mb = self._child.receive(wait=True)  # type: ignore[misc]
        self._child.send(None)
        self._child.join()
        return occ

    def close(self) -> None:
        self._child.close()
