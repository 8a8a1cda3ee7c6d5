"""``open_log`` / ``detect_format``: the right reader for CARMEN and KITTI inputs, by name and by content."""

from __future__ import annotations

import bz2
import gzip

import numpy as np
import pytest

from core.errors import LogFormatError, TopicNotFoundError
from slam.logs import LogReader, detect_format, open_log
from slam.logs.carmen import CarmenReader
from slam.logs.kitti import KittiReader
from tests.conftest import DATA
from tests.test_logs_carmen import flaser

LINE = (flaser([1.0, 2.0, 3.0]) + "\n").encode()


_COMPRESS = {"plain": lambda b: b, "bz2": bz2.compress, "gz": lambda b: gzip.compress(b, mtime=0)}


# (parameters are plain strings: xdist workers must collect identical test ids)
@pytest.mark.parametrize("name, comp", [
    ("a.clf", "plain"), ("a.log", "plain"), ("a.carmen", "plain"), ("a.txt", "plain"),
    ("a.clf.bz2", "bz2"), ("a.log.gz", "gz"), ("no_suffix_bz2", "bz2"), ("no_suffix_gz", "gz"),
])
def test_carmen_by_name_or_magic(tmp_path, name, comp):
    """CARMEN logs are recognised by suffix, or by the bz2/gzip magic bytes whatever the name,
    and every such file reads back the same one scan."""
    p = tmp_path / name
    p.write_bytes(_COMPRESS[comp](LINE))
    assert detect_format(p) == "carmen"
    r = open_log(p)
    assert isinstance(r, CarmenReader) and isinstance(r, LogReader)
    (f,) = list(r)
    np.testing.assert_array_equal(f.ranges, [1.0, 2.0, 3.0])


def test_bundled_logs_are_carmen():
    """The bundled data/*.clf.bz2 logs open as CARMEN with the FLASER topic."""
    for name in ("intel.clf.bz2", "mit-csail.clf.bz2"):
        r = open_log(DATA / name)
        assert r.format == "carmen" and r.sensor_topic == "FLASER"


def test_kitti_inputs(tmp_path):
    """A sequence folder (velodyne/), the velodyne folder, a folder of .bin files and one .bin are KITTI."""
    seq = tmp_path / "sequences" / "03"
    (seq / "velodyne").mkdir(parents=True)
    np.zeros((5, 4), "<f4").tofile(seq / "velodyne" / "000000.bin")
    for p in (seq, seq / "velodyne", seq / "velodyne" / "000000.bin"):
        assert detect_format(p) == "kitti"
        r = open_log(p)
        assert isinstance(r, KittiReader)
        assert [f.points.shape for f in r] == [(5, 3)]


def test_topic_is_passed_through(tmp_path):
    """open_log(path, topic) hands the topic to the reader: an unknown one is refused at once."""
    p = tmp_path / "a.clf"
    p.write_bytes(LINE)
    assert open_log(p, "FLASER").sensor_topic == "FLASER"
    with pytest.raises(TopicNotFoundError):
        open_log(p, "/points")
    seq = tmp_path / "s"
    (seq / "velodyne").mkdir(parents=True)
    np.zeros((1, 4), "<f4").tofile(seq / "velodyne" / "000000.bin")
    with pytest.raises(TopicNotFoundError):
        open_log(seq, "FLASER")


def test_unknown_and_missing(tmp_path):
    """A missing path, an unknown suffix without magic bytes, and a folder that is no KITTI
    sequence raise LogFormatError naming the path."""
    odd = tmp_path / "notes.xyz"
    odd.write_text("hello")
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    for p in (tmp_path / "missing.clf", odd, empty_dir):
        with pytest.raises(LogFormatError) as ei:
            open_log(p)
        assert str(p) in str(ei.value)


def test_the_scan_count_hint_is_the_number_of_frames_where_an_index_tells_it(tmp_path):
    """A progress bar's total without a second pass: an MCAP's summary, a ROS 1 bag's connection index and a
    KITTI folder's files give the exact number of frames the reader yields; a CARMEN text log has no index."""
    from evaluation.sim import LASER_PRESETS, load_world, simulate
    from slam.logs.mcap_writer import write_cloud_log
    from slam.logs.simulated import write_simulated_log
    from tests.conftest import shared_path

    sim = simulate(load_world("corridor"), n_scans=40, spec=LASER_PRESETS["sick_lms"], seed=2)
    write_simulated_log(sim, tmp_path / "sim.mcap")
    seq = shared_path("kitti_mini", "sequences", "07")
    write_cloud_log(tmp_path / "kitti.mcap", open_log(seq).frames())
    for path in (tmp_path / "sim.mcap", seq, tmp_path / "kitti.mcap"):
        r = open_log(path)
        assert r.scan_count_hint() == len(list(r.frames())) > 0, path
    assert open_log(DATA / "intel.clf.bz2").scan_count_hint() is None


def test_slam_run_reads_the_log_once(tmp_path, monkeypatch):
    """``slam run`` with its progress bar takes the total from the index, never from a summarising pass."""
    from evaluation.sim import LASER_PRESETS, load_world, simulate
    from slam.cli import main
    from slam.logs.mcap_reader import McapReader
    from slam.logs.simulated import write_simulated_log

    sim = simulate(load_world("corridor"), n_scans=60, spec=LASER_PRESETS["sick_lms"], seed=2)
    write_simulated_log(sim, tmp_path / "sim.mcap")

    def no_second_pass(self):  # type: ignore[no-untyped-def]
        raise AssertionError("info() read the log a second time")

    monkeypatch.setattr(McapReader, "info", no_second_pass)
    with pytest.raises(SystemExit) as exc:
        main(["run", str(tmp_path / "sim.mcap"), "--out", str(tmp_path / "run"),
              "--config", str(_inline_config(tmp_path))])
    assert exc.value.code in (0, None)
    assert (tmp_path / "run" / "trajectory.tum").exists()


def _inline_config(tmp_path):  # type: ignore[no-untyped-def]
    """Stages in this process (the patched reader must be the one that runs), no map (faster)."""
    p = tmp_path / "inline.yaml"
    p.write_text("stage_processes: false\nmapping:\n  enabled: false\n")
    return p


def test_a_ros2_bag_folder_stored_as_one_mcap_file_reads_as_that_file(tmp_path, capsys):
    """A ROS 2 bag folder (``metadata.yaml`` beside its storage) stored as one MCAP file reads exactly as that
    file (`slam info` counts the same scans); a folder with neither storage file is refused in one line naming
    it — never mistaken for a KITTI folder. (SQLite storage: tests/test_logs_rosbag2.py.)"""
    from tests.cli_helpers import corridor_log, one_error_line, slam

    bag = tmp_path / "rosbag2_2026_11_28"
    bag.mkdir()
    corridor_log(bag / "rosbag2_2026_11_28_0.mcap", 30, seed=3)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: mcap\n")
    assert detect_format(bag) == "mcap"
    from_folder, from_file = list(open_log(bag)), list(open_log(bag / "rosbag2_2026_11_28_0.mcap"))
    assert len(from_folder) == len(from_file) == 30
    for a, b in zip(from_folder, from_file):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.odom, b.odom)
    code, out, _ = slam(["info", bag], capsys)
    assert code == 0 and "scans: 30" in out.splitlines()

    empty = tmp_path / "empty_bag"
    empty.mkdir()
    (empty / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: mcap\n")
    code, _, err = slam(["info", empty], capsys)
    one_error_line(code, err, empty, "without its .mcap or .db3 storage file")
