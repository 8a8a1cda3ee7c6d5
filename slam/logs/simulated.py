"""A simulated run (:func:`evaluation.sim.simulate`) written as a robot log: a ROS 2 MCAP with scans, wheel
odometry, tf and ground truth, and the world's map beside it as the ground-truth map."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from core import geometry as geo
from evaluation.sim.simulate import SimulatedLog

from .mcap_writer import McapLogWriter

__all__ = ["write_simulated_log", "map_paths"]


def map_paths(mcap_path: str | Path) -> tuple[Path, Path]:
    """Where :func:`write_simulated_log` puts the ground-truth map: ``<stem>_map.yaml``/``.pgm``."""
    p = Path(mcap_path)
    return p.with_name(f"{p.stem}_map.yaml"), p.with_name(f"{p.stem}_map.pgm")


def write_simulated_log(sim: SimulatedLog, mcap_path: str | Path) -> None:
    """Write the run as a ROS 2 MCAP log plus the ground-truth map beside it.

    Topics: ``/scan`` (sensor_msgs/LaserScan, frame ``laser``), ``/odom`` (nav_msgs/Odometry
    ``odom → base_link``, with the odometry twist), ``/tf`` (``odom → base_link``), ``/tf_static``
    (``base_link → laser``), ``/ground_truth`` (nav_msgs/Odometry ``map → base_link``). The map
    is ``<stem>_map.pgm`` + ``<stem>_map.yaml`` (map_server). Nothing appears under the final
    names unless everything was written.
    """
    out = Path(mcap_path)
    yaml_path, pgm_path = map_paths(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    try:
        sim.world.save(tmp / yaml_path.name, image_name=pgm_path.name)
        spec = sim.spec
        odo_xyt = geo.matrix_to_xytheta(sim.odometry)
        dt = np.diff(sim.stamps)
        step = geo.relative(sim.odometry[:-1], sim.odometry[1:])
        vel = np.zeros((len(sim), 6))
        if len(sim) > 1:
            vel[1:, 0] = step[:, 0, 3] / dt
            vel[1:, 1] = step[:, 1, 3] / dt
            vel[1:, 5] = geo.wrap_angle(np.diff(odo_xyt[:, 2])) / dt
        with McapLogWriter(out) as w:
            w.write_tf(float(sim.stamps[0]), [("base_link", "laser", sim.base_T_sensor)], static=True)
            for i in range(len(sim)):
                t = float(sim.stamps[i])
                w.write_tf(t, [("odom", "base_link", sim.odometry[i])])
                w.write_odometry("/odom", t, "odom", "base_link", sim.odometry[i], twist=vel[i])
                w.write_odometry("/ground_truth", t, "map", "base_link", sim.ground_truth[i])
                w.write_scan("/scan", t, "laser", spec.angle_min, spec.angle_increment, spec.range_min,
                             spec.range_max, sim.ranges[i], time_increment=spec.time_increment,
                             scan_time=spec.period if spec.revolution_s > 0 else 0.0)
        # the MCAP is complete under its final name; the finished map files follow by rename
        os.replace(tmp / pgm_path.name, pgm_path)
        os.replace(tmp / yaml_path.name, yaml_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
