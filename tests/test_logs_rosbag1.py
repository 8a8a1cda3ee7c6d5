"""ROS 1 bag reader: the Killian benchmark bag, written bags round trip, bad input."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from core import geometry as geo
from core import pose_formats
from core.errors import LogFormatError, TopicNotFoundError
from slam.logs import open_log
from slam.logs.rosbag1 import Ros1BagReader
from tests.conftest import shared_path


def _ros1_store():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # the Noetic store of rosbags lacks tf2_msgs
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def write_bag(path, n=20, *, mount=None, nan_at=None, with_cloud=False, compression=None, chunk_threshold=None,
              time_increment=0.0, scan_time=0.0):
    """A ROS 1 bag with /scan (LaserScan), /odom (Odometry), /tf_static (mount) and optionally /points
    (chunks *compression* ``"bz2"``/``"lz4"`` when given, of about *chunk_threshold* bytes)."""
    from rosbags.rosbag1 import Writer

    ts = _ros1_store()
    Ty = ts.types
    rng = np.random.default_rng(11)
    written = []

    def hdr(t, frame):
        sec, nsec = int(t), int(round((t - int(t)) * 1e9))
        return Ty["std_msgs/msg/Header"](seq=0, stamp=Ty["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame)

    def pose_msg(P):
        t, q = pose_formats.pose_to_quat(P)
        return Ty["geometry_msgs/msg/Pose"](
            position=Ty["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
            orientation=Ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    w = Writer(path)
    if compression is not None:
        w.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    if chunk_threshold is not None:
        w.chunk_threshold = chunk_threshold
    with w:
        cs = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        ct = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        cp = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts) if with_cloud else None
        t0 = 1000.0
        if mount is not None:
            p, q = pose_formats.pose_to_quat(mount)
            tr = Ty["geometry_msgs/msg/Transform"](
                translation=Ty["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                rotation=Ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            m = Ty["tf2_msgs/msg/TFMessage"](transforms=[Ty["geometry_msgs/msg/TransformStamped"](header=hdr(t0, "base_link"), child_frame_id="laser", transform=tr)])
            w.write(ct, int(t0 * 1e9), ts.serialize_ros1(m, "tf2_msgs/msg/TFMessage"))
        for i in range(n):
            t = t0 + 0.5 * i
            r = rng.uniform(0.2, 7.0, 180).astype(np.float32)
            r[::9] = np.inf
            if i == nan_at:
                r[3] = np.nan
            odom = geo.xytheta_to_matrix(0.3 * i, -0.1 * i, 0.05 * i)
            written.append((t, r, odom))
            scan = Ty["sensor_msgs/msg/LaserScan"](
                header=hdr(t, "laser"), angle_min=-np.pi / 2, angle_max=np.pi / 2, angle_increment=np.pi / 180,
                time_increment=time_increment, scan_time=scan_time, range_min=0.1, range_max=6.5, ranges=r,
                intensities=np.zeros(0, np.float32),
            )
            w.write(cs, int(round(t * 1e9)), ts.serialize_ros1(scan, "sensor_msgs/msg/LaserScan"))
            cov = Ty["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(odom), covariance=np.zeros(36))
            zero = Ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            tw = Ty["geometry_msgs/msg/TwistWithCovariance"](twist=Ty["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36))
            om = Ty["nav_msgs/msg/Odometry"](header=hdr(t, "odom"), child_frame_id="base_link", pose=cov, twist=tw)
            w.write(co, int(round(t * 1e9)), ts.serialize_ros1(om, "nav_msgs/msg/Odometry"))
            if cp is not None:
                pts = rng.normal(size=(64, 3)).astype(np.float32)
                pf = [Ty["sensor_msgs/msg/PointField"](name=c, offset=4 * k, datatype=7, count=1) for k, c in enumerate("xyz")]
                cm = Ty["sensor_msgs/msg/PointCloud2"](header=hdr(t, "velodyne"), height=1, width=64, fields=pf, is_bigendian=False,
                                                       point_step=12, row_step=768, data=pts.view(np.uint8).reshape(-1), is_dense=True)
                w.write(cp, int(round(t * 1e9)), ts.serialize_ros1(cm, "sensor_msgs/msg/PointCloud2"))
    return written


def test_killian_bag_scan_count(capsys):
    """`slam info` on the MIT Killian bag prints `scans: 17480` (SOURCE.md: 17,480 /scan messages,
    180 beams), with odometry detected; its first frames carry the /odom pose and the identity mount."""
    from slam.cli import main

    bag = shared_path("slam2d_kummerle_benchmark", "mit-killian.clf2bag.bag")
    try:
        main(["info", str(bag)])
    except SystemExit as e:
        assert e.code in (0, None)
    out = capsys.readouterr().out.splitlines()
    assert "scans: 17480" in out
    assert "beams_per_scan: 180" in out and "odometry: yes" in out and "format: ros1" in out
    frames = list(itertools.islice(open_log(bag).frames(), 30))
    assert [f.index for f in frames] == list(range(30))
    np.testing.assert_allclose(np.diff([f.stamp for f in frames]), 0.1, atol=1e-6)  # SOURCE.md: t = 1e9 + 0.1·i
    assert frames[0].stamp == 1e9
    for f in frames:
        assert f.num_beams == 180 and f.odom is not None
        np.testing.assert_allclose(f.base_T_sensor, np.eye(4), atol=1e-15)
        assert f.angles[0] == float(np.float32(-np.pi / 2))


def test_written_bag_round_trip(tmp_path):
    """Frames of a written ROS 1 bag hold the written ranges (float32 → float64 exactly, inf for no
    return), the odometry of the same stamp, and the static TF mount as base_T_sensor."""
    p = tmp_path / "a.bag"
    mount = geo.xytheta_to_matrix(0.25, 0.05, -0.3)
    written = write_bag(p, mount=mount)
    r = Ros1BagReader(p)
    frames = list(r.frames())
    assert len(frames) == len(written)
    for f, (t, rr, odom) in zip(frames, written):
        assert f.stamp == pytest.approx(t, abs=1e-9)
        nr = rr >= np.float32(6.5)
        np.testing.assert_array_equal(f.ranges, np.where(nr, np.inf, rr.astype(np.float64)))
        np.testing.assert_array_equal(f.no_return, nr)
        np.testing.assert_allclose(f.odom, odom, atol=1e-12)
        np.testing.assert_allclose(f.base_T_sensor, mount, atol=1e-12)
    inf = r.info()
    assert (inf.format, inf.scans, inf.beams_per_scan, inf.has_odometry) == ("ros1", 20, 180, True)


def test_beam_times_from_time_increment(tmp_path, capsys):
    """A LaserScan's ``time_increment`` gives each beam's time after the stamp (i·increment, REP-117),
    which the front end deskews with — a negative one counts from the last beam; a driver that leaves it 0,
    or states a sweep longer than its own ``scan_time``, gives none."""
    inc = 1.0 / 75 / 360  # a SICK LMS at 75 Hz, 0.5° steps
    p = tmp_path / "timed.bag"
    write_bag(p, n=3, time_increment=inc, scan_time=1.0 / 75)
    for f in Ros1BagReader(p).frames():
        np.testing.assert_allclose(f.beam_times, np.arange(180) * float(np.float32(inc)), rtol=1e-12)
    write_bag(tmp_path / "backwards.bag", n=2, time_increment=-inc, scan_time=1.0 / 75)  # the last beam first
    for f in Ros1BagReader(tmp_path / "backwards.bag").frames():
        np.testing.assert_allclose(f.beam_times, np.arange(180)[::-1] * float(np.float32(inc)), rtol=1e-12)
    write_bag(tmp_path / "plain.bag", n=2)
    write_bag(tmp_path / "odd.bag", n=2, time_increment=0.01, scan_time=0.1)  # 1.79 s of sweep in a 0.1 s scan
    for name in ("plain.bag", "odd.bag"):
        assert all(f.beam_times is None for f in Ros1BagReader(tmp_path / name).frames())
    # `slam info` says so: the sweep of 179 increments, or none
    from slam.cli import main

    for name, said in (("timed.bag", f"beam_times: yes ({179e3 * float(np.float32(inc)):.1f} ms a sweep"),
                       ("plain.bag", "beam_times: no")):
        with pytest.raises(SystemExit) as done:
            main(["info", str(tmp_path / name)])
        assert done.value.code in (0, None)
        assert any(line.startswith(said) for line in capsys.readouterr().out.splitlines())


def test_pointcloud_topic_in_bag(tmp_path):
    """A PointCloud2 topic in a ROS 1 bag is read as 3D frames with the written points."""
    p = tmp_path / "c.bag"
    write_bag(p, n=4, with_cloud=True)
    frames = list(Ros1BagReader(p, "/points").frames())
    assert len(frames) == 4 and all(f.dim == 3 and len(f.points) == 64 for f in frames)


def test_bag_bad_input(tmp_path, capsys):
    """NaN range → LogFormatError naming file and '/scan message k'; a missing topic →
    TopicNotFoundError listing the topics; a truncated or foreign file → LogFormatError; the CLI
    turns each into exit 2 with one stderr line."""
    from slam.cli import main

    p = tmp_path / "nan.bag"
    write_bag(p, nan_at=7)
    with pytest.raises(LogFormatError) as ei:
        list(Ros1BagReader(p).frames())
    assert str(p) in str(ei.value) and "/scan message 7" in str(ei.value)
    with pytest.raises(TopicNotFoundError) as ei:
        Ros1BagReader(p, "/nope").info()
    assert "/scan" in str(ei.value) and "/odom" in str(ei.value)

    good = tmp_path / "good.bag"
    write_bag(good, n=40)
    data = good.read_bytes()
    for name, content in [("trunc.bag", data[: len(data) // 2]), ("junk.bag", b"#ROSBAG V2.0\n" + bytes(100)), ("empty.bag", b"")]:
        q = tmp_path / name
        q.write_bytes(content)
        with pytest.raises(LogFormatError) as ei:
            Ros1BagReader(q).info()
        assert str(q) in str(ei.value)
        with pytest.raises(SystemExit) as se:
            main(["info", str(q)])
        assert se.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and str(q) in err[0]
