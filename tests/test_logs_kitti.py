"""KITTI Velodyne reader: the 10 real frames of sequence 00, synthetic sequences with known numbers, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import geometry as geo
from core.errors import LogFormatError, TopicNotFoundError
from slam.logs import open_log
from slam.logs.kitti import KittiReader, read_velodyne_bin
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def seq00():
    return shared_path("kitti_odometry_00_sample", "sequences", "00")


@pytest.fixture(scope="module")
def frames00(seq00):
    return list(open_log(seq00))


def test_point_counts_are_file_size_over_16(seq00, frames00):
    """10 frames (000001…000010); each has size/16 points, float64 copies of the file's float32 x, y, z."""
    bins = sorted((seq00 / "velodyne").glob("*.bin"))
    assert len(frames00) == len(bins) == 10
    for f, b in zip(frames00, bins):
        assert f.points.shape == (b.stat().st_size // 16, 3)
        assert f.points.dtype == np.float64
        assert np.array_equal(f.points.astype(np.float32).astype(np.float64), f.points)  # exact float32 values
        assert f.source == b.name
    raw = np.fromfile(bins[0], dtype="<f4").reshape(-1, 4)
    assert np.array_equal(frames00[0].points, raw[:, :3].astype(np.float64))


def test_stamps_without_times_txt(frames00):
    """No times.txt: stamp = 0.1 s × frame number (the files start at 000001)."""
    np.testing.assert_allclose([f.stamp for f in frames00], 0.1 * np.arange(1, 11))


def test_ground_truth_is_in_the_velodyne_frame(frames00):
    """GT motion between consecutive frames runs straight along the Velodyne's +x (forward), with a
    near-identity rotation — in cam0 axes it would be along +z instead. (Only the axes: this folder's
    official poses are a constant-velocity placeholder over frames 0–14, so their lengths are not measured.)"""
    for a, b in zip(frames00, frames00[1:]):
        d = geo.relative(a.ground_truth, b.ground_truth)
        t = d[:3, 3]
        assert t[0] > 0.5
        assert abs(t[1]) < 0.1 and abs(t[2]) < 0.1
        assert np.degrees(np.linalg.norm(geo.so3_log(d[:3, :3]))) < 1.0
        assert geo.is_pose(b.ground_truth)


def test_conjugation_keeps_rotation_angle(seq00):
    """T_velo = Tr⁻¹·P·Tr is a similarity transform: every pose keeps its rotation angle, and pose 0
    (the cam0 origin, ≈ I) stays ≈ I."""
    from slam.logs.kitti import read_kitti_poses

    r = KittiReader(seq00)
    gt = r.ground_truth_velo()
    cam = read_kitti_poses(r.poses_path)
    assert len(gt) == 4541  # official length of sequence 00
    ang = lambda T: np.linalg.norm(geo.so3_log(geo.project_to_so3(T[:3, :3])))  # noqa: E731
    for k in (0, 1, 500, 2000, 4540):
        assert ang(gt[k]) == pytest.approx(ang(cam[k]), abs=1e-6)
    np.testing.assert_allclose(gt[0], np.eye(4), atol=1e-6)


def _median_nn(a: np.ndarray, b: np.ndarray, T: np.ndarray) -> float:
    """Median distance from the non-ground points of b (moved by T) to those of a."""
    def sel(p):
        r = np.linalg.norm(p[:, :2], axis=1)
        return p[(p[:, 2] > -1.3) & (r < 40.0)][::3]

    tree = cKDTree(sel(a))
    return float(np.median(tree.query(geo.transform_points(T, sel(b)))[0]))


def test_ground_truth_aligns_scans_better_than_identity(frames00):
    """Scan k+1 moved by the GT relative pose lies closer to scan k than without moving it."""
    for a, b in list(zip(frames00, frames00[1:]))[::3]:
        d = geo.relative(a.ground_truth, b.ground_truth)
        with_gt, ident = _median_nn(a.points, b.points, d), _median_nn(a.points, b.points, np.eye(4))
        assert with_gt < 0.75 * ident


def test_info(seq00):
    """info(): 10 scans, 3D, median points per scan from the file sizes, ground truth present."""
    inf = open_log(seq00).info()
    sizes = [b.stat().st_size // 16 for b in sorted((seq00 / "velodyne").glob("*.bin"))]
    assert (inf.format, inf.scans, inf.dimension, inf.sensor_topic) == ("kitti", 10, 3, "velodyne")
    assert inf.beams_per_scan == int(np.median(sizes))
    assert inf.has_ground_truth and not inf.has_odometry
    assert inf.duration_s == pytest.approx(0.9)


def test_single_bin_and_velodyne_folder(seq00):
    """A single .bin file or the velodyne/ folder itself open as KITTI, with the sequence's GT."""
    one = open_log(seq00 / "velodyne" / "000003.bin")
    (f,) = list(one)
    assert f.stamp == pytest.approx(0.3) and f.ground_truth is not None
    folder = list(open_log(seq00 / "velodyne"))
    assert len(folder) == 10
    np.testing.assert_array_equal(folder[2].ground_truth, f.ground_truth)


# ----------------------------------------------------------------------------- synthetic sequences

def _row(T: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in T[:3].ravel())


def _write_seq(root, rng, n=3, start=1, times=None, poses=None, Tr=None):
    seq = root / "sequences" / "07"
    (seq / "velodyne").mkdir(parents=True)
    clouds = []
    for k in range(start, start + n):
        pts = rng.normal(0, 10, (50 + k, 4)).astype("<f4")
        pts.tofile(seq / "velodyne" / f"{k:06d}.bin")
        clouds.append(pts)
    if Tr is not None:
        P = np.eye(4)
        (seq / "calib.txt").write_text("".join(f"P{i}: " + _row(P) + "\n" for i in range(4))
                                       + "Tr: " + _row(Tr) + "\n")
    if poses is not None:
        (root / "poses").mkdir()
        (root / "poses" / "07.txt").write_text("".join(_row(P) + "\n" for P in poses))
    if times is not None:
        (seq / "times.txt").write_text("".join(f"{float(t)!r}\n" for t in times))
    return seq, clouds


def test_synthetic_sequence_known_numbers(tmp_path, rng):
    """Known Tr, poses, times: GT = Tr⁻¹·P_k·Tr for line k = frame number, stamps from times.txt,
    reflectance kept apart on request."""
    Tr = geo.se3_exp(rng.normal(0, 0.5, 6))
    poses = geo.se3_exp(rng.normal(0, 1.0, (6, 6)))
    times = [0.0, 0.1037, 0.2071, 0.3102, 0.4133, 0.5168]
    seq, clouds = _write_seq(tmp_path, rng, n=3, start=2, times=times, poses=poses, Tr=Tr)
    frames = list(KittiReader(seq))
    for j, f in enumerate(frames):
        k = 2 + j
        assert f.stamp == times[k]
        np.testing.assert_allclose(f.ground_truth, geo.inverse(Tr) @ poses[k] @ Tr, atol=1e-9)
        np.testing.assert_array_equal(f.points, clouds[j][:, :3].astype(np.float64))
    pts, refl = read_velodyne_bin(seq / "velodyne" / "000002.bin", with_reflectance=True)
    np.testing.assert_array_equal(refl, clouds[0][:, 3].astype(np.float64))


@pytest.mark.parametrize("seq,first_m,last_m,total_yaw_deg,yaw_tol_deg",
                         [("00", 0.67, 0.81, 0.0, 3.0), ("01", 1.0, 1.0, -23.7, 0.5)])
def test_semantic_kitti_poses_are_read_from_the_sequence(seq, first_m, last_m, total_yaw_deg, yaw_tol_deg):
    """kitti_mini (SemanticKITTI layout: sequences/NN/poses.txt): ground truth is read from there, and its
    motion is the one its SOURCE.md measured — 00 accelerating from 0.67 to 0.81 m a frame, nearly straight,
    01 about 1 m a frame through 23.7° of a right-hand curve."""
    r = KittiReader(shared_path("kitti_mini", "sequences", seq))
    assert r.poses_path == r.sequence_dir / "poses.txt" and r.info().has_ground_truth
    gt = np.array([f.ground_truth for f in r.frames()])
    steps = [geo.relative(a, b) for a, b in zip(gt, gt[1:])]
    length = [float(np.linalg.norm(d[:3, 3])) for d in steps]
    assert length[0] == pytest.approx(first_m, abs=0.05) and length[-1] == pytest.approx(last_m, abs=0.05)
    assert all(d[0, 3] > 0.5 for d in steps)  # forward, in the Velodyne frame
    yaw = np.degrees(geo.matrix_to_xytheta(geo.relative(gt[0], gt[-1]))[2])
    assert yaw == pytest.approx(total_yaw_deg, abs=yaw_tol_deg)


def test_sequence_poses_take_precedence_over_the_devkit_poses(tmp_path, rng):
    """With both poses/NN.txt and sequences/NN/poses.txt, the sequence's own (SemanticKITTI) file is used."""
    Tr = np.eye(4)
    official = np.tile(np.eye(4), (3, 1, 1))
    seq, _ = _write_seq(tmp_path, rng, n=3, start=0, poses=official, Tr=Tr)
    semantic = geo.se3_exp(rng.normal(0, 1.0, (3, 6)))
    (seq / "poses.txt").write_text("".join(_row(P) + "\n" for P in semantic))
    frames = list(KittiReader(seq))
    for k, f in enumerate(frames):
        np.testing.assert_allclose(f.ground_truth, semantic[k], atol=1e-9)


def test_no_poses_means_no_ground_truth(tmp_path, rng):
    """Without poses/NN.txt (or calib.txt) frames carry no ground truth and info says so."""
    seq, _ = _write_seq(tmp_path, rng, n=2)
    assert all(f.ground_truth is None for f in KittiReader(seq))
    assert not KittiReader(seq).info().has_ground_truth


def test_truncated_bin_is_named(tmp_path, rng):
    """A .bin whose size is not a multiple of 16 raises LogFormatError naming that file."""
    seq, _ = _write_seq(tmp_path, rng, n=3)
    bad = seq / "velodyne" / "000002.bin"
    bad.write_bytes(bad.read_bytes()[:-6])
    with pytest.raises(LogFormatError, match="000002.bin.*not a multiple of 16"):
        list(KittiReader(seq))
    with pytest.raises(LogFormatError, match="000002.bin"):
        KittiReader(seq).info()


def test_short_poses_file_and_bad_topic(tmp_path, rng):
    """A poses file with fewer lines than frames is an error naming it; a topic other than velodyne too."""
    seq, _ = _write_seq(tmp_path, rng, n=3, poses=np.tile(np.eye(4), (2, 1, 1)), Tr=np.eye(4))
    with pytest.raises(LogFormatError, match="07.txt.*has 2 poses, frame 2"):
        list(KittiReader(seq))
    with pytest.raises(TopicNotFoundError):
        KittiReader(seq, "/scan")
    it = iter(KittiReader(seq, "velodyne"))
    assert next(it).index == 0  # frame 000001 has its pose line; frame 000002 does not
    with pytest.raises(LogFormatError):
        next(it)


def test_empty_sequence(tmp_path):
    """A velodyne/ folder without scans is an error: no scans."""
    (tmp_path / "s" / "velodyne").mkdir(parents=True)
    with pytest.raises(LogFormatError, match="no scans"):
        KittiReader(tmp_path / "s")
