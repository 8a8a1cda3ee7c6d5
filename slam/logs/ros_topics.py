"""Which topic of a ROS log plays which role: the sensor (LaserScan, else PointCloud2), wheel odometry,
ground truth and TF (REP-105 names; the topics with most messages when nothing is named)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from core.errors import LogFormatError, TopicNotFoundError

from .base import TopicInfo
from .ros_msgs import GROUND_TRUTH_NAMES, LASER_SCAN, ODOMETRY, POINTCLOUD2, POSE_STAMPED, SENSOR_TYPES, TF_TYPES

__all__ = ["TopicChoice", "choose_topics"]


def _pick_most(topics: Sequence[TopicInfo], msgtype: str, prefer: Sequence[str] = ()) -> TopicInfo | None:
    cands = [t for t in topics if t.msgtype == msgtype and t.count > 0]
    if not cands:
        return None
    for name in prefer:
        for t in cands:
            if t.name == name:
                return t
    return max(cands, key=lambda t: (t.count, t.name))


def _is_ground_truth_name(topic: str) -> bool:
    return topic.strip("/").split("/")[-1].lower() in GROUND_TRUTH_NAMES


@dataclass
class TopicChoice:
    """Which topic plays which role in a log."""

    sensor: TopicInfo
    odom: TopicInfo | None = None
    ground_truth: TopicInfo | None = None
    tf: list[str] = field(default_factory=list)
    tf_static: list[str] = field(default_factory=list)


def choose_topics(path: Path, topics: list[TopicInfo], topic: str | None, odom_topic: str | None,
                  ground_truth_topic: str | None) -> TopicChoice:
    """Assign the sensor, odometry, ground-truth and TF roles among *topics* of the log *path* (the arguments
    as :class:`~slam.logs.ros_reader.RosLogReader` takes them; raises TopicNotFoundError)."""
    listing = ", ".join(f"{t.name} [{t.msgtype}]" for t in topics) or "none"
    by_name = {t.name: t for t in topics}
    if topic is not None:
        sensor = by_name.get(topic)
        if sensor is None:
            raise TopicNotFoundError(path, None, f"topic {topic!r} not in the log; topics: {listing}")
        if sensor.msgtype not in SENSOR_TYPES:
            raise LogFormatError(
                path, f"topic {topic}", f"unsupported message type {sensor.msgtype} (expected {LASER_SCAN} or {POINTCLOUD2})"
            )
    else:
        sensor = _pick_most(topics, LASER_SCAN) or _pick_most(topics, POINTCLOUD2)
        if sensor is None:
            raise TopicNotFoundError(path, None, f"no LaserScan or PointCloud2 topic with messages; topics: {listing}")
    choice = TopicChoice(sensor=sensor)
    if odom_topic is None:
        non_gt = [t for t in topics if not _is_ground_truth_name(t.name)]
        choice.odom = _pick_most(non_gt, ODOMETRY, prefer=("/odom", "odom"))
    elif odom_topic:
        choice.odom = _require(path, by_name, odom_topic, (ODOMETRY,), listing)
    if ground_truth_topic is None:
        gts = [t for t in topics if _is_ground_truth_name(t.name) and t.msgtype in (ODOMETRY, POSE_STAMPED) and t.count > 0]
        choice.ground_truth = max(gts, key=lambda t: t.count) if gts else None
    elif ground_truth_topic:
        choice.ground_truth = _require(path, by_name, ground_truth_topic, (ODOMETRY, POSE_STAMPED), listing)
    for t in topics:
        if t.msgtype in TF_TYPES:
            (choice.tf_static if t.name.rstrip("/").endswith("tf_static") else choice.tf).append(t.name)
    return choice


def _require(path: Path, by_name: dict[str, TopicInfo], name: str, types: tuple[str, ...], listing: str) -> TopicInfo:
    t = by_name.get(name)
    if t is None:
        raise TopicNotFoundError(path, None, f"topic {name!r} not in the log; topics: {listing}")
    if t.msgtype not in types:
        raise LogFormatError(path, f"topic {name}", f"type {t.msgtype}, expected one of {', '.join(types)}")
    return t
