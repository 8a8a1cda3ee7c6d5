"""CARMEN log reader: the benchmark logs, synthetic lines with known numbers, bad input, fuzzing."""

from __future__ import annotations

import bz2
import gzip
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core import geometry as geo
from core.errors import LogFormatError, TopicNotFoundError
from core.frame import Frame
from evaluation.relations import read_relations
from slam.logs import open_log
from slam.logs.carmen import CarmenReader, detect_saturation
from slam.logs.carmen_lines import DEFAULT_FLASER_MAX_RANGE, parse_laser_line
from tests.conftest import DATA, shared_path

INTEL = DATA / "intel.clf.bz2"
CSAIL = DATA / "mit-csail.clf.bz2"


# ----------------------------------------------------------------------------- helpers

def _num(v: float) -> str:
    return repr(float(v))


def flaser(ranges, laser=(0.0, 0.0, 0.0), robot=(0.0, 0.0, 0.0), stamp=1000.5, tag="FLASER") -> str:
    """A FLASER/RLASER line with exactly representable numbers (repr round-trips floats)."""
    vals = " ".join(_num(r) for r in ranges)
    poses = " ".join(_num(v) for v in (*laser, *robot))
    return f"{tag} {len(ranges)} {vals} {poses} {_num(stamp)} myhost 0.001"


def robotlaser(ranges, start=-1.5, res=0.01, max_range=30.0, laser=(0.2, 0.0, 0.0), robot=(0.0, 0.0, 0.0),
               stamp=2000.25, remissions=(), tag="ROBOTLASER1") -> str:
    vals = " ".join(_num(r) for r in ranges)
    rem = " ".join(_num(r) for r in remissions)
    poses = " ".join(_num(v) for v in (*laser, *robot))
    fov = res * (len(ranges) - 1)
    head = f"{tag} 0 {_num(start)} {_num(fov)} {_num(res)} {_num(max_range)} 0.01 0 {len(ranges)} {vals} {len(remissions)}"
    return f"{head}{' ' + rem if rem else ''} {poses} 0.1 0.2 0.5 0.3 0.4 {_num(stamp)} host 12.5"


def odom_line(x=0.0, y=0.0, th=0.0, stamp=999.0) -> str:
    return f"ODOM {_num(x)} {_num(y)} {_num(th)} 0.0 0.0 0.0 {_num(stamp)} host 0.0"


def write_log(path: Path, lines: list[str], comp: str = "plain") -> Path:
    data = ("\n".join(lines) + "\n").encode()
    if comp == "bz2":
        data = bz2.compress(data)
    elif comp == "gz":
        data = gzip.compress(data)
    path.write_bytes(data)
    return path


def synthetic_log(rng, n_scans=30, n_beams=90) -> list[str]:
    lines = ["# synthetic CARMEN log", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    t = 100.0
    for k in range(n_scans):
        r = np.round(rng.uniform(0.1, 20.0, n_beams), 3)
        r[rng.random(n_beams) < 0.1] = 81.91
        pose = (k * 0.1, 0.5 * k, 0.01 * k)
        lines.append(odom_line(*pose, stamp=t))
        lines.append(flaser(r, pose, pose, stamp=t + 0.05))
        t += 0.2
    return lines


@pytest.fixture(scope="module")
def intel_frames() -> list[Frame]:
    return list(CarmenReader(INTEL).frames())


# ----------------------------------------------------------------------------- real logs

def test_intel_scan_count_and_beam_geometry(intel_frames):
    """Intel has 13,631 FLASER scans of 180 beams (SOURCE.md), 1° apart from −90° (CARMEN's own reader)."""
    assert len(intel_frames) == 13631
    f = intel_frames[0]
    assert f.num_beams == 180
    assert np.allclose(np.diff(f.angles), math.pi / 180)  # the SICK's 1° mode (flaser_layout)
    assert f.angles[0] == pytest.approx(-math.pi / 2) and f.angles[-1] == pytest.approx(math.radians(89.0))
    assert [fr.index for fr in intel_frames[:5]] == [0, 1, 2, 3, 4]
    assert intel_frames[0].source == "intel.clf.bz2:line 13"


def test_intel_points_are_the_returned_beams(intel_frames):
    """points = (r cos a, r sin a) of exactly the beams with a return; no-return beams carry inf."""
    for f in intel_frames[::500]:
        hit = ~f.no_return
        assert np.array_equal(np.isinf(f.ranges), f.no_return)
        assert f.points.shape == (hit.sum(), 2)
        np.testing.assert_allclose(f.points, np.column_stack([f.ranges[hit] * np.cos(f.angles[hit]),
                                                              f.ranges[hit] * np.sin(f.angles[hit])]), atol=1e-12)
        assert (f.ranges[hit] < f.max_range).all()


def test_intel_max_range_code_is_detected(intel_frames):
    """Intel saturates at 81.83 m: every such beam is no-return, and no hit is beyond 80 m."""
    assert 80.0 < intel_frames[0].max_range < 81.83
    n_noreturn = sum(int(f.no_return.sum()) for f in intel_frames)
    hits = np.concatenate([f.ranges[~f.no_return] for f in intel_frames[::50]])
    assert hits.max() < 80.0
    assert n_noreturn > 0


def test_intel_odometry_and_mounting(intel_frames):
    """Odometry is a proper SE(2) pose; laser pose equals robot pose in Intel, so base_T_sensor = I."""
    poses = np.array([f.odom for f in intel_frames[::100]])
    assert geo.is_pose(poses)
    for f in intel_frames[::997]:
        np.testing.assert_allclose(f.base_T_sensor, np.eye(4), atol=1e-9)
    xyt = geo.matrix_to_xytheta(np.array([f.odom for f in intel_frames]))
    assert np.abs(np.diff(xyt[:, :2], axis=0)).max() < 1.0  # odometry is continuous (no pose jumps)
    # Frames come in file order. Intel's ipc_timestamps are not monotonic (631 steps back, all
    # under 1 s: the logger interleaves hosts), so nothing downstream may assume sorted stamps.
    d = np.diff([f.stamp for f in intel_frames])
    assert (d > -1.0).all() and (d > 0).mean() > 0.95


def test_csail_scans_and_half_degree_beams():
    """CSAIL: 1,988 FLASER scans of 361 beams, i.e. 0.5° steps over 180°, odometry in the laser lines."""
    frames = list(open_log(CSAIL).frames())
    assert len(frames) == 1988
    assert frames[0].num_beams == 361
    assert np.allclose(np.diff(frames[0].angles), math.radians(0.5))
    assert np.ptp([f.odom[0, 3] for f in frames]) > 10.0


@pytest.mark.parametrize("log", ["intel", "mit-csail"])
def test_relation_stamps_match_scan_stamps(log, request):
    """Every t1/t2 of data/<log>.relations equals the ipc_timestamp of a scan (< 1e-5 s, SOURCE.md)."""
    frames = request.getfixturevalue("intel_frames") if log == "intel" else open_log(DATA / f"{log}.clf.bz2")
    stamps = np.sort([f.stamp for f in frames])
    rel = read_relations(DATA / f"{log}.relations")
    t = np.unique(np.concatenate([rel.t1, rel.t2]))
    i = np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1)
    err = np.minimum(np.abs(stamps[i] - t), np.abs(stamps[i - 1] - t))
    assert err.max() < 1e-5


def test_fr_clinic_robotlaser():
    """Freiburg hospital: 6,917 ROBOTLASER1 scans; the laser sits at a fixed offset ahead of the base
    (the laser pose in the robot frame is the same rigid transform on every line)."""
    frames = list(open_log(shared_path("slam2d_kummerle_benchmark", "fr-clinic_robotlaser.clf.bz2")).frames())
    assert len(frames) == 6917
    off = np.array([f.base_T_sensor[:3, 3] for f in frames])
    assert np.abs(off[:, 0] - np.median(off[:, 0])).max() < 0.01
    assert np.median(off[:, 0]) > 0.0 and np.abs(off[:, 1]).max() < 0.01
    f = frames[0]
    assert f.max_range == pytest.approx(81.9)
    assert np.allclose(np.diff(f.angles), 0.017453)


# ----------------------------------------------------------------------------- synthetic lines

def test_flaser_line_round_trip():
    """The numbers written into a FLASER line come back: ranges, stamp, odometry, laser pose."""
    r = np.array([1.0, 2.5, 81.91, 0.0, 3.25])
    robot = (10.0, -2.0, 0.5)
    laser = (10.0 + 0.04 * math.cos(0.5), -2.0 + 0.04 * math.sin(0.5), 0.5)  # 4 cm ahead, like fr079
    f = parse_laser_line(flaser(r, laser, robot, stamp=976052857.337284), path="x.clf", lineno=7)
    assert f.stamp == 976052857.337284
    assert f.source == "x.clf:line 7"
    # zero reading dropped, 81.91 ≥ 80 m default is no-return
    assert f.num_beams == 4
    np.testing.assert_array_equal(f.no_return, [False, False, True, False])
    np.testing.assert_array_equal(f.ranges[~f.no_return], [1.0, 2.5, 3.25])
    np.testing.assert_allclose(f.angles, [-math.pi / 2, -math.pi / 4, 0.0, math.pi / 2])
    np.testing.assert_allclose(geo.matrix_to_xytheta(f.odom), robot)
    np.testing.assert_allclose(geo.matrix_to_xytheta(f.odom @ f.base_T_sensor), laser, atol=1e-12)
    np.testing.assert_allclose(f.base_T_sensor[:3, 3], [0.04, 0.0, 0.0], atol=1e-12)
    assert f.max_range == DEFAULT_FLASER_MAX_RANGE


ROOM = (-3.0, 5.0, -2.0, 4.0)  # x_min, x_max, y_min, y_max of a box-shaped room (m)


def _room_scan(pose: tuple[float, float, float], angles: np.ndarray) -> np.ndarray:
    """Ranges from *pose* (x, y, θ) inside ROOM along the laser-frame *angles*: the nearest wall."""
    x, y, th = pose
    c, s = np.cos(th + angles), np.sin(th + angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (ROOM[1] - x) / c, (ROOM[0] - x) / c)
        ty = np.where(s > 0, (ROOM[3] - y) / s, (ROOM[2] - y) / s)
    return np.minimum(np.abs(tx), np.abs(ty))


def _sick(n: int) -> np.ndarray:
    """Beam angles of a SICK LMS in the mode whose line has n beams: its step from −90°."""
    step = math.radians(1.0 if n in (180, 181) else 0.5)
    return -0.5 * math.pi + step * np.arange(n)


@pytest.mark.parametrize("n", [180, 181, 360, 361])
def test_flaser_beams_of_a_known_room_read_back_onto_its_walls(n):
    """A SICK's scan of a box-shaped room written as an n-beam FLASER line reads back with every point on a
    wall: the reader spaces the beams at the mode's step (1° or 0.5°), not 180° / (n − 1), which for 180
    beams misplaces the outer points by 0.5° (4 cm at 5 m)."""
    pose = (0.4, 0.3, 0.2)
    f = parse_laser_line(flaser(np.round(_room_scan(pose, _sick(n)), 12), pose, pose))
    p = geo.transform_points(f.odom @ f.base_T_sensor, f.points)
    off_wall = np.min(np.abs(np.column_stack([p[:, 0] - ROOM[0], p[:, 0] - ROOM[1], p[:, 1] - ROOM[2], p[:, 1] - ROOM[3]])), axis=1)
    assert f.num_beams == n and off_wall.max() < 1e-9


def test_a_turn_between_two_flaser_scans_is_measured_unscaled():
    """Two 180-beam scans of a room 27.3° and 0.3 m apart, read and registered (point-to-plane ICP): the
    turn comes out at 27.3° to 0.02°. Beams spread over 180° would stretch each scan by 180/179 and the
    registration would turn the robot that much too far (0.15° here, 2° per full circle)."""
    from registration.point_to_plane import icp_point_to_plane

    a, b = (0.4, 0.3, 0.2), (0.6, 0.5, 0.2 + math.radians(27.3))
    fa, fb = (parse_laser_line(flaser(np.round(_room_scan(p, _sick(180)), 12), p, p)) for p in (a, b))
    truth = geo.relative(geo.xytheta_to_matrix(*a), geo.xytheta_to_matrix(*b))
    res = icp_point_to_plane(fb.points, fa.points, geo.xytheta_to_matrix(0.25, 0.1, 0.45))
    err = geo.matrix_to_xytheta(geo.relative(truth, res.transform))
    assert abs(math.degrees(err[2])) < 0.02 and np.hypot(err[0], err[1]) < 2e-3


def test_rlaser_faces_backwards():
    """A rear laser written with the robot's heading gets a half turn: base_T_sensor yaw = π."""
    f = parse_laser_line(flaser([1.0, 1.0, 1.0], tag="RLASER"))
    assert abs(abs(geo.matrix_to_xytheta(f.base_T_sensor)[2]) - math.pi) < 1e-12
    # a hit straight ahead of the rear laser lies behind the robot
    mid = geo.transform_points(f.base_T_sensor, f.points)[1]
    np.testing.assert_allclose(mid, [-1.0, 0.0], atol=1e-12)


def test_robotlaser_geometry_and_max_range():
    """ROBOTLASER1: angle_i = start + i·res, no-return at its own max_range, remissions skipped."""
    r = [1.0, 30.0, 2.0, 45.0]
    f = parse_laser_line(robotlaser(r, start=-1.0, res=0.25, max_range=30.0, remissions=(5.0, 6.0, 7.0, 8.0)))
    np.testing.assert_allclose(f.angles, [-1.0, -0.75, -0.5, -0.25])
    np.testing.assert_array_equal(f.no_return, [False, True, False, True])
    assert f.max_range == 30.0 and f.stamp == 2000.25
    np.testing.assert_allclose(f.base_T_sensor[:3, 3], [0.2, 0.0, 0.0])


def test_max_range_override_and_saturation_heuristic():
    """An explicit max range wins; the saturation heuristic finds a repeated ceiling value only."""
    f = parse_laser_line(flaser([1.0, 40.0, 50.0]), max_range=45.0)
    np.testing.assert_array_equal(f.no_return, [False, False, True])
    rng = np.random.default_rng(0)
    r = rng.uniform(0.2, 15.0, 5000)
    assert detect_saturation(r) is None  # no ceiling, short ranges
    r[::50] = 49.98
    thr = detect_saturation(r)
    assert thr is not None and 49.8 < thr < 49.98
    assert detect_saturation(np.append(rng.uniform(0.2, 15, 5000), 60.0)) is None  # a single far hit is no ceiling


@pytest.mark.parametrize("comp", ["plain", "bz2", "gz"])
def test_compression_gives_identical_frames(tmp_path, comp):
    """Plain, bz2 and gzip copies of one log give the same frames (streamed in 1 MiB blocks)."""
    rng = np.random.default_rng(3)
    lines = synthetic_log(rng, n_scans=40)
    ref = list(CarmenReader(write_log(tmp_path / "ref.clf", lines)).frames())
    got = list(CarmenReader(write_log(tmp_path / f"log.clf.{comp}", lines, comp)).frames())
    assert len(got) == len(ref) == 40
    for a, b in zip(ref, got):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.ranges, b.ranges)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.odom, b.odom)


def test_long_lines_across_blocks(tmp_path, monkeypatch):
    """Lines that straddle block boundaries are reassembled (tiny blocks force many boundaries)."""
    import slam.logs.text_stream as text_stream

    lines = synthetic_log(np.random.default_rng(4), n_scans=25, n_beams=361)
    ref = list(CarmenReader(write_log(tmp_path / "a.clf", lines)).frames())
    monkeypatch.setattr(text_stream, "BLOCK_BYTES", 997)
    for comp in ("plain", "bz2"):
        got = list(CarmenReader(write_log(tmp_path / f"b.clf.{comp}", lines, comp)).frames())
        assert [g.source for g in got] == [r.source.replace("a.clf", f"b.clf.{comp}") for r in ref]
        for a, b in zip(ref, got):
            np.testing.assert_array_equal(a.ranges, b.ranges)


@pytest.mark.parametrize("block", [3000, 1 << 20])
def test_block_path_equals_line_parser(tmp_path, monkeypatch, block):
    """The block-vectorised FLASER path gives exactly the frames of the one-line parser, also for
    zero readings (dropped beams) and for blocks that mix beam counts (small blocks: uniform
    ones and mixed ones; one big block: mixed)."""
    import slam.logs.text_stream as text_stream

    monkeypatch.setattr(text_stream, "BLOCK_BYTES", block)
    rng = np.random.default_rng(8)
    lines = []
    for k in range(60):
        n = 181 if k < 30 or k % 7 else 90  # uniform blocks first, then mixed
        r = np.round(rng.uniform(0.05, 30.0, n), 2)
        r[rng.random(n) < 0.05] = 81.91
        if k % 5 == 0:
            r[rng.integers(0, n, 3)] = 0.0
        pose = tuple(rng.normal(0, 5, 3))
        lines.append(flaser(r, pose, pose, stamp=50.0 + k))
    p = write_log(tmp_path / "mix.clf", lines)
    reader = CarmenReader(p)
    frames = list(reader.frames())
    assert len(frames) == 60
    for k, f in enumerate(frames):
        ref = parse_laser_line(lines[k], path=str(p), lineno=k + 1, index=k, max_range=reader.flaser_max_range())
        assert (f.stamp, f.index, f.source, f.max_range) == (ref.stamp, ref.index, ref.source, ref.max_range)
        for a in ("angles", "ranges", "no_return", "points", "odom", "base_T_sensor"):
            np.testing.assert_array_equal(getattr(f, a), getattr(ref, a), err_msg=a)


def test_float_cache_is_bounded_and_exact():
    """The range-token cache returns exactly float(token) and never holds more than its limit."""
    from slam.logs.carmen_lines import FloatCache as _FloatCache

    c = _FloatCache(limit=4)
    toks = [f"{v:.2f}".encode() for v in np.random.default_rng(9).uniform(0, 80, 50)]
    assert [c[t] for t in toks] == [float(t) for t in toks]
    assert len(c) <= 4
    with pytest.raises(ValueError):
        c[b"two"]


def test_abandoned_stream_stops_its_thread():
    """Stopping early (close, or dropping the iterator) ends the background decompression thread."""
    import gc
    import threading

    before = threading.active_count()
    for _ in range(5):
        it = iter(CarmenReader(CSAIL).frames())
        next(it)
        del it
    it = CarmenReader(CSAIL).frames()
    next(it)
    it.close()
    gc.collect()
    assert threading.active_count() == before


def test_topic_choice(tmp_path):
    """Default topic is the front laser; RLASER/rear selects the rear one; ROBOTLASER1 when alone."""
    lines = [flaser([1.0, 2.0], stamp=1.0), flaser([3.0, 4.0, 5.0], stamp=1.5, tag="RLASER"), flaser([1.0, 2.0], stamp=2.0)]
    p = write_log(tmp_path / "two.clf", lines)
    assert [f.stamp for f in CarmenReader(p)] == [1.0, 2.0]
    assert [f.stamp for f in CarmenReader(p, "rear")] == [1.5]
    assert CarmenReader(p, "RLASER").info().sensor_topic == "RLASER"
    q = write_log(tmp_path / "rl.clf", [robotlaser([1.0, 2.0])])
    assert CarmenReader(q).sensor_topic == "ROBOTLASER1"


def test_info_counts_every_tag(tmp_path):
    """info(): one topic per message tag with its count, scans, beams, stamps, odometry."""
    lines = synthetic_log(np.random.default_rng(5), n_scans=12, n_beams=50)
    lines += ["SYNC tag 1.0 host 1.0", "NMEA-GGA 1 2 3 host 4"]
    inf = CarmenReader(write_log(tmp_path / "i.log", lines)).info()
    counts = {t.name: t.count for t in inf.topics}
    assert counts == {"PARAM": 1, "ODOM": 12, "FLASER": 12, "SYNC": 1, "NMEA-GGA": 1}
    assert inf.scans == 12 and inf.beams_per_scan == 50 and inf.dimension == 2 and inf.has_odometry
    assert inf.start == pytest.approx(100.05) and inf.end == pytest.approx(100.05 + 11 * 0.2)


# ----------------------------------------------------------------------------- bad input

BAD_LINES = {
    "garbage": ("\x00\x01binary junk", "garbage line"),
    "field_count": (flaser([1.0, 2.0, 3.0]).rsplit(" ", 2)[0], "needs 14 fields"),
    "non_numeric": (flaser([1.0, 2.0, 3.0]).replace(" 2.0 ", " two "), "non-numeric"),
    "nan_range": (flaser([1.0, float("nan"), 3.0]), "range 2 is nan"),
    "negative_range": (flaser([1.0, -2.0, 3.0]), "range 2 is -2.0"),
    "empty_scan": ("FLASER 0 0.0 0.0 0.0 0.0 0.0 0.0 5.0 host 0.1", "empty FLASER scan"),
    "bad_count": ("FLASER x 1.0 2.0", "num_readings"),
    "bad_stamp": (flaser([1.0]).replace("1000.5", "noon"), "ipc_timestamp"),
    "bad_odom": ("ODOM 1 2 3 4 5 six 7.0 host 8", "non-numeric ODOM"),
    "short_odom": ("ODOM 1 2 3", "ODOM needs 10 fields"),
    "robotlaser_count": (robotlaser([1.0, 2.0]).rsplit(" ", 4)[0], "needs 26 fields"),
    # Numbers follow the C locale grammar: Python's '1_000' digit groups are not numbers (issue 27).
    "underscore_range": (flaser([1.0, 2.0, 3.0]).replace(" 2.0 ", " 2_0.0 "), "'2_0.0'"),
    "underscore_count": (flaser([1.0] * 10).replace("FLASER 10 ", "FLASER 1_0 "), "'1_0'"),
    "underscore_pose": (flaser([1.0, 2.0, 3.0], robot=(1.0, 0.0, 0.0)).replace(" 1.0 0.0 0.0 1000.5", " 1_0.0 0.0 0.0 1000.5"), "'1_0.0'"),
    "underscore_odom": (odom_line(stamp=1_000.0).replace("1000.0", "1_000.0"), "'1_000.0'"),
    # Every stamp is finite, the logger's (last field) too.
    "nan_logger_stamp": (flaser([1.0, 2.0, 3.0]).replace("myhost 0.001", "myhost nan"), "logger_timestamp"),
    "inf_logger_stamp": (flaser([1.0, 2.0, 3.0]).replace("myhost 0.001", "myhost -inf"), "logger_timestamp"),
    "inf_odom_stamp": (odom_line(stamp=float("inf")), "ODOM"),
    "nan_odom_logger_stamp": (odom_line().rsplit(" ", 1)[0] + " nan", "ODOM"),
}


@pytest.mark.parametrize("case", sorted(BAD_LINES))
def test_bad_line_names_file_and_line(tmp_path, case):
    """Each malformed line raises LogFormatError naming the file and its line number; the good
    scans before it are still handed out."""
    bad, what = BAD_LINES[case]
    lines = [flaser([1.0, 2.0, 3.0], stamp=1.0), odom_line(), bad, flaser([1.0, 2.0, 3.0], stamp=2.0)]
    if case == "robotlaser_count":
        lines = [robotlaser([1.0, 2.0], stamp=1.0), bad]
    p = write_log(tmp_path / "bad.clf", lines)
    got = []
    with pytest.raises(LogFormatError) as ei:
        for f in CarmenReader(p).frames():
            got.append(f.stamp)
    assert ei.value.where == ("line 3" if case != "robotlaser_count" else "line 2")
    assert ei.value.path == str(p) and what in str(ei.value)
    assert got == [1.0]
    with pytest.raises(LogFormatError):
        CarmenReader(p).info()


def test_empty_file_has_no_scans(tmp_path):
    """An empty file, or one without any laser line, is an error: no scans."""
    for name, lines in (("empty.clf", None), ("odom_only.clf", [odom_line()] * 3)):
        p = tmp_path / name
        if lines is None:
            p.write_bytes(b"")
        else:
            write_log(p, lines)
        with pytest.raises(LogFormatError, match="no scans"):
            CarmenReader(p).info()
        with pytest.raises(LogFormatError, match="no scans"):
            list(CarmenReader(p))


def test_unknown_topic_and_missing_topic(tmp_path):
    """An unknown topic name is refused up front; a known but absent laser names what the log has."""
    p = write_log(tmp_path / "t.clf", [flaser([1.0, 2.0])])
    with pytest.raises(TopicNotFoundError, match="unknown CARMEN topic"):
        open_log(p, "/scan")
    with pytest.raises(TopicNotFoundError, match="FLASER ×1"):
        list(open_log(p, "ROBOTLASER1"))


def test_truncated_bz2_names_line_reached(tmp_path):
    """The Intel log cut in half: the frames before the cut are read, then an error naming the file
    and the line reached (not a bare EOFError)."""
    raw = INTEL.read_bytes()
    p = tmp_path / "intel_cut.clf.bz2"
    p.write_bytes(raw[: len(raw) // 2])
    n = 0
    with pytest.raises(LogFormatError) as ei:
        for _ in CarmenReader(p).frames():
            n += 1
    assert "truncated bz2" in str(ei.value) and "intel_cut.clf.bz2:line " in str(ei.value)
    line = int(ei.value.where.split()[1])
    assert 4000 < n < 13631 and line > 2 * n  # ~2 ODOM per FLASER


@pytest.mark.parametrize("comp", ["bz2", "gz"])
def test_corrupt_and_truncated_compressed(tmp_path, comp):
    """Flipped bytes inside, or a cut, of a bz2/gzip stream give LogFormatError with file and line."""
    lines = synthetic_log(np.random.default_rng(6), n_scans=200)
    good = write_log(tmp_path / f"g.clf.{comp}", lines, comp).read_bytes()
    cut = tmp_path / f"cut.clf.{comp}"
    cut.write_bytes(good[: len(good) * 2 // 3])
    bad = bytearray(good)
    mid = len(bad) // 2
    bad[mid:mid + 16] = bytes(b ^ 0x5A for b in bad[mid:mid + 16])
    corrupt = tmp_path / f"corrupt.clf.{comp}"
    corrupt.write_bytes(bytes(bad))
    for p in (cut, corrupt):
        with pytest.raises(LogFormatError) as ei:
            CarmenReader(p).info()
        assert ei.value.path == str(p) and ei.value.where.startswith("line ")


# ----------------------------------------------------------------------------- fuzzing

_TOKENS = st.one_of(
    st.sampled_from(["FLASER", "RLASER", "ROBOTLASER1", "ROBOTLASER2", "ODOM", "0", "1", "2", "3", "-1",
                     "nan", "inf", "-inf", "1e308", "1e999", "0x10", "1_0", "", "#", "host", "81.91", "\x00", "é"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-5, 400).map(str),
    st.text(max_size=6),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(tag=st.sampled_from(["FLASER", "RLASER", "ROBOTLASER1", "ROBOTLASER2", "ODOM", "XX", ""]),
       toks=st.lists(_TOKENS, max_size=40))
def test_fuzz_token_soup(tag, toks):
    """Random token soup: parse_laser_line returns a valid Frame or raises LogFormatError, nothing else."""
    line = " ".join([tag, *toks])
    try:
        f = parse_laser_line(line)
    except LogFormatError:
        return
    assert isinstance(f, Frame)
    assert f.points.shape[1] == 2 and len(f.points) == int((~f.no_return).sum())
    assert np.isfinite(f.points).all() and np.isfinite(f.stamp)


@settings(max_examples=150, deadline=None)
@given(
    ranges=st.lists(st.floats(0.001, 79.99), min_size=2, max_size=400),
    pose=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-3.1, 3.1)),
    offset=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-3.1, 3.1)),
    stamp=st.floats(0, 2e9),
)
def test_fuzz_valid_lines_round_trip(ranges, pose, offset, stamp):
    """Valid synthetic FLASER lines round-trip: ranges and stamp exactly, poses to rounding."""
    robot = geo.xytheta_to_matrix(*pose)
    laser = geo.matrix_to_xytheta(robot @ geo.xytheta_to_matrix(*offset))
    f = parse_laser_line(flaser(ranges, laser, pose, stamp=stamp))
    assert f.stamp == stamp
    np.testing.assert_array_equal(f.ranges, ranges)
    assert not f.no_return.any()
    np.testing.assert_allclose(f.base_T_sensor, geo.xytheta_to_matrix(*offset), atol=1e-6)
    np.testing.assert_allclose(geo.matrix_to_xytheta(f.odom)[:2], pose[:2])


@settings(max_examples=40, deadline=None)
@given(lines=st.lists(st.lists(_TOKENS, max_size=12).map(" ".join), max_size=8),
       comp=st.sampled_from(["plain", "bz2", "gz"]))
def test_fuzz_whole_file(lines, comp):
    """A file of random lines: the reader yields Frames and ends, or raises LogFormatError."""
    with tempfile.TemporaryDirectory() as d:
        p = write_log(Path(d) / f"f.clf.{comp}", lines, comp)
        try:
            for f in CarmenReader(p).frames():
                assert isinstance(f, Frame)
        except LogFormatError:
            pass
