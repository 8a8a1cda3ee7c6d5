"""ROS message handling shared by the MCAP (ROS 2) and ROS 1 bag readers and the MCAP writer.

What lives here:

* the rosbags typestores (ROS 2 Humble for writing; per-file stores built from the message
  definitions carried in the log for reading, so that files written by others decode too);
* stamp conversion float seconds ↔ ``builtin_interfaces/Time`` (sec, nanosec) to the nanosecond;
* message → pose / :class:`~core.frame.Frame` conversion (LaserScan, PointCloud2,
  Odometry, PoseStamped, TFMessage);
* a vectorised PointCloud2 decoder for any field layout;
* a small TF buffer (static + dynamic transforms) and a pose track that interpolates odometry
  to the scan stamps;
* :class:`RosLogReader`, the streaming frame assembly both readers share.

Frames of reference follow REP-105: an Odometry message gives ``odom_T_base`` (header.frame_id →
child_frame_id), a TransformStamped gives ``parent_T_child``. Poses are 4×4 float64 matrices,
stamps float seconds, lengths metres.
"""

from __future__ import annotations

import abc
import bisect
import contextlib
import functools
import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core.errors import LogFormatError, TopicNotFoundError
from core.frame import Frame

from .base import LogInfo, LogReader, SkipHandler, TopicInfo, counting, lost

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
    return geo.pose_from_quat(v[..., :3], v[..., 3:])


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
    ``angle_min + i·angle_increment``.
    """
    check_scan(msg, path, where)
    angles, ranges = scan_arrays(msg)
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    keep = ranges >= rmin  # +inf included
    if not keep.all():
        angles, ranges = angles[keep], ranges[keep]
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
        max_range=rmax,
        min_range=rmin,
        source=f"{Path(path).name}:{where}",
        **extra,
    )


# ----------------------------------------------------------------------------- PointCloud2

# sensor_msgs/PointField datatypes → numpy type codes (without byte order).
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
NUMPY_TO_POINTFIELD = {np.dtype(v).str[1:]: k for k, v in POINTFIELD_TYPES.items()}


def pointcloud2_dtype(fields: Sequence[Any], point_step: int, big_endian: bool, names: Sequence[str] | None = None) -> np.dtype:
    """numpy structured dtype (itemsize = ``point_step``) for the PointFields *fields*.

    Each field becomes its base type at its byte offset; ``count`` > 1 becomes a sub-array.
    Only the fields in *names* are kept when given. Raises ``ValueError`` for unknown datatypes
    or fields that reach beyond ``point_step``.
    """
    order = ">" if big_endian else "<"
    nm, fm, of = [], [], []
    for f in fields:
        if names is not None and f.name not in names:
            continue
        code = POINTFIELD_TYPES.get(int(f.datatype))
        if code is None:
            raise ValueError(f"PointField {f.name!r} has unknown datatype {f.datatype}")
        count = max(int(f.count), 1)
        base = np.dtype(order + code)
        if int(f.offset) + base.itemsize * count > point_step:
            raise ValueError(f"PointField {f.name!r} (offset {f.offset}, {count}×{base.itemsize} B) exceeds point_step {point_step}")
        if f.name in nm:
            raise ValueError(f"PointField {f.name!r} appears twice")
        nm.append(f.name)
        fm.append(base if count == 1 else (base, (count,)))
        of.append(int(f.offset))
    return np.dtype({"names": nm, "formats": fm, "offsets": of, "itemsize": int(point_step)})


def pointcloud2_structured(msg: Any, names: Sequence[str] | None = None) -> np.ndarray:
    """Zero-copy structured ``(height·width,)`` or ``(height, width)`` view of a PointCloud2's data.

    Rows may be padded (``row_step`` > ``width·point_step``); the view uses strides, so nothing
    is copied. Raises ``ValueError`` when the buffer is too short for the declared layout.
    """
    h, w = int(msg.height), int(msg.width)
    step, row = int(msg.point_step), int(msg.row_step)
    dt = pointcloud2_dtype(msg.fields, step, bool(msg.is_bigendian), names)
    data = np.asarray(msg.data, dtype=np.uint8)
    if h == 0 or w == 0:
        return np.zeros(0, dtype=dt)
    if step <= 0:
        raise ValueError(f"point_step must be > 0, got {step}")
    if row < w * step and h > 1:
        raise ValueError(f"row_step {row} < width {w} × point_step {step}")
    need = (h - 1) * row + w * step
    if data.nbytes < need:
        raise ValueError(f"PointCloud2 data has {data.nbytes} bytes, layout needs {need}")
    strides = (row if h > 1 else w * step, step)
    return np.ndarray(shape=(h, w), dtype=dt, buffer=data, offset=0, strides=strides)


def decode_pointcloud2(msg: Any) -> Array:
    """Vectorised PointCloud2 → ``(N, 3)`` float64 x, y, z (sensor frame, m); non-finite points dropped.

    Layout per ``sensor_msgs/msg/PointCloud2`` + ``PointField`` (ROS 2 common_interfaces): point
    *i* of row *r* starts at byte ``r·row_step + i·point_step``; each field at its ``offset``.

    Works for any field order, padding, per-field datatype (int8 … float64), big or little
    endian, padded rows and organised (height > 1) clouds; no per-point Python loop — the data
    buffer is viewed through a numpy structured dtype and the three columns are copied out.
    ``is_dense`` is not trusted: NaN/inf points are always removed.
    """
    names = {f.name for f in msg.fields}
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise ValueError(f"PointCloud2 has no field(s) {missing}; fields are {sorted(names)}")
    view = pointcloud2_structured(msg, ("x", "y", "z"))
    n = view.size
    out = np.empty((n, 3), dtype=np.float64)
    for j, c in enumerate(("x", "y", "z")):
        col = view[c]
        if col.ndim > view.ndim:  # count > 1: the first element is the coordinate
            col = col[..., 0]
        out[:, j] = col.reshape(-1)
    if n and not np.isfinite(out.reshape(-1)).all():  # flat check first: the common dense case is cheap
        fin = np.isfinite(out)
        out = out[fin[:, 0] & fin[:, 1] & fin[:, 2]]  # cheaper than fin.all(axis=1)
    return out


def cloud_to_frame(msg: Any, path: Path | str, where: str, index: int, **extra: Any) -> Frame:
    """A ``sensor_msgs/PointCloud2`` → 3D :class:`Frame` (points in the sensor frame)."""
    try:
        pts = decode_pointcloud2(msg)
    except ValueError as exc:
        raise LogFormatError(path, where, f"bad PointCloud2: {exc}") from None
    return Frame(stamp=header_stamp(msg), points=pts, index=index, source=f"{Path(path).name}:{where}", **extra)


# ----------------------------------------------------------------------------- pose tracks and TF


class PoseTrack:
    """A short time-ordered buffer of pose samples with geodesic interpolation.

    Samples are stored as ``(x, y, z, qx, qy, qz, qw)`` and turned into 4×4 matrices lazily —
    only those a query needs, in one vectorised call. Memory stays bounded: the reader
    trims samples that no pending scan can need.
    """

    def __init__(self, max_gap: float = 0.5) -> None:
        self.stamps: list[float] = []
        self.vecs: list[Array] = []
        self.mats: list[Array | None] = []
        self.max_gap = max_gap  # how far (s) outside the samples a query may hold the end pose

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def latest(self) -> float:
        return self.stamps[-1] if self.stamps else -math.inf

    def add(self, stamp: float, vec: Array) -> None:
        """Add a sample ``(7,)`` at *stamp* (seconds); out-of-order samples are inserted in place."""
        i = len(self.stamps)
        if self.stamps and stamp < self.stamps[-1]:
            i = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(i, float(stamp))
        self.vecs.insert(i, np.asarray(vec, dtype=float))
        self.mats.insert(i, None)

    def _matrices(self, idx: Iterable[int]) -> dict[int, Array]:
        """4×4 poses of the samples *idx*, converting the ones not converted yet in one call."""
        idx = sorted(set(int(k) for k in idx))
        todo = [k for k in idx if self.mats[k] is None]
        if todo:
            conv = vecs_to_matrices(np.stack([self.vecs[k] for k in todo]))
            for c, k in enumerate(todo):
                self.mats[k] = conv[c]
        return {k: self.mats[k] for k in idx}  # type: ignore[misc]

    def query_many(self, ts: ArrayLike, max_gap: float | None = None) -> list[Array | None]:
        """Poses at the stamps *ts*: interpolated between the bracketing samples, the end sample
        when a stamp is at most ``max_gap`` (default: the track's) outside the buffer, else None."""
        ts = np.atleast_1d(np.asarray(ts, dtype=float))
        gap = self.max_gap if max_gap is None else max_gap
        if not self.stamps:
            return [None] * len(ts)
        S = np.asarray(self.stamps)
        n = len(S)
        i = np.searchsorted(S, ts, side="left")
        ic = np.minimum(i, n - 1)
        exact = S[ic] == ts
        before = (i == 0) & ~exact & (S[0] - ts <= gap)
        after = (i == n) & (ts - S[-1] <= gap)
        inner = (i > 0) & (i < n) & ~exact
        i1 = i[inner]
        i0 = i1 - 1
        M = self._matrices([*ic[exact], *i0, *i1, *([0] if before.any() else []), *([n - 1] if after.any() else [])])
        out: list[Array | None] = [None] * len(ts)
        if inner.any():
            alpha = (ts[inner] - S[i0]) / (S[i1] - S[i0])
            P = interpolate_pose(np.stack([M[k] for k in i0]), np.stack([M[k] for k in i1]), alpha)
            for k, j in enumerate(np.flatnonzero(inner)):
                out[j] = P[k]
        for j in np.flatnonzero(exact):
            out[j] = M[int(ic[j])].copy()
        for j in np.flatnonzero(before):
            out[j] = M[0].copy()
        for j in np.flatnonzero(after):
            out[j] = M[n - 1].copy()
        return out

    def query(self, t: float) -> Array | None:
        """Pose at one stamp (see :meth:`query_many`)."""
        return self.query_many([t])[0]

    def trim(self, t: float) -> None:
        """Drop samples no query at time ≥ *t* can use (keeps the last sample at or before *t*)."""
        i = bisect.bisect_right(self.stamps, t) - 1
        if i > 0:
            del self.stamps[:i]
            del self.vecs[:i]
            del self.mats[:i]

    def keep_last(self, n: int) -> None:
        if len(self.stamps) > n:
            k = len(self.stamps) - n
            del self.stamps[:k]
            del self.vecs[:k]
            del self.mats[:k]


class TfBuffer:
    """Static and dynamic transforms of a tf2 tree (each child has one parent; Foote 2013, "tf: The
    transform library", TePRA — lookups compose the edges through the common ancestor).

    Dynamic edges keep the last ``history`` samples and are interpolated at the query stamp
    (held at the ends); static edges are fixed. Frame ids are compared without a leading ``/``.
    A lookup composes the edges up to the lowest common ancestor of the two frames only, so a
    static sensor mount is not disturbed by the (dynamic) odometry edges above the base.
    """

    def __init__(self, history: int = 1000) -> None:
        self.parent: dict[str, str] = {}
        self.latest_dynamic = -math.inf  # newest stamp of any dynamic transform (s)
        self.static: dict[str, Array] = {}
        self.dynamic: dict[str, PoseTrack] = {}
        self.history = history
        self.version = 0  # bumped whenever the tree or a static edge changes
        self._cache: dict[tuple[str, str], tuple[int, Array | None]] = {}

    def __contains__(self, frame: str) -> bool:
        f = strip_frame(frame)
        return f in self.parent or f in self.parent.values()

    def set_transform(self, parent: str, child: str, vec_or_pose: Array, stamp: float = 0.0, static: bool = False) -> None:
        """Record ``parent_T_child``, given as a 4×4 pose or a ``(7,)`` translation + quaternion."""
        parent, child = strip_frame(parent), strip_frame(child)
        v = np.asarray(vec_or_pose, dtype=float)
        if self.parent.get(child) != parent:
            self.static.pop(child, None)
            self.dynamic.pop(child, None)
            self.parent[child] = parent
            self.version += 1
        if static or child in self.static:  # a static edge re-published on /tf stays static
            self.static[child] = vecs_to_matrices(v) if v.shape == (7,) else v
            self.dynamic.pop(child, None)
            self.version += 1
            return
        if v.shape != (7,):
            t, q = geo.pose_to_quat(v)
            v = np.concatenate([t, q])
        track = self.dynamic.setdefault(child, PoseTrack(max_gap=math.inf))
        track.add(stamp, v)
        self.latest_dynamic = max(self.latest_dynamic, stamp)
        track.keep_last(self.history)

    def add_message(self, msg: Any, static: bool) -> None:
        """Add every ``geometry_msgs/TransformStamped`` of a ``tf2_msgs/TFMessage``."""
        for ts in msg.transforms:
            self.set_transform(ts.header.frame_id, ts.child_frame_id, transform_msg_vec(ts.transform), header_stamp(ts), static)

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        seen = {frame}
        while chain[-1] in self.parent:
            p = self.parent[chain[-1]]
            if p in seen:
                break  # a cycle: stop here
            chain.append(p)
            seen.add(p)
        return chain

    def _up(self, chain: list[str], stamp: float) -> tuple[Array, bool]:
        """``chain[-1]_T_chain[0]`` and whether every edge on the way is static."""
        T = np.eye(4)
        static = True
        for child in reversed(chain[:-1]):
            if child in self.static:
                E = self.static[child]
            else:
                static = False
                E = self.dynamic[child].query(stamp)
                assert E is not None
            T = T @ E
        return T, static

    def lookup(self, target: str, source: str, stamp: float) -> Array | None:
        """``target_T_source`` at *stamp* (maps points from *source* into *target*), or None when
        the two frames are not connected."""
        target, source = strip_frame(target), strip_frame(source)
        if target == source:
            return np.eye(4)
        hit = self._cache.get((target, source))
        if hit is not None and hit[0] == self.version:
            return None if hit[1] is None else hit[1].copy()
        ct, cs = self._chain(target), self._chain(source)
        common = set(ct) & set(cs)
        if not common:
            self._cache[(target, source)] = (self.version, None)
            return None
        lca = next(f for f in ct if f in common)
        lca_T_t, st = self._up(ct[: ct.index(lca) + 1], stamp)
        lca_T_s, ss = self._up(cs[: cs.index(lca) + 1], stamp)
        T = geo.inverse(lca_T_t) @ lca_T_s
        if st and ss:
            self._cache[(target, source)] = (self.version, T.copy())
        return T


# ----------------------------------------------------------------------------- shared reader


@dataclass
class RawMessage:
    """One message of a log, not yet decoded."""

    index: int  # position among the messages of its topic, in time order (0-based)
    topic: str
    msgtype: str
    log_time_ns: int
    data: Any  # the serialised message: bytes, or a read-only memoryview (MCAP indexed path)
    where: str = ""  # e.g. "/scan message 12", for error messages


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


class RosLogReader(LogReader):
    """Streaming frame assembly for ROS logs (MCAP / ROS 1 bag); subclasses provide the messages.

    Memory is constant in the log length: the reader holds the scans still waiting for an
    odometry / ground-truth sample at or after their stamp (at most ``max_pending``), the pose
    samples bracketing them, and the last ``history`` samples of each dynamic TF edge.

    Args:
        path: the log file.
        topic: the sensor topic; default: the LaserScan topic with most messages, else the
            PointCloud2 topic with most messages.
        odom_topic: a ``nav_msgs/Odometry`` topic; default ``/odom`` or the Odometry topic with
            most messages (ground-truth-named topics excluded) and, when the log has none, the
            TF edge ``odom → base`` (REP-105). ``""`` disables odometry.
        ground_truth_topic: an Odometry or PoseStamped topic; default a topic named
            ``ground_truth`` / ``groundtruth`` / ``gt`` / ``base_pose_ground_truth``.
        max_gap: odometry/ground truth is held (not extrapolated) up to this many seconds
            beyond its first/last sample; farther out the frame gets None.
    """

    max_pending = 256
    trim_margin = 1.0  # s of pose samples kept before the oldest waiting scan

    def __init__(
        self,
        path: str | Path,
        topic: str | None = None,
        *,
        odom_topic: str | None = None,
        ground_truth_topic: str | None = None,
        max_gap: float = 0.5,
    ) -> None:
        super().__init__(path, topic)
        self.odom_topic = odom_topic
        self.ground_truth_topic = ground_truth_topic
        self.max_gap = max_gap

    # -- provided by the format -------------------------------------------------------------

    @abc.abstractmethod
    def topics(self) -> list[TopicInfo]:
        """Every topic of the log with its (normalised) message type and message count."""

    @abc.abstractmethod
    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        """Messages of *topics* (all when None) in time order, undecoded; raises LogFormatError
        on a corrupt or truncated container, or, with *on_skip*, reports it and goes on after it
        where the container allows (else ends the messages)."""

    @abc.abstractmethod
    def _decode(self, raw: RawMessage) -> Any:
        """Deserialise one message (raises LogFormatError naming the message)."""

    def _session(self) -> contextlib.AbstractContextManager:
        """Resources kept open across the several passes of one frames()/info() call."""
        return contextlib.nullcontext()

    def _load_meta(self, tolerant: bool = False) -> None:
        """Read topics and message definitions (*tolerant*: as far as a damaged file allows)."""

    # -- topic roles ------------------------------------------------------------------------

    def choose_topics(self) -> TopicChoice:
        """Assign the sensor, odometry, ground-truth and TF roles (raises TopicNotFoundError)."""
        topics = self.topics()
        listing = ", ".join(f"{t.name} [{t.msgtype}]" for t in topics) or "none"
        by_name = {t.name: t for t in topics}
        if self.topic is not None:
            sensor = by_name.get(self.topic)
            if sensor is None:
                raise TopicNotFoundError(self.path, None, f"topic {self.topic!r} not in the log; topics: {listing}")
            if sensor.msgtype not in SENSOR_TYPES:
                raise LogFormatError(
                    self.path, f"topic {self.topic}", f"unsupported message type {sensor.msgtype} (expected {LASER_SCAN} or {POINTCLOUD2})"
                )
        else:
            sensor = _pick_most(topics, LASER_SCAN) or _pick_most(topics, POINTCLOUD2)
            if sensor is None:
                raise TopicNotFoundError(self.path, None, f"no LaserScan or PointCloud2 topic with messages; topics: {listing}")
        choice = TopicChoice(sensor=sensor)
        if self.odom_topic is None:
            non_gt = [t for t in topics if not _is_ground_truth_name(t.name)]
            choice.odom = _pick_most(non_gt, ODOMETRY, prefer=("/odom", "odom"))
        elif self.odom_topic:
            choice.odom = self._require(by_name, self.odom_topic, (ODOMETRY,), listing)
        if self.ground_truth_topic is None:
            gts = [t for t in topics if _is_ground_truth_name(t.name) and t.msgtype in (ODOMETRY, POSE_STAMPED) and t.count > 0]
            choice.ground_truth = max(gts, key=lambda t: t.count) if gts else None
        elif self.ground_truth_topic:
            choice.ground_truth = self._require(by_name, self.ground_truth_topic, (ODOMETRY, POSE_STAMPED), listing)
        for t in topics:
            if t.msgtype in TF_TYPES:
                (choice.tf_static if t.name.rstrip("/").endswith("tf_static") else choice.tf).append(t.name)
        return choice

    def _require(self, by_name: dict[str, TopicInfo], name: str, types: tuple[str, ...], listing: str) -> TopicInfo:
        t = by_name.get(name)
        if t is None:
            raise TopicNotFoundError(self.path, None, f"topic {name!r} not in the log; topics: {listing}")
        if t.msgtype not in types:
            raise LogFormatError(self.path, f"topic {name}", f"type {t.msgtype}, expected one of {', '.join(types)}")
        return t

    # -- frames -----------------------------------------------------------------------------

    @contextlib.contextmanager
    def _fields(self, raw: RawMessage) -> Iterator[None]:
        """Read fields of *raw*'s decoded message inside the block: one its type lacks — the log carries its
        own message definitions, and a damaged or unusual one decodes into other fields — is a
        LogFormatError naming the message, as a bad value is."""
        try:
            yield
        except (AttributeError, TypeError) as exc:
            raise LogFormatError(self.path, raw.where, f"{raw.msgtype} on {raw.topic} lacks a standard field of "
                                                       f"its type (its definition in the log differs): {exc}") from None

    def _to_frame(self, raw: RawMessage, msg: Any, scan_index: int, **extra: Any) -> Frame:
        with self._fields(raw):
            if raw.msgtype == LASER_SCAN:
                return scan_to_frame(msg, self.path, raw.where, scan_index, **extra)
            return cloud_to_frame(msg, self.path, raw.where, scan_index, **extra)

    def _scan_head(self, raw: RawMessage, msg: Any) -> tuple[float, str]:
        """The stamp (s) and sensor frame of a sensor message, a LaserScan checked first."""
        with self._fields(raw):
            if raw.msgtype == LASER_SCAN:
                check_scan(msg, self.path, raw.where)  # fail at the bad message, not a batch later
            return header_stamp(msg), strip_frame(msg.header.frame_id)

    def _pose_sample(self, raw: RawMessage, msg: Any) -> tuple[float, Array]:
        with self._fields(raw):
            try:
                vec = pose_msg_vec(msg.pose.pose if raw.msgtype == ODOMETRY else msg.pose)
            except ValueError as exc:
                raise LogFormatError(self.path, raw.where, f"{raw.topic}: {exc}") from None
            return header_stamp(msg), vec

    def _add_tf(self, tf: TfBuffer, raw: RawMessage, static: bool) -> None:
        msg = self._decode(raw)
        with self._fields(raw):
            try:
                tf.add_message(msg, static=static)
            except ValueError as exc:
                raise LogFormatError(self.path, raw.where, f"{raw.topic}: {exc}") from None

    def _first(self, topic: str, skip: SkipHandler | None = None, read: Any = None) -> Any | None:
        """``read(message)`` of the first message of *topic* (the message itself without *read*; None when
        the topic is empty); with *skip*, of the first one that decodes and reads (the bad ones go to *skip*)."""
        it = self._raw_messages({topic}, skip)
        try:
            for raw in it:
                try:
                    msg = self._decode(raw)
                    with self._fields(raw):
                        return msg if read is None else read(msg)
                except LogFormatError as exc:
                    if skip is None:
                        raise
                    skip(exc)
            return None
        finally:
            it.close()  # type: ignore[attr-defined]

    def _tf_odometry_child(self, tf_topics: Sequence[str], probe: int = 200, skip: SkipHandler | None = None) -> str | None:
        """The child of a dynamic ``odom → base`` transform among the first *probe* /tf messages
        (REP-105: the odometry frame is ``odom``), or None. With *skip*, undecodable messages go to it."""
        for name in tf_topics:
            it = self._raw_messages({name}, skip)
            try:
                for k, raw in enumerate(it):
                    if k >= probe:
                        break
                    try:
                        msg = self._decode(raw)
                        with self._fields(raw):
                            child = next((strip_frame(ts.child_frame_id) for ts in msg.transforms
                                          if strip_frame(ts.header.frame_id) == "odom"), None)
                    except LogFormatError as exc:
                        if skip is None:
                            raise
                        skip(exc)
                        continue
                    if child is not None:
                        return child
            finally:
                it.close()  # type: ignore[attr-defined]
        return None

    def _base_candidates(self, odom_child: str | None) -> list[str]:
        return ([odom_child] if odom_child else []) + [b for b in BASE_FRAMES if b != odom_child]

    def _tf_odometry(self, tf: TfBuffer, child: str, stamps: Sequence[float]) -> list[Array | None]:
        """``odom_T_child`` at *stamps* from TF, interpolated; None farther than ``max_gap`` outside
        the samples of a direct odom → child edge, or when TF does not connect the two frames."""
        track = tf.dynamic.get(child) if tf.parent.get(child) == "odom" else None
        if track is not None:
            return track.query_many(stamps, max_gap=self.max_gap)
        return [tf.lookup("odom", child, t) for t in stamps]

    def _base_T_sensor(self, tf: TfBuffer, odom_child: str | None, sensor: str, stamp: float) -> Array:
        """``base_T_sensor`` from TF: base = the odometry child frame, else base_link / base_footprint;
        identity when TF does not connect any of them to the sensor frame."""
        for base in self._base_candidates(odom_child):
            if base == sensor or (base in tf and sensor in tf):
                T = tf.lookup(base, sensor, stamp)
                if T is not None:
                    return T
        return np.eye(4)

    def has_ground_truth(self) -> bool:
        """Whether a ground-truth topic (named or given) is in the log."""
        return self.choose_topics().ground_truth is not None

    def frames(self, on_skip: SkipHandler | None = None) -> Iterator[Frame]:
        """Every scan of the sensor topic as a Frame (in log order), with ``odom`` /
        ``ground_truth`` interpolated to the scan stamp and ``base_T_sensor`` from TF.

        With *on_skip*, a message that does not decode (or a scan that is malformed) is reported
        and left out; a corrupt container stretch is reported and skipped where the format
        allows (see the readers). The preparatory passes (static TF, first messages) skip bad
        messages silently: the main pass, which reads them again, reports each once.
        """
        quiet: SkipHandler | None = None if on_skip is None else (lambda exc: None)

        def guarded(fn: Any, raw: RawMessage, *args: Any, **kwargs: Any) -> Any:
            """``fn(raw, *args, **kwargs)``; with *on_skip*, a LogFormatError is reported (costing that one
            message) and None returned."""
            try:
                return fn(raw, *args, **kwargs)
            except LogFormatError as exc:
                if on_skip is None:
                    raise
                on_skip(lost(exc, {raw.topic: 1}))
                return None

        with self._session():
            self._load_meta(tolerant=on_skip is not None)
            choice = self.choose_topics()
            if on_skip is not None:
                on_skip = counting(on_skip, choice.sensor.name)
            laser = choice.sensor.msgtype == LASER_SCAN
            batch_size = 64 if laser else 1
            max_pending = self.max_pending if laser else 16
            tf = TfBuffer()
            for name in choice.tf_static:
                for raw in self._raw_messages({name}, quiet):
                    try:
                        self._add_tf(tf, raw, static=True)
                    except LogFormatError:
                        if quiet is None:
                            raise
            odom = PoseTrack(self.max_gap) if choice.odom else None
            gt = PoseTrack(self.max_gap) if choice.ground_truth else None
            odom_child: str | None = None
            if choice.odom is not None:
                odom_child = self._first(choice.odom.name, quiet, lambda m: strip_frame(m.child_frame_id))
            # Dynamic /tf is only needed when the static tree does not already mount the sensor on the base.
            need_tf = bool(choice.tf)
            sensor0 = self._first(choice.sensor.name, quiet, lambda m: strip_frame(m.header.frame_id))
            if need_tf and sensor0 is not None:
                need_tf = not any(
                    b == sensor0 or (b in tf and sensor0 in tf and tf.lookup(b, sensor0, 0.0) is not None)
                    for b in self._base_candidates(odom_child)
                )
            # No Odometry topic: take odometry from the TF edge odom → base when the log has one.
            tf_odom: str | None = None
            if choice.odom is None and self.odom_topic is None and choice.tf:
                tf_odom = self._tf_odometry_child(choice.tf, skip=quiet)
                if tf_odom is not None:
                    odom_child, need_tf = tf_odom, True
            wanted = {choice.sensor.name, *choice.tf_static}
            if need_tf:
                wanted.update(choice.tf)
            for c in (choice.odom, choice.ground_truth):
                if c is not None:
                    wanted.add(c.name)

            pending: deque[tuple[RawMessage, Any, int, float, str]] = deque()
            batch: list[tuple[RawMessage, Any, int, float, str]] = []

            def flush() -> Iterator[Frame]:
                stamps = [b[3] for b in batch]
                od = odom.query_many(stamps) if odom is not None else [None] * len(batch)
                gp = gt.query_many(stamps) if gt is not None else [None] * len(batch)
                if tf_odom is not None:
                    od = self._tf_odometry(tf, tf_odom, stamps)
                for (raw, msg, k, t, sframe), o, g in zip(batch, od, gp):
                    extra: dict[str, Any] = {"base_T_sensor": self._base_T_sensor(tf, odom_child, sframe, t)}
                    if odom is not None or tf_odom is not None:
                        extra["odom"] = o
                    if gt is not None:
                        extra["ground_truth"] = g
                    frame = guarded(self._to_frame, raw, msg, k, **extra)
                    if frame is not None:
                        yield frame
                batch.clear()

            def ready(t: float) -> bool:
                return (
                    (odom is None or odom.latest >= t)
                    and (gt is None or gt.latest >= t)
                    and (tf_odom is None or tf.latest_dynamic >= t)
                )

            scan_index = 0

            def take(raw: RawMessage) -> None:
                """Decode one message and file it (a scan into *pending*, a pose into its track)."""
                nonlocal scan_index
                topic = raw.topic
                if topic == choice.sensor.name:
                    msg = self._decode(raw)
                    pending.append((raw, msg, scan_index, *self._scan_head(raw, msg)))
                    scan_index += 1
                elif choice.odom is not None and topic == choice.odom.name:
                    assert odom is not None
                    odom.add(*self._pose_sample(raw, self._decode(raw)))
                elif choice.ground_truth is not None and topic == choice.ground_truth.name:
                    assert gt is not None
                    gt.add(*self._pose_sample(raw, self._decode(raw)))
                elif topic in choice.tf_static:
                    self._add_tf(tf, raw, static=True)
                elif topic in choice.tf:
                    self._add_tf(tf, raw, static=False)

            for raw in self._raw_messages(wanted, on_skip):
                guarded(take, raw)
                while pending and (ready(pending[0][3]) or len(pending) > max_pending):
                    batch.append(pending.popleft())
                if len(batch) >= batch_size:
                    yield from flush()
                # Keep trim_margin seconds of pose history before the oldest waiting scan (or the
                # newest sample): scans may be logged after odometry with later stamps.
                oldest = batch[0][3] if batch else (pending[0][3] if pending else math.inf)
                for track in (odom, gt):
                    if track is not None and track.stamps:
                        track.trim(min(oldest, track.latest) - self.trim_margin)
            batch.extend(pending)
            pending.clear()
            if batch:
                yield from flush()

    # -- info -------------------------------------------------------------------------------

    def info(self) -> LogInfo:
        """Summary of the log, read whole: topic counts from the index (summary / connections); every
        message read from the container, and those of the topics a run uses (sensor, odometry, ground
        truth, TF) decoded and checked as a run checks them, so a log it summarises without an error is
        one a run reads; scans, beams and start/end from the sensor topic."""
        choice = self.choose_topics()
        poses = {c.name for c in (choice.odom, choice.ground_truth) if c is not None}
        scratch = TfBuffer()
        scans = 0
        beams: list[int] = []
        start = end = None
        for raw in self._raw_messages(None):
            if raw.topic != choice.sensor.name:
                if raw.topic in poses:
                    self._pose_sample(raw, self._decode(raw))
                elif raw.topic in choice.tf or raw.topic in choice.tf_static:
                    self._add_tf(scratch, raw, static=raw.topic in choice.tf_static)
                continue
            msg = self._decode(raw)
            t, _ = self._scan_head(raw, msg)
            with self._fields(raw):
                if raw.msgtype == LASER_SCAN:
                    beams.append(len(msg.ranges))
                else:
                    try:
                        view = pointcloud2_structured(msg, ("x", "y", "z"))
                    except ValueError as exc:
                        raise LogFormatError(self.path, raw.where, f"bad PointCloud2: {exc}") from None
                    beams.append(int(view.size))
            start = t if start is None else min(start, t)
            end = t if end is None else max(end, t)
            scans += 1
        dim = 2 if choice.sensor.msgtype == LASER_SCAN else 3
        bps = None
        if beams:
            bps = int(max(beams)) if dim == 2 else int(np.median(beams))
        return LogInfo(
            path=str(self.path),
            format=self.format,
            sensor_topic=choice.sensor.name,
            scans=scans,
            beams_per_scan=bps,
            dimension=dim,
            start=start,
            end=end,
            has_odometry=choice.odom is not None
            or (self.odom_topic is None and bool(choice.tf) and self._tf_odometry_child(choice.tf) is not None),
            has_ground_truth=choice.ground_truth is not None,
            topics=self.topics(),
        )
