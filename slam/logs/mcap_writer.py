"""MCAP writer for ROS 2 (CDR) messages: scans, clouds, odometry, TF, paths, occupancy grids.

Files open in Foxglove and decode with ``rosbags`` without a ROS installation: every channel
has ``message_encoding="cdr"`` and a schema with ``encoding="ros2msg"`` whose data is the full
ROS 2 message definition with every dependent type appended (separated by a line of 80 ``=``
and ``MSG: pkg/msg/Type``), as ``ros2 bag record`` writes it. The mcap ``Writer`` adds chunk
indexes, statistics and the summary section, so readers can seek and count without a scan.

Stamps are float seconds, rounded to the nearest nanosecond as ``builtin_interfaces/Time``
(sec, nanosec) without going through a lossy ``stamp * 1e9``; the MCAP ``log_time`` and
``publish_time`` are the same stamp in integer nanoseconds. Reading back gives the written float
exactly for every stamp ≥ 10⁷ s (epoch times) and for every stamp that is the float nearest to a
whole number of nanoseconds (e.g. ``k / 10``, not ``k * 0.1``). Poses are 4×4
matrices ``parent_T_child`` (metres); quaternions are written ``(x, y, z, w)``.

The file is written to a temporary sibling and renamed on a clean exit of the ``with`` block
(:mod:`core.atomic`), so a failed run never leaves a half-written log.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import pose_formats
from core.atomic import atomic_path
from core.errors import GeometryError

from .pointcloud2 import NUMPY_TO_POINTFIELD

from .ros_msgs import (LASER_SCAN, ODOMETRY, POINTCLOUD2, POSE_STAMPED, TF_MESSAGE, humble_typestore, message_definition,
                       stamp_to_ns, stamp_to_time)

if TYPE_CHECKING:
    from core.frame import Frame

Array = NDArray[np.float64]

__all__ = ["McapLogWriter", "write_cloud_log"]

PATH = "nav_msgs/msg/Path"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"

# ROS 2 QoS the tf2 listeners expect on /tf_static (transient local, so late joiners get it).
_QOS_STATIC = (
    "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 1\n  deadline:\n    sec: 2147483647\n"
    "    nsec: 4294967295\n  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n"
    "  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n  avoid_ros_namespace_conventions: false\n"
)
_QOS_DEFAULT = _QOS_STATIC.replace("durability: 1", "durability: 2")


class McapLogWriter:
    """Context manager writing a ROS 2 MCAP log.

    Args:
        path: output ``.mcap`` file (created atomically on a clean exit).
        profile: MCAP header profile, ``"ros2"``.
        compression: chunk compression, ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        chunk_size: target uncompressed chunk size in bytes.
    """

    def __init__(self, path: str | os.PathLike[str], *, profile: str = "ros2", compression: str = "zstd", chunk_size: int = 1 << 20) -> None:
        if profile != "ros2":
            raise ValueError(f"only the 'ros2' profile (CDR messages) is supported, got {profile!r}")
        self.path = Path(path)
        self.profile = profile
        self.compression = compression
        self.chunk_size = chunk_size
        self.typestore = humble_typestore()
        self._stack: contextlib.ExitStack | None = None
        self._writer: Any = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._T = self.typestore.types

    # -- lifecycle --------------------------------------------------------------------------

    def __enter__(self) -> "McapLogWriter":
        from mcap.writer import CompressionType, Writer

        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}.get(self.compression)
        if comp is None:
            raise ValueError(f"compression must be zstd, lz4 or none, got {self.compression!r}")
        stack = contextlib.ExitStack()
        try:
            tmp = stack.enter_context(atomic_path(self.path))
            fh = stack.enter_context(open(tmp, "wb"))
            self._writer = Writer(fh, chunk_size=self.chunk_size, compression=comp)
            self._writer.start(profile=self.profile, library="gpslam")
        except BaseException:
            stack.close()
            raise
        self._stack = stack
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        stack, self._stack = self._stack, None
        assert stack is not None
        if exc_type is None:
            try:
                self._writer.finish()
            except BaseException as err:
                stack.__exit__(type(err), err, err.__traceback__)
                raise
        return bool(stack.__exit__(exc_type, exc, tb))

    # -- generic ----------------------------------------------------------------------------

    def _channel(self, topic: str, msgtype: str) -> int:
        key = (topic, msgtype)
        cid = self._channels.get(key)
        if cid is None:
            if self._writer is None:
                raise RuntimeError("McapLogWriter must be used as a context manager (with McapLogWriter(path) as w: ...)")
            if any(t == topic for t, _ in self._channels):
                raise ValueError(f"topic {topic!r} already carries another message type")
            sid = self._schemas.get(msgtype)
            if sid is None:
                sid = self._writer.register_schema(name=msgtype, encoding="ros2msg", data=message_definition(msgtype).encode())
                self._schemas[msgtype] = sid
            qos = _QOS_STATIC if topic.rstrip("/").endswith("tf_static") else _QOS_DEFAULT
            cid = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=sid, metadata={"offered_qos_profiles": qos})
            self._channels[key] = cid
        return cid

    def write_message(self, topic: str, msgtype: str, msg: Any, stamp: float) -> None:
        """Write any message of the Humble typestore (``self.typestore.types[msgtype](...)``) at *stamp* (s)."""
        cid = self._channel(topic, msgtype)
        data = self.typestore.serialize_cdr(msg, msgtype)
        ns = stamp_to_ns(float(stamp))
        self._writer.add_message(channel_id=cid, log_time=ns, publish_time=ns, data=bytes(data))

    # -- builders ---------------------------------------------------------------------------

    def _time(self, stamp: float) -> Any:
        sec, nsec = stamp_to_time(float(stamp))
        return self._T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)

    def _header(self, stamp: float, frame_id: str) -> Any:
        return self._T["std_msgs/msg/Header"](stamp=self._time(stamp), frame_id=str(frame_id))

    def _pose(self, pose: ArrayLike) -> Any:
        T = np.asarray(pose, dtype=float)
        if T.shape != (4, 4):
            raise GeometryError(f"pose must be 4×4, got shape {T.shape}")
        return self._pose_msg(*pose_formats.pose_to_quat(T))

    def _pose_msg(self, t: Array, q: Array) -> Any:
        """``geometry_msgs/Pose`` from a translation (3,) and a quaternion (4,) x, y, z, w."""
        P = self._T
        return P["geometry_msgs/msg/Pose"](
            position=P["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=P["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )

    def _transform(self, t: Array, q: Array) -> Any:
        """``geometry_msgs/Transform`` from a translation (3,) and a quaternion (4,) x, y, z, w."""
        p = self._pose_msg(t, q)
        P = self._T
        return P["geometry_msgs/msg/Transform"](
            translation=P["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z), rotation=p.orientation
        )

    # -- typed writers ----------------------------------------------------------------------

    def write_scan(
        self,
        topic: str,
        stamp: float,
        frame_id: str,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
        ranges: ArrayLike,
        intensities: ArrayLike | None = None,
        time_increment: float = 0.0,
        scan_time: float = 0.0,
    ) -> None:
        """``sensor_msgs/LaserScan``: ranges (m) stored float32, ``inf`` = no return (REP-117);
        ``angle_max = angle_min + (n − 1)·angle_increment`` (rad); *time_increment* (s between beams, the
        first at the stamp) and *scan_time* (s between scans), 0 where unknown."""
        r = np.ascontiguousarray(ranges, dtype=np.float32).reshape(-1)
        inten = np.zeros(0, np.float32) if intensities is None else np.ascontiguousarray(intensities, dtype=np.float32).reshape(-1)
        if inten.size and inten.shape != r.shape:
            raise ValueError(f"intensities have {inten.size} values for {r.size} ranges")
        msg = self._T[LASER_SCAN](
            header=self._header(stamp, frame_id),
            angle_min=float(angle_min),
            angle_max=float(angle_min) + (r.size - 1) * float(angle_increment),
            angle_increment=float(angle_increment),
            time_increment=float(time_increment),
            scan_time=float(scan_time),
            range_min=float(range_min),
            range_max=float(range_max),
            ranges=r,
            intensities=inten,
        )
        self.write_message(topic, LASER_SCAN, msg, stamp)

    def write_pointcloud(
        self, topic: str, stamp: float, frame_id: str, points: ArrayLike, fields: Mapping[str, ArrayLike] | None = None
    ) -> None:
        """``sensor_msgs/PointCloud2`` (unorganised, little endian): x, y, z as float32 (m) plus
        each extra ``fields[name]`` ``(N,)`` array in its own numpy type (int8 … float64;
        other types are stored as float64)."""
        P = np.asarray(points)
        if P.ndim != 2 or P.shape[1] != 3:
            raise GeometryError(f"points must be (N, 3), got shape {P.shape}")
        n = P.shape[0]
        names, formats = ["x", "y", "z"], ["<f4", "<f4", "<f4"]
        cols: dict[str, np.ndarray] = {}
        for name, arr in (fields or {}).items():
            a = np.asarray(arr).reshape(-1)
            if a.shape[0] != n:
                raise ValueError(f"field {name!r} has {a.shape[0]} values for {n} points")
            if name in names:
                raise ValueError(f"field name {name!r} is reserved or repeated")
            code = a.dtype.str[1:]
            if code not in NUMPY_TO_POINTFIELD:
                a, code = a.astype(np.float64), "f8"
            names.append(name)
            formats.append("<" + code if a.dtype.itemsize > 1 else "|" + code)
            cols[name] = a
        dt = np.dtype({"names": names, "formats": formats})  # packed, offsets in order
        rec = np.empty(n, dtype=dt)
        rec["x"], rec["y"], rec["z"] = P[:, 0], P[:, 1], P[:, 2]
        for name, a in cols.items():
            rec[name] = a
        PF = self._T["sensor_msgs/msg/PointField"]
        pfields = [
            PF(name=nm, offset=int(dt.fields[nm][1]), datatype=NUMPY_TO_POINTFIELD[dt.fields[nm][0].str[1:]], count=1) for nm in names
        ]
        dense = bool(np.isfinite(P).all())
        msg = self._T[POINTCLOUD2](
            header=self._header(stamp, frame_id),
            height=1,
            width=n,
            fields=pfields,
            is_bigendian=False,
            point_step=dt.itemsize,
            row_step=dt.itemsize * n,
            data=rec.view(np.uint8).reshape(-1),
            is_dense=dense,
        )
        self.write_message(topic, POINTCLOUD2, msg, stamp)

    def write_odometry(
        self,
        topic: str,
        stamp: float,
        frame_id: str,
        child_frame_id: str,
        pose: ArrayLike,
        covariance: ArrayLike | None = None,
        twist: ArrayLike | None = None,
    ) -> None:
        """``nav_msgs/Odometry``: *pose* = ``frame_id_T_child_frame_id`` (4×4); *covariance* 6×6 in
        ROS order (x, y, z, rx, ry, rz), zeros when None; *twist* optional ``(6,)`` = linear (m/s)
        then angular (rad/s) velocity in the child frame."""
        cov = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=np.float64).reshape(-1)
        if cov.size != 36:
            raise ValueError(f"covariance must be 6×6, got {cov.size} values")
        tw = np.zeros(6) if twist is None else np.asarray(twist, dtype=np.float64).reshape(-1)
        if tw.size != 6:
            raise ValueError(f"twist must have 6 values, got {tw.size}")
        P = self._T
        V3 = P["geometry_msgs/msg/Vector3"]
        msg = P[ODOMETRY](
            header=self._header(stamp, frame_id),
            child_frame_id=str(child_frame_id),
            pose=P["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(pose), covariance=cov.copy()),
            twist=P["geometry_msgs/msg/TwistWithCovariance"](
                twist=P["geometry_msgs/msg/Twist"](linear=V3(x=tw[0], y=tw[1], z=tw[2]), angular=V3(x=tw[3], y=tw[4], z=tw[5])),
                covariance=np.zeros(36),
            ),
        )
        self.write_message(topic, ODOMETRY, msg, stamp)

    def write_pose(self, topic: str, stamp: float, frame_id: str, pose: ArrayLike) -> None:
        """``geometry_msgs/PoseStamped``: *pose* = ``frame_id_T_body`` (4×4)."""
        msg = self._T[POSE_STAMPED](header=self._header(stamp, frame_id), pose=self._pose(pose))
        self.write_message(topic, POSE_STAMPED, msg, stamp)

    def write_tf(self, stamp: float, transforms: Sequence[tuple[str, str, ArrayLike]], static: bool = False) -> None:
        """``tf2_msgs/TFMessage`` on ``/tf`` (or ``/tf_static``): each ``(parent, child, parent_T_child)``."""
        TS = self._T["geometry_msgs/msg/TransformStamped"]
        Ts = [np.asarray(T, dtype=float) for _, _, T in transforms]
        for T in Ts:
            if T.shape != (4, 4):
                raise GeometryError(f"pose must be 4×4, got shape {T.shape}")
        ts, qs = pose_formats.pose_to_quat(np.stack(Ts)) if Ts else ((), ())  # one vectorised conversion for the message
        items = [TS(header=self._header(stamp, parent), child_frame_id=str(child), transform=self._transform(t, q))
                 for (parent, child, _), t, q in zip(transforms, ts, qs)]
        msg = self._T[TF_MESSAGE](transforms=items)
        self.write_message("/tf_static" if static else "/tf", TF_MESSAGE, msg, stamp)

    def write_path(self, topic: str, stamp: float, frame_id: str, stamps: ArrayLike, poses: ArrayLike) -> None:
        """``nav_msgs/Path``: poses ``(N, 4, 4)`` = ``frame_id_T_base`` at *stamps* ``(N,)`` (s)."""
        st = np.asarray(stamps, dtype=float).reshape(-1)
        Ps = np.asarray(poses, dtype=float)
        if Ps.ndim != 3 or Ps.shape[1:] != (4, 4) or Ps.shape[0] != st.shape[0]:
            raise GeometryError(f"path needs (N, 4, 4) poses for N stamps, got {Ps.shape} and {st.shape}")
        PS = self._T[POSE_STAMPED]
        ts, qs = pose_formats.pose_to_quat(Ps)  # one vectorised conversion, not one per pose
        items = [PS(header=self._header(s, frame_id), pose=self._pose_msg(t, q)) for s, t, q in zip(st, ts, qs)]
        msg = self._T[PATH](header=self._header(stamp, frame_id), poses=items)
        self.write_message(topic, PATH, msg, stamp)

    def write_occupancy_grid(self, topic: str, stamp: float, frame_id: str, resolution: float, origin: ArrayLike, data: ArrayLike) -> None:
        """``nav_msgs/OccupancyGrid``: *data* int8 ``(H, W)`` (−1 unknown, 0 free … 100 occupied),
        row 0 = lowest y; *origin* = ``frame_id_T_cell(0,0) corner`` (4×4); *resolution* m/cell."""
        D = np.asarray(data)
        if D.ndim != 2:
            raise ValueError(f"occupancy data must be (H, W), got shape {D.shape}")
        if D.dtype != np.int8:
            if np.any((D < -1) | (D > 100)):
                raise ValueError("occupancy values must lie in [-1, 100]")
            D = D.astype(np.int8)
        h, w = D.shape
        P = self._T
        info = P["nav_msgs/msg/MapMetaData"](
            map_load_time=self._time(stamp), resolution=float(resolution), width=int(w), height=int(h), origin=self._pose(origin)
        )
        msg = P[OCCUPANCY_GRID](header=self._header(stamp, frame_id), info=info, data=np.ascontiguousarray(D).reshape(-1))
        self.write_message(topic, OCCUPANCY_GRID, msg, stamp)


def write_cloud_log(path: str | os.PathLike[str], frames: Iterable["Frame"], *, topic: str = "/points",
                    sensor_frame: str = "velodyne") -> int:
    """Write 3D frames (those of a KITTI sequence, say) as a ROS 2 MCAP log that ``slam run`` reads back
    as the same frames; returns the number of clouds written.

    Topics, as :func:`evaluation.sim.write_simulated_log` lays out a log: *topic*
    (``sensor_msgs/PointCloud2`` in frame *sensor_frame*, x, y, z float32, stamped ``frame.stamp``),
    ``/tf_static`` (``base_link → sensor_frame``: the frames' ``base_T_sensor``), ``/odom``
    (``nav_msgs/Odometry odom → base_link``) when the frames carry odometry and ``/ground_truth``
    (``map → base_link``) when they carry ground truth. The points are exact when they are float32
    values already (KITTI's ``.bin`` scans are), else rounded to float32; stamps round to the nanosecond
    (the module docstring says when they read back exactly).

    Raises:
        GeometryError: a planar (2D) frame, or a ``base_T_sensor`` that changes between frames (one static
            transform cannot carry it).
    """
    n = 0
    mount: Array | None = None
    with McapLogWriter(path) as w:
        for f in frames:
            if f.is_planar:
                raise GeometryError(f"frame {f.index} is a planar scan; write_cloud_log writes 3D clouds")
            if mount is None:
                mount = np.asarray(f.base_T_sensor, dtype=float)
                w.write_tf(f.stamp, [("base_link", sensor_frame, mount)], static=True)
            elif not np.array_equal(f.base_T_sensor, mount):
                raise GeometryError(f"frame {f.index}: base_T_sensor differs from the first frame's; "
                                    "a static transform cannot carry a moving sensor mount")
            if f.odom is not None:
                w.write_odometry("/odom", f.stamp, "odom", "base_link", f.odom)
            if f.ground_truth is not None:
                w.write_odometry("/ground_truth", f.stamp, "map", "base_link", f.ground_truth)
            w.write_pointcloud(topic, f.stamp, sensor_frame, f.points)
            n += 1
    return n
