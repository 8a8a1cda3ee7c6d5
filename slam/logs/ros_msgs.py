"""ROS message decoding shared by the MCAP (ROS 2) and ROS 1 bag readers and the MCAP writer.

* the rosbags typestores (ROS 2 Humble for writing; per-file stores built from the message
  definitions carried in the log for reading, so that files written by others decode too);
* stamp conversion float seconds ↔ ``builtin_interfaces/Time`` (sec, nanosec) to the nanosecond;
* message → pose conversion (Odometry, PoseStamped, TransformStamped) and LaserScan → :class:`~core.frame.Frame`.

PointCloud2 decoding is in :mod:`slam.logs.pointcloud2`, the TF buffer in :mod:`slam.logs.tf_buffer` and the
streaming frame assembly of both readers in :mod:`slam.logs.ros_reader`.

Frames of reference follow REP-105: an Odometry message gives ``odom_T_base`` (header.frame_id →
child_frame_id), a TransformStamped gives ``parent_T_child``. Poses are 4×4 float64 matrices,
stamps float seconds, lengths metres.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core import pose_formats
from core.errors import LogFormatError
from core.frame import Frame


Array = NDArray[np.float64]

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_TYPES = (TF_MESSAGE, "tf/msg/tfMessage")  # ROS 1 bags may still carry the old tf type (same layout)
SENSOR_TYPES = (LASER_SCAN, POINTCLOUD2)
GROUND_TRUTH_NAMES = ("ground_truth", "groundtruth", "gt", "base_pose_ground_truth")
BASE_FRAMES = ("base_link", "base_footprint")

# ----------------------------------------------------------------------------- typestores


@functools.lru_cache(maxsize=None)
def humble_typestore():
    """The rosbags typestore of ROS 2 Humble (message classes and CDR serialisers)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def normalize_msgtype(name: str) -> str:
    """``sensor_msgs/LaserScan`` → ``sensor_msgs/msg/LaserScan`` (ROS 1 and ROS 2 spellings agree)."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.strip()


def message_definition(msgtype: str) -> str:
    """Full ROS 2 ``.msg`` text of *msgtype* with every dependent type appended after a line of
    80 ``=`` and ``MSG: pkg/msg/Type`` — the ``ros2msg`` schema encoding of MCAP / Foxglove."""
    text, _ = humble_typestore().generate_msgdef(msgtype, ros_version=2)
    return text


def build_typestore(definitions: Iterable[tuple[str, str, str]]):
    """A fresh typestore holding the types described by *definitions*.

    Args:
        definitions: ``(msgtype, encoding, text)`` with encoding ``"msg"`` (a concatenated ``.msg``
            definition, ROS 1 or ROS 2) or ``"idl"``.

    Raises whatever rosbags raises on a malformed or conflicting definition (callers wrap it in
    a :class:`LogFormatError` naming the file).
    """
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    for msgtype, encoding, text in definitions:
        if encoding == "idl":
            sep = "=" * 80 + "\n"
            chunks = text.split(sep)[1:] if text.startswith(f"{sep}IDL: ") else [text]
            for chunk in chunks:
                body = chunk.split("\n", 1)[1] if chunk.startswith("IDL: ") else chunk
                store.register(get_types_from_idl(body))
        else:
            store.register(get_types_from_msg(text, msgtype))
    return store


@functools.lru_cache(maxsize=16)
def cached_typestore(definitions: tuple[tuple[str, str, str], ...]):
    """:func:`build_typestore` memoised on the exact definitions: reopening a log (or another log
    with the same schemas) reuses the parsed types and rosbags' generated deserialisers, which
    cost tens of milliseconds per file otherwise. The store is only read from after building."""
    return build_typestore(definitions)


# ----------------------------------------------------------------------------- stamps


def stamp_to_time(stamp: float) -> tuple[int, int]:
    """Float seconds → (sec, nanosec) with 0 ≤ nanosec < 10⁹, rounded to the nearest nanosecond.

    ``stamp - floor(stamp)`` is exact in floating point, so no precision is lost for large epoch
    stamps (a plain ``stamp * 1e9`` would round to 256 ns at 1.7·10⁹ s).
    """
    if not math.isfinite(stamp):
        raise ValueError(f"stamp must be finite, got {stamp}")
    sec = math.floor(stamp)
    nsec = round((stamp - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return int(sec), int(nsec)


def stamp_to_ns(stamp: float) -> int:
    """Float seconds → integer nanoseconds (exact integer arithmetic after :func:`stamp_to_time`)."""
    sec, nsec = stamp_to_time(stamp)
    return sec * 1_000_000_000 + nsec


def time_to_stamp(t: Any) -> float:
    """A ``builtin_interfaces/Time`` (or ROS 1 ``time``) → float seconds."""
    return float(t.sec) + int(t.nanosec) / 1e9


def header_stamp(msg: Any) -> float:
    """Stamp of a message's ``header`` in float seconds."""
    return time_to_stamp(msg.header.stamp)


def strip_frame(frame_id: str) -> str:
    """tf2 frame ids carry no leading slash (``/base_link`` and ``base_link`` are the same frame)."""
    return frame_id.lstrip("/")


# ----------------------------------------------------------------------------- poses


def _check_vec(v: Array) -> Array:
    """*v* if its numbers are finite and its quaternion has a finite, non-zero norm (one of garbage size
    overflows: refused here rather than warned about by numpy)."""
    with np.errstate(over="ignore"):
        qn = float(np.linalg.norm(v[3:]))
    if not np.all(np.isfinite(v)) or not (1e-12 <= qn < np.inf):
        raise ValueError(f"invalid pose (translation, quaternion) {v.tolist()}")
    return v


def pose_msg_vec(pose: Any) -> Array:
    """``geometry_msgs/Pose`` → ``(7,)`` = x, y, z, qx, qy, qz, qw (raises ValueError if not finite / zero quaternion)."""
    p, q = pose.position, pose.orientation
    return _check_vec(np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=float))


def transform_msg_vec(tf: Any) -> Array:
    """``geometry_msgs/Transform`` → ``(7,)`` = x, y, z, qx, qy, qz, qw."""
    t, q = tf.translation, tf.rotation
    return _check_vec(np.array([t.x, t.y, t.z, q.x, q.y, q.z, q.w], dtype=float))


def vecs_to_matrices(v: Array) -> Array:
    """``(..., 7)`` translation + quaternion → ``(..., 4, 4)`` poses (one vectorised call)."""
    v = np.asarray(v, dtype=float)
    return pose_formats.pose_from_quat(v[..., :3], v[..., 3:])


def pose_msg_to_matrix(pose: Any) -> Array:
    """``geometry_msgs/Pose`` → 4×4 (the quaternion is normalised)."""
    return vecs_to_matrices(pose_msg_vec(pose))


def transform_msg_to_matrix(tf: Any) -> Array:
    """``geometry_msgs/Transform`` → 4×4 ``parent_T_child``."""
    return vecs_to_matrices(transform_msg_vec(tf))


def interpolate_pose(a: Array, b: Array, alpha: ArrayLike) -> Array:
    """Geodesic interpolation on SE(3): ``a · Exp(α · Log(a⁻¹ b))`` (Barfoot 2017, eq. 7.86/7.94).

    Works on one pair or stacks ``(N, 4, 4)`` with ``alpha`` ``(N,)``. For planar poses (z = 0,
    rotation about z) the result stays planar and equals the SE(2) geodesic. ``alpha`` = 0
    gives *a* exactly, 1 gives *b* exactly.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    al = np.asarray(alpha, dtype=float)
    out = a @ geo.se3_exp(al[..., None] * geo.se3_log(geo.relative(a, b)))
    out = np.where((al <= 0.0)[..., None, None], a, out)
    return np.where((al >= 1.0)[..., None, None], b, out)


# ----------------------------------------------------------------------------- LaserScan


def scan_arrays(msg: Any) -> tuple[Array, Array]:
    """Beam angles (``angle_min + i·angle_increment``, float64 rad) and ranges (float64 m) of a LaserScan."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    angles = float(msg.angle_min) + np.arange(ranges.shape[0], dtype=np.float64) * float(msg.angle_increment)
    return angles, ranges


def beam_times(msg: Any, n: int) -> Array | None:
    """Each beam's time after the stamp, ``i·time_increment`` (REP-117 / sensor_msgs/LaserScan: the
    stamp is the first beam's), or None where the driver left it out: a ``time_increment`` that is zero or
    not finite, or a sweep (n − 1)·|time_increment| longer than ``scan_time`` (when given) or than a second.
    A negative increment (a driver that says its last beam came first) gives the times counted from the last
    beam; which way they really run is read from the scans before deskewing (registration.sweep_check)."""
    inc = float(getattr(msg, "time_increment", 0.0) or 0.0)
    if not (math.isfinite(inc) and inc != 0.0):
        return None
    period = float(getattr(msg, "scan_time", 0.0) or 0.0)
    limit = period * 1.01 if math.isfinite(period) and period > 0.0 else 1.0
    if (n - 1) * abs(inc) > limit:
        return None
    order = np.arange(n, dtype=np.float64)
    return (order if inc > 0 else order[::-1]) * abs(inc)


def check_scan(msg: Any, path: Path | str, where: str) -> None:
    """Reject scans the pipeline cannot use, naming the file and message.

    REP-117 lets a driver report ``-inf`` (object closer than ``range_min``) and ``NaN`` (an
    erroneous reading). This project refuses both, and any other negative range: a mapping back
    end cannot tell free from unknown space along such a beam, and a silent drop would hide a
    broken driver or a bad conversion. ``+inf`` (no return, REP-117) is accepted. A scan with
    zero beams, a non-positive or non-finite angle increment, or ``range_max`` ≤ 0 is malformed.
    """
    r = np.asarray(msg.ranges)
    if r.shape[0] == 0:
        raise LogFormatError(path, where, "empty LaserScan (0 beams)")
    inc = float(msg.angle_increment)
    if not math.isfinite(inc) or inc == 0.0 or not math.isfinite(float(msg.angle_min)):
        raise LogFormatError(path, where, f"LaserScan angle_min/angle_increment must be finite and nonzero, got {msg.angle_min}/{inc}")
    if not float(msg.range_max) > 0.0:
        raise LogFormatError(path, where, f"LaserScan range_max must be > 0, got {msg.range_max}")
    bad_nan = np.isnan(r)
    if bad_nan.any():
        i = int(np.argmax(bad_nan))
        raise LogFormatError(path, where, f"LaserScan beam {i} range is NaN (REP-117 error reading; expected a range or +inf)")
    neg = r < 0
    if neg.any():
        i = int(np.argmax(neg))
        raise LogFormatError(path, where, f"LaserScan beam {i} range is {float(r[i])} (negative; expected ≥ 0 or +inf)")


def scan_to_frame(msg: Any, path: Path | str, where: str, index: int, **extra: Any) -> Frame:
    """A ``sensor_msgs/LaserScan`` → planar :class:`Frame` (sensor frame, metres).

    ``no_return`` is True for ``+inf`` and for ranges ≥ ``range_max`` (max-range readings);
    those are stored as ``inf`` in ``ranges``. Points are the returned beams with
    ``range_min ≤ r < range_max`` at ``r·(cos a, sin a)``. Beams below ``range_min`` (e.g. the 0
    many drivers report for "no measurement") are neither a hit nor free space and are left out
    of ``angles`` / ``ranges`` / ``no_return`` — as the CARMEN reader drops zero ranges — so every
    beam of a Frame is either a point or a no-return; the kept beams keep their angles
    ``angle_min + i·angle_increment``, and their times ``i·time_increment`` when the driver gives them
    (:func:`beam_times`; the front end deskews with them).
    """
    check_scan(msg, path, where)
    angles, ranges = scan_arrays(msg)
    times = beam_times(msg, len(ranges))
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    keep = ranges >= rmin  # +inf included
    if not keep.all():
        angles, ranges = angles[keep], ranges[keep]
        times = None if times is None else times[keep]
    no_return = ranges >= rmax  # +inf included
    ranges = np.where(no_return, np.inf, ranges)
    hit = ~no_return
    r, a = ranges[hit], angles[hit]
    points = np.column_stack([r * np.cos(a), r * np.sin(a)])
    return Frame(
        stamp=header_stamp(msg),
        points=points,
        index=index,
        angles=angles,
        ranges=ranges,
        no_return=no_return,
        beam_times=times,
        max_range=rmax,
        min_range=rmin,
        source=f"{Path(path).name}:{where}",
        **extra,
    )


@dataclass
class RawMessage:
    """One message of a log, not yet decoded."""

    index: int  # position among the messages of its topic, in time order (0-based)
    topic: str
    msgtype: str
    log_time_ns: int
    data: Any  # the serialised message: bytes, or a read-only memoryview (MCAP indexed path)
    where: str = ""  # e.g. "/scan message 12", for error messages
