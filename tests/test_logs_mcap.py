"""MCAP (ROS 2) writer and reader: round trips, independent decoding, TF, interpolation, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core import geometry as geo
from core import pose_formats
from core.errors import LogFormatError, TopicNotFoundError
from slam.logs import open_log
from slam.logs.mcap_reader import McapReader
from slam.logs.mcap_writer import McapLogWriter, write_cloud_log
from slam.logs.ros_msgs import LASER_SCAN, humble_typestore, stamp_to_ns, stamp_to_time
from slam.logs.tf_buffer import PoseTrack, TfBuffer

T = humble_typestore().types


def random_pose(rng, planar=False):
    if planar:
        return geo.xytheta_to_matrix(*rng.uniform(-20, 20, 2), rng.uniform(-np.pi, np.pi))
    return geo.se3_exp(np.concatenate([rng.uniform(-20, 20, 3), rng.uniform(-2, 2, 3)]))


def write_basic_log(path, n=30, *, odom=True, tf=True, nan_at=None, neg_at=None, empty_at=None, stamp0=1.7e9, chunk_size=1 << 20, compression="zstd"):
    """LaserScan /scan (10 Hz) + /odom + static TF base_link → laser."""
    rng = np.random.default_rng(3)
    with McapLogWriter(path, chunk_size=chunk_size, compression=compression) as w:
        if tf:
            w.write_tf(stamp0, [("base_link", "laser", geo.xytheta_to_matrix(0.3, -0.1, 0.2))], static=True)
        for i in range(n):
            t = stamp0 + 0.1 * i
            r = rng.uniform(0.5, 9.0, 181).astype(np.float32)
            r[::7] = np.inf
            if i == nan_at:
                r[5] = np.nan
            if i == neg_at:
                r[9] = -1.0
            if i == empty_at:
                r = r[:0]
            w.write_scan("/scan", t, "laser", -np.pi / 2, np.pi / 180, 0.1, 8.0, r)
            if odom:
                w.write_odometry("/odom", t, "odom", "base_link", geo.xytheta_to_matrix(0.1 * i, 0.02 * i, 0.01 * i))
    return path


# ----------------------------------------------------------------------------- round trip


def test_round_trip_every_type_decoded_independently(tmp_path, rng):
    """Every writer method's message is read back by rosbags (AnyReader, no gpslam code) with
    equal content: arrays bit-exact (float32 ranges incl. inf, covariances, grid cells), stamps
    exact (sec, nanosec), translations and quaternions exactly those of the written pose; the
    schemas are ros2msg with dependent types, the channels cdr, and the summary indexes chunks."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    p = tmp_path / "all.mcap"
    st = 1731234567.123456789
    ranges = rng.uniform(0.1, 30, 360).astype(np.float32)
    ranges[::5] = np.inf
    inten = rng.uniform(0, 1000, 360).astype(np.float32)
    pts = rng.normal(size=(777, 3)) * 10
    pose = random_pose(rng)
    cov = rng.normal(size=(6, 6))
    cov = cov @ cov.T
    twist = rng.normal(size=6)
    tfs = [("odom", "base_link", random_pose(rng)), ("base_link", "laser", random_pose(rng))]
    path_stamps = st + np.arange(5) * 0.25
    path_poses = np.stack([random_pose(rng) for _ in range(5)])
    grid = rng.choice(np.array([-1, 0, 100], np.int8), size=(7, 11))
    origin = geo.xytheta_to_matrix(-3.5, 2.25, 0.0)
    with McapLogWriter(p) as w:
        w.write_scan("/scan", st, "laser", -np.pi, np.pi / 180, 0.05, 30.0, ranges, inten)
        w.write_pointcloud("/points", st, "velodyne", pts)
        w.write_odometry("/odom", st, "odom", "base_link", pose, cov, twist)
        w.write_pose("/ground_truth", st, "map", pose)
        w.write_tf(st, tfs)
        w.write_tf(st, tfs[1:], static=True)
        w.write_path("/path", st, "map", path_stamps, path_poses)
        w.write_occupancy_grid("/map", st, "map", 0.05, origin, grid)
        w.write_message("/chatter", "std_msgs/msg/String", T["std_msgs/msg/String"](data="hello"), st)

    sec, nsec = stamp_to_time(st)

    def same_time(t, s=st):
        assert (t.sec, t.nanosec) == stamp_to_time(s)

    def same_pose(msgpose, P):
        t, q = pose_formats.pose_to_quat(P)
        got = np.array([msgpose.position.x, msgpose.position.y, msgpose.position.z])
        gq = np.array([msgpose.orientation.x, msgpose.orientation.y, msgpose.orientation.z, msgpose.orientation.w])
        np.testing.assert_array_equal(got, t)
        np.testing.assert_array_equal(gq, q)

    seen = set()
    with AnyReader([p]) as ar:
        for c, log_ns, raw in ar.messages():
            m = ar.deserialize(raw, c.msgtype)
            seen.add(c.topic)
            assert log_ns == stamp_to_ns(st) == sec * 10**9 + nsec
            if c.topic == "/scan":
                same_time(m.header.stamp)
                assert m.header.frame_id == "laser"
                np.testing.assert_array_equal(m.ranges, ranges)
                np.testing.assert_array_equal(m.intensities, inten)
                assert m.angle_min == np.float32(-np.pi) and m.angle_increment == np.float32(np.pi / 180)
                assert (m.range_min, m.range_max) == (np.float32(0.05), np.float32(30.0))
            elif c.topic == "/points":
                xyz = np.frombuffer(m.data.tobytes(), dtype=np.float32).reshape(-1, 3)
                np.testing.assert_array_equal(xyz, pts.astype(np.float32))
            elif c.topic == "/odom":
                assert (m.header.frame_id, m.child_frame_id) == ("odom", "base_link")
                same_pose(m.pose.pose, pose)
                np.testing.assert_array_equal(m.pose.covariance, cov.reshape(-1))
                tw = m.twist.twist
                np.testing.assert_array_equal([tw.linear.x, tw.linear.y, tw.linear.z, tw.angular.x, tw.angular.y, tw.angular.z], twist)
            elif c.topic == "/ground_truth":
                same_pose(m.pose, pose)
            elif c.topic in ("/tf", "/tf_static"):
                exp = tfs if c.topic == "/tf" else tfs[1:]
                assert [(x.header.frame_id, x.child_frame_id) for x in m.transforms] == [e[:2] for e in exp]
                for x, e in zip(m.transforms, exp):
                    tr = x.transform
                    t, q = pose_formats.pose_to_quat(e[2])
                    np.testing.assert_array_equal([tr.translation.x, tr.translation.y, tr.translation.z], t)
                    np.testing.assert_array_equal([tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w], q)
            elif c.topic == "/path":
                assert len(m.poses) == 5
                for ps, s, P in zip(m.poses, path_stamps, path_poses):
                    same_time(ps.header.stamp, s)
                    same_pose(ps.pose, P)
            elif c.topic == "/map":
                assert (m.info.width, m.info.height, m.info.resolution) == (11, 7, float(np.float32(0.05)))  # float32 field
                same_pose(m.info.origin, origin)
                np.testing.assert_array_equal(np.asarray(m.data, np.int8).reshape(7, 11), grid)
            elif c.topic == "/chatter":
                assert m.data == "hello"
    assert seen == {"/scan", "/points", "/odom", "/ground_truth", "/tf", "/tf_static", "/path", "/map", "/chatter"}

    with open(p, "rb") as fh:
        rd = make_reader(fh)
        assert rd.get_header().profile == "ros2"
        summ = rd.get_summary()
        assert summ is not None and summ.chunk_indexes and summ.statistics.message_count == 9
        assert all(ch.message_encoding == "cdr" for ch in summ.channels.values())
        for sc in summ.schemas.values():
            assert sc.encoding == "ros2msg" and "/msg/" in sc.name
        scan_schema = next(s for s in summ.schemas.values() if s.name == LASER_SCAN).data.decode()
        assert "\nMSG: std_msgs/Header\n" in scan_schema and "\nMSG: builtin_interfaces/Time\n" in scan_schema
        assert ("=" * 80 + "\nMSG: ") in scan_schema


def test_scan_frames_equal_written(tmp_path, rng):
    """Reader frames hold exactly the written beams at or above range_min: ranges =
    float64(float32 ranges) with inf for no return, angles = angle_min + i·increment, no_return for
    inf and ≥ range_max, points the returned beams at r(cos a, sin a), so every beam is either a
    point or a no-return; stamps exact."""
    p = tmp_path / "s.mcap"
    scans = []
    with McapLogWriter(p) as w:
        for i in range(12):
            r = rng.uniform(0.0, 12.0, 240).astype(np.float32)
            r[rng.random(240) < 0.1] = np.inf
            st = 1.6e9 + 0.1 * i
            scans.append((st, r))
            w.write_scan("/scan", st, "laser", -2.0, 0.0175, 0.2, 10.0, r)
    fr = list(McapReader(p).frames())
    assert [f.index for f in fr] == list(range(12))
    amin, inc = float(np.float32(-2.0)), float(np.float32(0.0175))
    for f, (st, r) in zip(fr, scans):
        keep = r >= np.float32(0.2)
        assert f.stamp == st and f.dim == 2 and f.num_beams == keep.sum() and (~keep).any()
        r64 = r.astype(np.float64)[keep]
        nr = r64 >= np.float32(10.0)
        np.testing.assert_array_equal(f.no_return, nr)
        np.testing.assert_array_equal(f.ranges, np.where(nr, np.inf, r64))
        np.testing.assert_array_equal(f.angles, amin + np.flatnonzero(keep) * inc)
        a = f.angles[~nr]
        np.testing.assert_array_equal(f.points, np.column_stack([r64[~nr] * np.cos(a), r64[~nr] * np.sin(a)]))
        assert len(f.points) + f.no_return.sum() == f.num_beams
        assert f.max_range == float(np.float32(10.0)) and f.odom is None
    inf = McapReader(p).info()
    assert (inf.format, inf.scans, inf.beams_per_scan, inf.dimension, inf.has_odometry) == ("mcap", 12, 240, 2, False)
    assert inf.duration_s == pytest.approx(1.1, abs=1e-6)


def test_stamps_round_trip_exactly(rng):
    """float → (sec, nanosec) → float is the identity for every stamp ≥ 1e7 s (epoch times: the
    float spacing exceeds 1 ns) and for every stamp that is the nearest float to a whole number of
    nanoseconds; nanosec is always in [0, 1e9)."""
    from types import SimpleNamespace

    from slam.logs.ros_msgs import time_to_stamp

    cands = list(rng.uniform(1e7, 4e9, 3000)) + [k / 1e9 for k in rng.integers(0, 4 * 10**18, 3000)] + [0.0, 1.0, 1e9 - 5e-10]
    for s in cands:
        sec, nsec = stamp_to_time(float(s))
        assert 0 <= nsec < 10**9
        assert time_to_stamp(SimpleNamespace(sec=sec, nanosec=nsec)) == float(s)


# ----------------------------------------------------------------------------- odometry, ground truth, TF


def test_odometry_interpolation_is_exact_on_constant_twist(tmp_path, rng):
    """Odometry sampled at 10 Hz along a constant-twist path T(t) = T0·Exp(t·ξ) (an SE(3) geodesic)
    interpolated to scan stamps between the samples equals the closed form T0·Exp(t·ξ): geodesic
    interpolation is exact on one-parameter subgroups. Planar twist → planar poses."""
    p = tmp_path / "o.mcap"
    T0 = geo.xytheta_to_matrix(1.0, -2.0, 0.4)
    xi = np.array([0.8, 0.1, 0.0, 0.0, 0.0, 0.35])
    t0 = 5000.0
    scan_t = t0 + 0.037 + 0.1 * np.arange(40)
    with McapLogWriter(p) as w:
        for k in range(42):
            t = t0 + 0.1 * k
            w.write_odometry("/odom", t, "odom", "base_link", T0 @ geo.se3_exp((t - t0) * xi))
        for t in scan_t:
            w.write_scan("/scan", t, "base_link", -1.0, 0.1, 0.1, 5.0, np.full(21, 2.0, np.float32))
    frames = list(open_log(p).frames())
    assert len(frames) == 40
    for f in frames:
        np.testing.assert_allclose(f.odom, T0 @ geo.se3_exp((f.stamp - t0) * xi), atol=1e-9)
        assert abs(f.odom[2, 3]) < 1e-12

    # Scans logged 0.3 s after their header stamp (driver latency): odometry with later stamps is
    # already in the stream, and the interpolation must still bracket each scan's stamp.
    p2 = tmp_path / "late.mcap"
    with McapLogWriter(p2) as w:
        for k in range(42):
            t = t0 + 0.1 * k
            w.write_odometry("/odom", t, "odom", "base_link", T0 @ geo.se3_exp((t - t0) * xi))
        for t in scan_t:
            sec, nsec = stamp_to_time(t)
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id="base_link")
            msg = T[LASER_SCAN](header=hdr, angle_min=-1.0, angle_max=1.0, angle_increment=0.1, time_increment=0.0, scan_time=0.0,
                                range_min=0.1, range_max=5.0, ranges=np.full(21, 2.0, np.float32), intensities=np.zeros(0, np.float32))
            w.write_message("/scan", LASER_SCAN, msg, t + 0.3)
    late = list(open_log(p2).frames())
    assert len(late) == 40
    for f in late:
        np.testing.assert_allclose(f.odom, T0 @ geo.se3_exp((f.stamp - t0) * xi), atol=1e-9)


def test_memory_does_not_grow_with_log_length(tmp_path):
    """Streaming: the peak memory allocated while iterating the frames of a 1500-scan log (with
    odometry and TF) is no larger than for a 150-scan log, up to a small slack."""
    import tracemalloc

    small = write_basic_log(tmp_path / "small.mcap", n=150, chunk_size=1 << 16)
    big = write_basic_log(tmp_path / "big.mcap", n=1500, chunk_size=1 << 16)
    peaks = []
    for p in (small, big):
        r = McapReader(p)
        r.topics()
        tracemalloc.start()
        n = sum(1 for _ in r.frames())
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        assert n in (150, 1500)
    assert peaks[1] < 1.25 * peaks[0] + 256 * 1024, peaks


def test_odometry_from_tf_when_no_odometry_topic(tmp_path):
    """Without an Odometry topic, Frame.odom comes from the TF edge odom → base_link (REP-105),
    geodesically interpolated (exact on a constant twist), the static mount still gives
    base_T_sensor, info reports odometry; odom_topic="" switches odometry off."""
    p = tmp_path / "tfodom.mcap"
    T0 = geo.xytheta_to_matrix(-1.0, 0.5, -0.2)
    xi = np.array([0.5, 0.0, 0.0, 0.0, 0.0, -0.25])
    mount = geo.xytheta_to_matrix(0.2, 0.0, 0.0)
    t0 = 1.6e9
    with McapLogWriter(p) as w:
        w.write_tf(t0, [("base_link", "laser", mount)], static=True)
        for k in range(61):
            t = t0 + 0.05 * k
            w.write_tf(t, [("odom", "base_link", T0 @ geo.se3_exp((t - t0) * xi))])
            if k % 2 == 1 and k < 59:
                w.write_scan("/scan", t + 0.013, "laser", -1.0, 0.1, 0.1, 5.0, np.full(21, 2.0, np.float32))
    r = McapReader(p)
    frames = list(r.frames())
    assert len(frames) == 29
    for f in frames:
        np.testing.assert_allclose(f.odom, T0 @ geo.se3_exp((f.stamp - t0) * xi), atol=1e-9)
        np.testing.assert_allclose(f.base_T_sensor, mount, atol=1e-12)
    assert r.info().has_odometry
    off = McapReader(p, odom_topic="")
    assert all(f.odom is None for f in off.frames()) and not off.info().has_odometry


def test_pose_track_holds_ends_and_refuses_far_queries():
    """Outside its samples the track holds the end pose within max_gap and returns None beyond."""
    tr = PoseTrack(max_gap=0.2)
    a, b = geo.xytheta_to_matrix(0, 0, 0), geo.xytheta_to_matrix(1, 0, 0)
    t_a, q_a = pose_formats.pose_to_quat(a)
    t_b, q_b = pose_formats.pose_to_quat(b)
    tr.add(1.0, np.concatenate([t_a, q_a]))
    tr.add(2.0, np.concatenate([t_b, q_b]))
    out = tr.query_many([0.9, 0.7, 1.5, 2.1, 2.5])
    np.testing.assert_array_equal(out[0], a)
    assert out[1] is None and out[4] is None
    np.testing.assert_allclose(out[2], geo.xytheta_to_matrix(0.5, 0, 0), atol=1e-12)
    np.testing.assert_array_equal(out[3], b)


def test_tf_chain_puts_sensor_on_base(tmp_path, rng):
    """base_T_sensor is the product of the static chain base_footprint → base_link → mount → laser
    (the odometry child frame is base_footprint), unaffected by the dynamic odom → base_footprint
    edges; and the dynamic-only mount case is interpolated in time."""
    p = tmp_path / "tf.mcap"
    A, B, C = random_pose(rng), random_pose(rng), random_pose(rng)
    with McapLogWriter(p) as w:
        w.write_tf(10.0, [("base_footprint", "base_link", A), ("base_link", "mount", B)], static=True)
        w.write_tf(10.0, [("mount", "laser", C)], static=True)
        for i in range(10):
            t = 10.0 + 0.1 * i
            w.write_tf(t, [("odom", "base_footprint", random_pose(rng, planar=True))])
            w.write_odometry("/odom", t, "odom", "base_footprint", np.eye(4))
            w.write_scan("/scan", t, "/laser", 0.0, 0.1, 0.1, 5.0, np.ones(5, np.float32))
    frames = list(open_log(p).frames())
    assert len(frames) == 10
    for f in frames:
        np.testing.assert_allclose(f.base_T_sensor, A @ B @ C, atol=1e-12)

    # Dynamic mount (e.g. a tilting laser): geodesic interpolation between its two samples.
    p2 = tmp_path / "tf2.mcap"
    M0, M1 = geo.xytheta_to_matrix(0, 0, 0), geo.xytheta_to_matrix(0.2, 0, 0.4)
    with McapLogWriter(p2) as w:
        w.write_tf(1.0, [("base_link", "laser", M0)])
        w.write_tf(2.0, [("base_link", "laser", M1)])
        w.write_scan("/scan", 1.5, "laser", 0.0, 0.1, 0.1, 5.0, np.ones(5, np.float32))
    (f,) = list(open_log(p2).frames())
    np.testing.assert_allclose(f.base_T_sensor, geo.se3_exp(0.5 * geo.se3_log(M1)), atol=1e-12)


def test_tf_buffer_lookup_is_consistent(rng):
    """On a random tf tree: lookup(a, c) = lookup(a, b)·lookup(b, c), lookup(b, a) = lookup(a, b)⁻¹,
    unconnected frames give None, and a leading '/' names the same frame."""
    tf = TfBuffer()
    names = [f"f{i}" for i in range(12)]
    for i in range(1, 12):
        tf.set_transform(names[int(rng.integers(0, i))], names[i], random_pose(rng), static=bool(i % 2))
        tf.set_transform(names[int(rng.integers(0, i))], names[i], random_pose(rng), stamp=0.0) if i % 2 == 0 else None
    tf.set_transform("x", "y", random_pose(rng), static=True)
    for _ in range(50):
        a, b, c = rng.choice(names, 3)
        ab, bc, ac = tf.lookup(a, b, 0.0), tf.lookup(b, c, 0.0), tf.lookup("/" + a, c, 0.0)
        np.testing.assert_allclose(ab @ bc, ac, atol=1e-9)
        np.testing.assert_allclose(tf.lookup(b, a, 0.0), geo.inverse(ab), atol=1e-9)
    assert tf.lookup("f0", "y", 0.0) is None


def test_ground_truth_and_topic_autodetection(tmp_path, rng):
    """The LaserScan topic with most messages is the sensor (over a PointCloud2 and a smaller
    LaserScan); topic= chooses another; /ground_truth (Odometry) fills Frame.ground_truth; with no
    LaserScan at all the PointCloud2 topic is used."""
    p = tmp_path / "gt.mcap"
    G = [random_pose(rng, planar=True) for _ in range(6)]
    with McapLogWriter(p) as w:
        for i in range(6):
            t = 100.0 + i
            w.write_scan("/scan", t, "laser", 0.0, 0.1, 0.1, 5.0, np.ones(4, np.float32))
            w.write_odometry("/ground_truth", t, "map", "base_link", G[i])
            w.write_odometry("/wheel_odom", t, "odom", "base_link", np.eye(4))
            if i < 3:
                w.write_scan("/scan_rear", t, "laser_rear", 0.0, 0.1, 0.1, 5.0, np.ones(3, np.float32))
            w.write_pointcloud("/points", t, "velodyne", rng.normal(size=(50, 3)))
    r = McapReader(p)
    fr = list(r.frames())
    assert len(fr) == 6 and all(f.num_beams == 4 for f in fr)
    for f, g in zip(fr, G):
        np.testing.assert_allclose(f.ground_truth, g, atol=1e-12)  # via the quaternion: equal to rounding
        np.testing.assert_array_equal(f.odom, np.eye(4))
    inf = r.info()
    assert (inf.sensor_topic, inf.has_ground_truth, inf.has_odometry) == ("/scan", True, True)
    assert {t.name: t.count for t in inf.topics}["/scan_rear"] == 3
    assert [f.num_beams for f in McapReader(p, "/scan_rear").frames()] == [3, 3, 3]
    assert McapReader(p, "/points").info().dimension == 3

    p2 = tmp_path / "cloud_only.mcap"
    with McapLogWriter(p2) as w:
        w.write_pointcloud("/points", 1.0, "velodyne", rng.normal(size=(50, 3)))
    inf = open_log(p2).info()
    assert (inf.sensor_topic, inf.dimension, inf.beams_per_scan) == ("/points", 3, 50)


def test_reads_file_written_by_rosbags(tmp_path, rng):
    """A ROS 2 bag written by rosbags (mcap storage) decodes through its own embedded schemas."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    d = tmp_path / "bag"
    ranges = rng.uniform(1, 3, 90).astype(np.float32)
    with Writer(d, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/base_scan", LASER_SCAN, typestore=ts)
        Tm, H = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
        for i in range(3):
            m = ts.types[LASER_SCAN](header=H(stamp=Tm(sec=7 + i, nanosec=5), frame_id="laser"), angle_min=-1.0,
                                     angle_max=1.0, angle_increment=0.02, time_increment=0.0, scan_time=0.1,
                                     range_min=0.1, range_max=4.0, ranges=ranges, intensities=np.zeros(0, np.float32))
            w.write(conn, (7 + i) * 10**9, ts.serialize_cdr(m, LASER_SCAN))
    (mcap_file,) = d.glob("*.mcap")
    fr = list(open_log(mcap_file).frames())
    assert [f.stamp for f in fr] == [7 + 5e-9, 8 + 5e-9, 9 + 5e-9]
    np.testing.assert_array_equal(fr[0].ranges, ranges.astype(np.float64))


def test_reads_file_without_summary(tmp_path):
    """An MCAP without summary section (streaming recorder) is read linearly with the same result."""
    from mcap.writer import IndexType, Writer

    from slam.logs.ros_msgs import message_definition

    src = write_basic_log(tmp_path / "a.mcap", n=8)
    ref = list(open_log(src).frames())
    p = tmp_path / "nosummary.mcap"
    r = McapReader(src)
    with open(p, "wb") as fh:
        w = Writer(fh, use_chunking=False, use_statistics=False, use_summary_offsets=False, repeat_channels=False,
                   repeat_schemas=False, index_types=IndexType(0))
        w.start("ros2", "test")
        ids = {}
        for raw in r._raw_messages(None):
            if raw.topic not in ids:
                sid = w.register_schema(raw.msgtype, "ros2msg", message_definition(raw.msgtype).encode())
                ids[raw.topic] = w.register_channel(raw.topic, "cdr", sid)
            w.add_message(ids[raw.topic], raw.log_time_ns, bytes(raw.data), raw.log_time_ns)
        w.finish()
    got = list(open_log(p).frames())
    assert len(got) == len(ref) == 8
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        np.testing.assert_array_equal(a.odom, b.odom)
        np.testing.assert_array_equal(a.base_T_sensor, b.base_T_sensor)
    assert open_log(p).info().scans == 8


# ----------------------------------------------------------------------------- bad input


def _expect(path, match, fn=lambda r: list(r.frames()), topic=None, exc=LogFormatError):
    with pytest.raises(exc) as ei:
        fn(McapReader(path, topic))
    msg = str(ei.value)
    assert str(path) in msg and match in msg, msg
    return msg


def test_bad_ranges_and_empty_scan_name_the_message(tmp_path):
    """A NaN range, a negative range and a 0-beam scan each raise LogFormatError naming the file
    and the scan's message index, from frames() and from info()."""
    p = write_basic_log(tmp_path / "nan.mcap", nan_at=4)
    _expect(p, "/scan message 4")
    _expect(p, "NaN", fn=lambda r: r.info())
    p = write_basic_log(tmp_path / "neg.mcap", neg_at=6)
    _expect(p, "/scan message 6")
    p = write_basic_log(tmp_path / "empty.mcap", empty_at=2)
    assert "empty LaserScan" in _expect(p, "/scan message 2")


def test_missing_topic_lists_topics(tmp_path):
    """Asking for a topic that is not there raises TopicNotFoundError listing the topics that exist;
    a log with no sensor topic likewise."""
    p = write_basic_log(tmp_path / "a.mcap", n=3)
    msg = _expect(p, "/velodyne_points", topic="/velodyne_points", exc=TopicNotFoundError)
    assert "/scan" in msg and "/odom" in msg
    p2 = tmp_path / "nosensor.mcap"
    with McapLogWriter(p2) as w:
        w.write_odometry("/odom", 1.0, "odom", "base_link", np.eye(4))
    _expect(p2, "no LaserScan or PointCloud2", fn=lambda r: r.info(), exc=TopicNotFoundError)


def test_unknown_types_on_chosen_topic(tmp_path):
    """Choosing a topic whose type is not a sensor type, or one whose schema is not ROS, raises
    LogFormatError."""
    p = tmp_path / "u.mcap"
    with McapLogWriter(p) as w:
        w.write_path("/path", 1.0, "map", [1.0], np.eye(4)[None])
    _expect(p, "unsupported message type nav_msgs/msg/Path", topic="/path")

    from mcap.writer import Writer

    p2 = tmp_path / "json.mcap"
    with open(p2, "wb") as fh:
        w = Writer(fh)
        w.start("", "test")
        sid = w.register_schema("sensor_msgs/msg/LaserScan", "jsonschema", b"{}")
        cid = w.register_channel("/scan", "json", sid)
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    _expect(p2, "/scan message 0")


@pytest.mark.parametrize("cut", [0.5, 0.97])
@pytest.mark.parametrize("chunk_size", [1 << 20, 8192])
def test_truncated_file(tmp_path, cut, chunk_size):
    """A truncated MCAP (summary lost, a chunk cut) raises LogFormatError with the byte offset and,
    when whole chunks precede the cut, the last message read."""
    src = write_basic_log(tmp_path / "a.mcap", n=400, chunk_size=chunk_size)
    data = src.read_bytes()
    p = tmp_path / "trunc.mcap"
    p.write_bytes(data[: int(len(data) * cut)])
    msg = _expect(p, "byte offset")
    if chunk_size < len(data) * cut:
        assert "after /scan message" in msg or "after /odom message" in msg, msg
    _expect(p, "truncated", fn=lambda r: r.info())


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_corrupt_bytes(tmp_path, compression):
    """Overwritten bytes inside the data section are detected (chunk CRC, decompression) and
    reported as LogFormatError naming the file and position, whatever the chunk compression."""
    src = write_basic_log(tmp_path / "a.mcap", n=400, compression=compression)
    data = bytearray(src.read_bytes())
    mid = len(data) // 3
    data[mid : mid + 64] = bytes(64)
    p = tmp_path / "corrupt.mcap"
    p.write_bytes(bytes(data))
    _expect(p, "corrupt")


@pytest.mark.parametrize("content", [b"", b"\x89MCAP0\r\n", b"hello world, not a log"])
def test_empty_or_foreign_file(tmp_path, content):
    """An empty file, a bare magic, or a non-MCAP file named .mcap is a LogFormatError."""
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(LogFormatError) as ei:
        list(open_log(p).frames())
    assert str(p) in str(ei.value)


def _bad_logs(d):
    """(name, path, extra CLI args, text the error must contain) for every kind of bad MCAP input."""
    out = [("nan", write_basic_log(d / "nan.mcap", nan_at=1), [], "/scan message 1"),
           ("negative", write_basic_log(d / "neg.mcap", neg_at=2), [], "/scan message 2"),
           ("empty_scan", write_basic_log(d / "empty_scan.mcap", empty_at=3), [], "/scan message 3")]
    good = write_basic_log(d / "good.mcap", n=300, chunk_size=8192)
    data = good.read_bytes()
    (d / "trunc.mcap").write_bytes(data[: len(data) // 2])
    out.append(("truncated", d / "trunc.mcap", [], "byte offset"))
    bad = bytearray(data)
    bad[len(bad) // 3 : len(bad) // 3 + 64] = bytes(64)
    (d / "corrupt.mcap").write_bytes(bytes(bad))
    out.append(("corrupt", d / "corrupt.mcap", [], "byte offset"))
    out.append(("missing_topic", good, ["--topic", "/nope"], "/nope"))
    out.append(("unknown_type", good, ["--topic", "/odom"], "unsupported message type"))
    (d / "empty.mcap").write_bytes(b"")
    out.append(("empty_file", d / "empty.mcap", [], "empty file"))
    return out


def test_cli_info_bad_input_exit_2(tmp_path, capsys):
    """For every bad input (NaN, negative, empty scan, truncated, corrupt, missing topic, unknown
    type, empty file) `slam info` exits 2 with exactly one stderr line naming the file and the
    position, prints no `scans:` line, and leaves no file behind."""
    from slam.cli import main

    for name, p, extra, what in _bad_logs(tmp_path):
        before = set(tmp_path.iterdir())
        with pytest.raises(SystemExit) as ei:
            main(["info", str(p), *extra])
        assert ei.value.code == 2, name
        cap = capsys.readouterr()
        err = cap.err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and str(p) in err[0] and what in err[0], (name, err)
        assert "scans:" not in cap.out, name
        assert set(tmp_path.iterdir()) == before, name


def test_cli_info_prints_scans(tmp_path, capsys):
    """`slam info` on a written log prints `scans: N` for the N scans written."""
    from slam.cli import main

    p = write_basic_log(tmp_path / "ok.mcap", n=17)
    try:
        main(["info", str(p)])
    except SystemExit as e:  # typer exits 0 on success
        assert e.code in (0, None)
    out = capsys.readouterr().out.splitlines()
    assert "scans: 17" in out and "odometry: yes" in out


def test_writer_failure_leaves_no_file(tmp_path):
    """An exception inside the writer's with-block leaves neither the log nor a temporary file."""
    p = tmp_path / "fail.mcap"
    with pytest.raises(RuntimeError):
        with McapLogWriter(p) as w:
            w.write_scan("/scan", 1.0, "laser", 0.0, 0.1, 0.1, 5.0, np.ones(5))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError):
        with McapLogWriter(p) as w:
            w.write_occupancy_grid("/map", 1.0, "map", 0.1, np.eye(4), np.full((2, 2), 300))
    assert list(tmp_path.iterdir()) == []


def _clouds(rng, n=4, mount=None):
    """3D frames with float32-valued points, odometry, ground truth and a sensor mount, 10 Hz."""
    from core.frame import Frame

    mount = random_pose(rng) if mount is None else mount
    return [Frame(stamp=1.7e9 + 0.1 * k, points=rng.normal(size=(200, 3)).astype(np.float32), index=k,
                  odom=random_pose(rng), ground_truth=random_pose(rng), base_T_sensor=mount) for k in range(n)]


def test_cloud_log_reads_back_as_the_frames(tmp_path, rng):
    """write_cloud_log → open_log: the same frames: float32 points bit-identical, stamps exact, odometry,
    ground truth and the sensor mount (static TF) equal to the float64 rounding of a quaternion."""
    frames = _clouds(rng)
    p = tmp_path / "clouds.mcap"
    assert write_cloud_log(p, frames) == len(frames)
    back = list(open_log(p).frames())
    assert len(back) == len(frames)
    for a, b in zip(frames, back):
        assert b.stamp == a.stamp and b.index == a.index and np.array_equal(b.points, a.points)
        for got, want in ((b.odom, a.odom), (b.ground_truth, a.ground_truth), (b.base_T_sensor, a.base_T_sensor)):
            np.testing.assert_allclose(got, want, atol=1e-12)


def test_cloud_log_refuses_what_it_cannot_carry(tmp_path, rng):
    """A planar scan, or a sensor mount that moves between frames, is a GeometryError naming the frame,
    and no file is left."""
    from core.errors import GeometryError
    from core.frame import Frame

    p = tmp_path / "bad.mcap"
    with pytest.raises(GeometryError, match="frame 0 is a planar scan"):
        write_cloud_log(p, [Frame(stamp=1.0, points=np.ones((5, 2)))])
    frames = _clouds(rng, 3)
    moved = frames[:2] + [dataclasses.replace(frames[2], base_T_sensor=random_pose(rng))]
    with pytest.raises(GeometryError, match="frame 2: base_T_sensor differs"):
        write_cloud_log(p, moved)
    assert list(tmp_path.iterdir()) == []
