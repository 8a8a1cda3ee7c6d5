"""Write the results of a SLAM run into one folder, atomically (see docs/ARCHITECTURE.md).

Files: ``trajectory.tum`` (optimised pose of every scan), ``odometry.tum`` (front-end odometry),
``wheel_odometry.tum`` (when the log has it), ``graph.g2o`` (loop edges marked), ``node_stamps.txt``
(graph node id → scan stamp), map files (``map.pgm/.yaml/.png``, ``variance.png``, ``map.npz``),
``points.ply`` (3D logs), ``result.mcap`` (OccupancyGrid, Paths, TF, keyframe scans; opens in
Foxglove), ``summary.json`` and ``config.yaml``. Everything is first written into a temporary
folder beside the target and moved in only when complete, replacing an earlier run's folder whole.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path
from typing import Callable

import numpy as np

from core.atomic import atomic_directory
from core.run_summary import RunSummary

from .config import SlamConfig
from .consistency import closure_consistency
from .run import SlamResult

#: Files every run folder holds: an existing folder with them is an earlier run, which a new run replaces.
RUN_MARKER = ("summary.json", "config.yaml")


def _versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for pkg in ("gpslam", "numpy", "scipy", "gtsam", "kiss-icp", "open3d", "mcap", "rosbags"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _write_mcap(path: Path, result: SlamResult, occ_map) -> None:  # type: ignore[no-untyped-def]
    from mapping.occupancy_map import write_occupancy_grid
    from slam.logs.mcap_writer import McapLogWriter

    t_end = float(result.stamps[-1])
    with McapLogWriter(path) as w:
        if occ_map is not None:
            write_occupancy_grid(occ_map, w, "/map", "map", float(result.stamps[0]))
        w.write_path("/path", t_end, "map", result.stamps, result.poses)
        w.write_path("/odometry_path", t_end, "map", result.stamps, result.odometry)
        kf_index = {kf.scan_index for kf in result.keyframes}
        for s, (t, T) in enumerate(zip(result.stamps, result.poses)):
            if s in kf_index or s % 5 == 0:
                w.write_tf(float(t), [("map", "base_link", T)])
        for kf, T in zip(result.keyframes, result.keyframe_poses):
            f = kf.frame
            w.write_tf(float(f.stamp), [("base_link", "sensor", kf.base_T_sensor)])
            if f.is_planar and f.ranges is not None and len(f.angles) > 1:
                inc = float((f.angles[-1] - f.angles[0]) / (len(f.angles) - 1))
                rmax = f.max_range if np.isfinite(f.max_range) else float(np.nanmax(np.where(np.isfinite(f.ranges), f.ranges, 0)) + 1)
                w.write_scan("/scan", float(f.stamp), "sensor", float(f.angles[0]), inc, f.min_range, rmax, f.ranges)
            elif not f.is_planar:
                w.write_pointcloud("/points", float(f.stamp), "sensor", kf.points)


def _write_ply(path: Path, result: SlamResult, voxel: float) -> None:
    import open3d as o3d

    from core import geometry as G
    from registration.voxel import voxel_downsample_stream

    # Batch by batch: every keyframe's points in the world at once would be ~1.4 GB on a 4,500-frame drive.
    parts = (G.transform_points(T @ kf.base_T_sensor, kf.points) for kf, T in zip(result.keyframes, result.keyframe_poses))
    pts = voxel_downsample_stream(parts, voxel)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if not o3d.io.write_point_cloud(str(path), pc):
        raise OSError(f"open3d could not write {path}")


def summarise(result: SlamResult, log: str, config: SlamConfig, run_s: float, wall_time_s: float, outputs_s: float,
              peak_main_mb: float, skipped=None) -> RunSummary:  # type: ignore[no-untyped-def]
    """The :class:`~core.run_summary.RunSummary` of *result*: *run_s* the pipeline's time (reading and SLAM),
    *wall_time_s* until the last file, *outputs_s* writing the files, *peak_main_mb* this process's peak (the
    stage processes' come with the result); *skipped* the :class:`~slam.logs.SkipLog` of ``on_error: skip``."""
    n = len(result.stamps)
    closure_nees, chain_model = closure_consistency(result.backend.graph,
                                                    float(np.radians(config.loops.heading_drift_deg_per_m)))
    scans_lost, exact = skipped.scans() if skipped is not None else (0, True)
    peaks = {"main": float(peak_main_mb), **result.peak_memory_mb}
    return RunSummary(
        log=log, scans=n, keyframes=len(result.keyframes),
        loop_closures=len(result.loops) - result.loop_stats.get("pruned", 0),
        loop_stats=result.loop_stats, odometry_stats=result.odometry_stats, self_check=result.self_check,
        dimension=2 if result.planar else 3, stage_times_s=result.stage_times_s | {"outputs_s": outputs_s},
        map_scans_fused=result.map_scans_fused, on_error=config.on_error,
        skipped_records=skipped.records() if skipped is not None else 0, skipped_scans=scans_lost,
        skipped_scans_exact=exact, errors=skipped.lines() if skipped is not None else [],
        wall_time_s=wall_time_s, scans_per_second=n / run_s if run_s > 0 else 0.0,
        peak_memory_mb=sum(peaks.values()), peak_memory_by_process_mb=peaks,
        versions=_versions(), config=config.model_dump(mode="json"),
        stamps_not_increasing=int(np.count_nonzero(np.diff(np.asarray(result.stamps, dtype=float)) <= 0.0)),
        pruned_closures=_pruned(result),
        variance_components=(result.backend.variance_components.as_dict()
                             if result.backend.variance_components is not None else None),
        closure_nees=closure_nees, chain_model=chain_model,
    )


def _pruned(result: SlamResult) -> list[dict]:
    """The closures the final solve dropped, with their keyframes' stamps (node ids are keyframe indices)."""
    kfs = result.keyframes
    return [{"i": p.i, "j": p.j, "stamp_i": float(kfs[p.i].stamp), "stamp_j": float(kfs[p.j].stamp),
             "translation_m": p.translation_m, "rotation_deg": p.rotation_deg, "round": p.round}
            for p in result.backend.pruned]


def write_outputs(out_dir: str | Path, result: SlamResult, occ_map, config: SlamConfig,  # type: ignore[no-untyped-def]
                  summary: Callable[[float], RunSummary], before_commit: Callable[[Path], None] | None = None) -> Path:
    """Write every output of a run into *out_dir* (atomically); returns the folder.

    ``summary(outputs_s)`` gives the run's summary once the other files are written (*outputs_s* the time
    they took); it is written once, as ``summary.json``. *before_commit*, when given, is then called with the
    temporary folder and may add files there (an evaluation report): they are moved into *out_dir* together
    with the rest, or not at all.
    """
    from core.trajectory import Trajectory, write_tum
    from mapping.occupancy_map import export_map
    from slam.graph.g2o import write_g2o

    out = Path(out_dir)
    t0 = time.perf_counter()
    with atomic_directory(out, RUN_MARKER) as tmp:
        write_tum(tmp / "trajectory.tum", Trajectory(result.stamps, result.poses, "slam"))
        write_tum(tmp / "odometry.tum", Trajectory(result.stamps, result.odometry, "odometry"))
        if result.wheel is not None:
            write_tum(tmp / "wheel_odometry.tum", Trajectory(result.stamps, result.wheel, "wheel odometry"))
        write_g2o(result.backend.graph, tmp / "graph.g2o")
        with open(tmp / "node_stamps.txt", "w") as fh:
            fh.write("# node_id stamp\n")
            fh.writelines(f"{kf.id} {kf.stamp!r}\n" for kf in result.keyframes)
        if occ_map is not None:
            export_map(occ_map, tmp, config.mapping.params.occupied_thresh, config.mapping.params.free_thresh)
        if not result.planar:
            _write_ply(tmp / "points.ply", result, config.mapping.point_map_voxel_m)
        _write_mcap(tmp / "result.mcap", result, occ_map)
        (tmp / "config.yaml").write_text(config.to_yaml())
        (tmp / "summary.json").write_text(summary(time.perf_counter() - t0).model_dump_json(indent=2) + "\n")
        if before_commit is not None:
            before_commit(tmp)
    return out
