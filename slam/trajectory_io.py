"""Trajectories from anywhere a user may point: a trajectory file (:mod:`core.trajectory`) or a robot log,
whose scans carry ground-truth (simulated logs, KITTI) or wheel-odometry poses."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from core.errors import LogFormatError
from core.trajectory import Trajectory, read_trajectory_file

Array = NDArray[np.float64]
PathLike = str | os.PathLike[str]

__all__ = ["read_trajectory", "trajectory_from_log", "LOG_SUFFIXES"]

#: File endings that can only be robot logs (never a TUM/KITTI text file).
LOG_SUFFIXES = (".mcap", ".bag", ".clf", ".clf.bz2", ".clf.gz", ".log.bz2", ".log.gz")


def trajectory_from_log(path: PathLike, source: str = "ground_truth", topic: str | None = None) -> Trajectory:
    """The ``ground_truth`` (simulated logs, KITTI) or ``odom`` (wheel odometry) pose of every scan of a log.

    Poses are ``world_T_base`` (resp. ``odom_T_base``) at the scan stamps, as the log reader gives them.
    """
    from slam.logs import open_log

    if source not in ("ground_truth", "odom"):
        raise LogFormatError(path, None, f"unknown pose source {source!r} (expected ground_truth or odom)")
    stamps: list[float] = []
    poses: list[Array] = []
    for f in open_log(path, topic).frames():
        T = getattr(f, source)
        if T is not None:
            stamps.append(f.stamp)
            poses.append(np.asarray(T, dtype=np.float64))
    if not poses:
        raise LogFormatError(path, None, f"no scan carries a {source} pose")
    return Trajectory(np.array(stamps), np.array(poses), f"{Path(path).name}:{source}").sorted_by_stamp()


def read_trajectory(path: PathLike, fmt: str = "auto", stamps: PathLike | None = None) -> Trajectory:
    """Read a trajectory of format ``tum``, ``kitti``, ``g2o``, ``log_gt`` / ``log_odom`` (the ground-truth /
    odometry poses of a robot log's scans) or ``auto`` (by suffix — logs by :data:`LOG_SUFFIXES` give their
    ground truth — and field count, :func:`core.trajectory.read_trajectory_file`)."""
    p = Path(path)
    if fmt == "auto" and p.name.lower().endswith(LOG_SUFFIXES):
        fmt = "log_gt"
    if fmt in ("log_gt", "log_odom"):
        return trajectory_from_log(p, "ground_truth" if fmt == "log_gt" else "odom")
    return read_trajectory_file(p, fmt, stamps)
