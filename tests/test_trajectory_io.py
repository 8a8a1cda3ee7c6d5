"""Trajectory files: exact round trips, evo can read our TUM output, malformed lines name file and line."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from core import pose_formats
from core.errors import LogFormatError
from core.trajectory import Trajectory, read_g2o_vertices, read_kitti, read_tum, write_kitti, write_tum
import core.trajectory as tio
from slam.trajectory_io import read_trajectory


def _random_traj(rng, n=50) -> Trajectory:
    poses = geo.se3_exp(rng.normal(0, [5, 5, 5, 1, 1, 1], (n, 6)))
    stamps = 1.6e9 + np.cumsum(rng.uniform(0.01, 0.2, n))  # realistic epoch stamps: 19 significant digits matter
    return Trajectory(stamps, poses, "t")


def test_tum_round_trip_is_exact(tmp_path, rng):
    """write_tum → read_tum returns bit-identical stamps and translations, rotations to 1e-15."""
    t = _random_traj(rng)
    write_tum(tmp_path / "a.tum", t)
    r = read_tum(tmp_path / "a.tum")
    assert np.array_equal(r.stamps, t.stamps)
    assert np.array_equal(r.positions, t.positions)
    np.testing.assert_allclose(r.poses[:, :3, :3], t.poses[:, :3, :3], atol=1e-15)


def test_tum_is_readable_by_evo(tmp_path, rng):
    """evo's own TUM reader yields the same stamps and poses as we wrote (evo compatibility)."""
    fi = pytest.importorskip("evo.tools.file_interface")
    t = _random_traj(rng)
    write_tum(tmp_path / "a.tum", t)
    e = fi.read_tum_trajectory_file(str(tmp_path / "a.tum"))
    assert np.array_equal(e.timestamps, t.stamps)
    np.testing.assert_allclose(np.array(e.poses_se3), t.poses, atol=1e-14)


def test_kitti_round_trip_is_bit_exact(tmp_path, rng):
    """write_kitti → read_kitti returns bit-identical 3×4 blocks; stamps default to 0..N-1 or come from times.txt."""
    t = _random_traj(rng)
    write_kitti(tmp_path / "p.txt", t)
    r = read_kitti(tmp_path / "p.txt")
    assert np.array_equal(r.poses, t.poses)
    assert np.array_equal(r.stamps, np.arange(len(t)))
    (tmp_path / "times.txt").write_text("".join(f"{float(s)!r}\n" for s in t.stamps))
    assert np.array_equal(read_kitti(tmp_path / "p.txt", tmp_path / "times.txt").stamps, t.stamps)


def test_g2o_vertices_se2_and_se3(tmp_path):
    """VERTEX_SE2 (x, y, θ) and VERTEX_SE3:QUAT lines give the poses they encode, sorted by id; edges are ignored."""
    (tmp_path / "a.g2o").write_text(
        "VERTEX_SE2 2 1.0 2.0 0.5\nVERTEX_SE2 0 0 0 0\nEDGE_SE2 0 2 1 2 0.5 1 0 0 1 0 1\nFIX 0\n"
    )
    t = read_g2o_vertices(tmp_path / "a.g2o")
    assert t.stamps.tolist() == [0.0, 2.0]
    np.testing.assert_allclose(t.poses[1], geo.xytheta_to_matrix(1.0, 2.0, 0.5), atol=1e-15)
    s = np.sin(0.25)
    (tmp_path / "b.g2o").write_text(f"VERTEX_SE3:QUAT 0 1 2 3 0 0 {float(s)!r} {float(np.cos(0.25))!r}\n")
    (tmp_path / "b.stamps").write_text("0 12.5\n")
    t3 = read_g2o_vertices(tmp_path / "b.g2o", tmp_path / "b.stamps")
    assert t3.stamps.tolist() == [12.5]
    np.testing.assert_allclose(t3.poses[0][:3, :3], geo.rotz(0.5), atol=1e-15)
    np.testing.assert_allclose(t3.poses[0][:3, 3], [1, 2, 3])
    assert read_trajectory(tmp_path / "a.g2o").stamps.tolist() == [0.0, 2.0]


@pytest.mark.parametrize(
    "reader,text,line",
    [(read_tum, "# c\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", "line 3"),
     (read_tum, "1 0 0 0 0 0 0 1\n2 0 0 x 0 0 0 1\n", "line 2"),
     (read_tum, "1 0 0 0 0 0 0 0\n", "line 1"),
     (read_kitti, "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n", "line 2"),
     (read_g2o_vertices, "VERTEX_SE2 0 0 0\n", "line 1")],
)
def test_malformed_line_names_file_and_line(tmp_path, reader, text, line):
    """A malformed line raises LogFormatError whose message names the file and the line number."""
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(LogFormatError) as ei:
        reader(p)
    assert ei.value.where == line and "bad.txt" in str(ei.value)


def test_failed_write_leaves_no_file(tmp_path, rng, monkeypatch):
    """An exception during writing leaves neither the target nor a temporary file behind (atomic write)."""
    def boom(values):
        raise RuntimeError("disk full")

    monkeypatch.setattr(tio, "_fmt", boom)
    with pytest.raises(RuntimeError):
        write_tum(tmp_path / "x.tum", _random_traj(rng))
    assert list(tmp_path.iterdir()) == []


def test_trajectory_from_log_odometry_and_missing_ground_truth():
    """A CARMEN log yields its per-scan wheel odometry as a trajectory (one pose per scan, increasing stamps);
    asking it for ground truth it does not have is a LogFormatError naming the file."""
    pytest.importorskip("slam.logs.carmen")
    from tests.conftest import DATA, shared_path

    log = DATA / "mit-csail.clf.bz2"
    if not log.exists():
        log = shared_path("slam2d_kummerle_benchmark", "mit-csail.clf.bz2")
    t = read_trajectory(log, "log_odom")
    assert len(t) == 1988 and np.all(np.diff(t.stamps) > 0) and t.is_planar()
    with pytest.raises(LogFormatError) as ei:
        read_trajectory(log)  # auto: a log suffix means its ground truth
    assert "mit-csail" in str(ei.value) and "ground_truth" in str(ei.value)


def _shuffled_stamps(rng, n=60) -> Trajectory:
    """A trajectory whose stamps step back now and then (as the Intel log's scan stamps do, 631 times)."""
    t = _random_traj(rng, n)
    stamps = t.stamps.copy()
    k = rng.choice(np.arange(1, n), 8, replace=False)
    stamps[k] = stamps[k - 1] - rng.uniform(0.001, 0.005, 8)
    return Trajectory(stamps, t.poses, "t")


def test_every_reader_returns_poses_in_stamp_order_whatever_the_line_order(tmp_path, rng):
    """TUM, KITTI with times.txt and g2o vertices with a stamp file: reading the lines in any order gives the
    same trajectory, sorted by stamp (issue 27: eval rpe depended on the line order of the reference)."""
    t = _shuffled_stamps(rng)
    perm = rng.permutation(len(t))
    want_order = np.argsort(t.stamps, kind="stable")
    for order, name in ((np.arange(len(t)), "a"), (perm, "b")):
        write_tum(tmp_path / f"{name}.tum", t.subset(order))
        write_kitti(tmp_path / f"{name}.kitti", t.subset(order))
        (tmp_path / f"{name}_times.txt").write_text("".join(f"{float(s)!r}\n" for s in t.stamps[order]))
        (tmp_path / f"{name}.g2o").write_text("".join(
            f"VERTEX_SE3:QUAT {k} {' '.join(repr(float(v)) for v in np.concatenate(pose_formats.pose_to_quat(T)))}\n"
            for k, T in zip(order, t.poses[order])))
        (tmp_path / f"{name}_ids.txt").write_text("".join(f"{k} {float(s)!r}\n" for k, s in zip(order, t.stamps[order])))
    for a, b in ((read_tum(tmp_path / "a.tum"), read_tum(tmp_path / "b.tum")),
                 (read_kitti(tmp_path / "a.kitti", tmp_path / "a_times.txt"),
                  read_kitti(tmp_path / "b.kitti", tmp_path / "b_times.txt")),
                 (read_g2o_vertices(tmp_path / "a.g2o", tmp_path / "a_ids.txt"),
                  read_g2o_vertices(tmp_path / "b.g2o", tmp_path / "b_ids.txt"))):
        np.testing.assert_array_equal(a.stamps, t.stamps[want_order])
        np.testing.assert_array_equal(a.stamps, b.stamps)
        np.testing.assert_array_equal(a.poses, b.poses)
        np.testing.assert_allclose(a.positions, t.positions[want_order], atol=1e-12)


def test_rpe_does_not_depend_on_the_line_order(tmp_path, rng, capsys):
    """`slam eval rpe` prints the same numbers for a reference whose lines are shuffled."""
    from slam.cli import main

    t = _shuffled_stamps(rng)
    est = Trajectory(t.stamps, t.poses @ geo.se3_exp(rng.normal(0, 0.01, (len(t), 6))), "e")
    write_tum(tmp_path / "est.tum", est)
    write_tum(tmp_path / "ref.tum", t)
    write_tum(tmp_path / "shuf.tum", t.subset(rng.permutation(len(t))))
    outs = []
    for ref in ("ref.tum", "shuf.tum"):
        with pytest.raises(SystemExit) as ei:
            main(["eval", "rpe", str(tmp_path / "est.tum"), str(tmp_path / ref)])
        assert (ei.value.code or 0) == 0
        outs.append(capsys.readouterr().out)
    assert outs[0] == outs[1] and "pairs: 59" in outs[0]
